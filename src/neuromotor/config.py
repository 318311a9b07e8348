"""TOML configuration files, validated with messages that name the file and the field.

Simulation config (every table and key optional)::

    clip = "path/to/clip.bvh"      # default: the embedded clip; relative to the config file
    units = "auto"                 # auto | m | cm | mm | in | cmu | ft | metres per unit
    up_axis = "auto"               # auto (from the motion) | 0 | 1 | 2: gravity along -up
    stature = 1.75                 # m; default: estimated from the long bones
    body_mass = 70.0               # kg; default: BMI 22 at the stature
    sex = "average"                # de Leva's segment table: male | female | average
    simulate_extremities = false   # fingers, toes, face joints as simulated bodies

    [sim]
    h = 0.008333333333333333       # time step (s)
    start = 0.0                    # clip time of the first step (s)
    duration = 3.0                 # simulated seconds (default: to the clip's end)
    implicit = true                # linearly implicit step (false: K = D = 0)
    driven_joints = []             # joints driven along the mocap like the root
    stabilization_steps = 2        # Newton steps of post-stabilization per step (1..5): 2 reach
                                   # round-off; 1 (one projection, as Cline & Pai) is ~20 % faster
                                   # and leaves up to ~4e-8 m at the joints

    [gains]
    ks = 400.0                     # 1/s^2 (see neuromotor.physics.control for the scaling)
    kd = 20.0                      # 1/s
    tau_floor = 0.5                # fraction of each DOF's RMS feedforward torque

    [[perturbation]]               # any number of these
    kind = "force"                 # force | impulse
    body = "Chest2"                # a body (joint) name, or chest | pelvis | head | left_hand ...
    point = [0.0, 0.1, 0.0]        # body frame, m, from the joint origin (default: its COM)
    direction = [1.0, 0.0, 0.0]    # world
    magnitude = 150.0              # N (force) or N s (impulse)
    start = 1.0                    # s, clip time
    duration = 0.1                 # s (force only)
    shape = "half_sine"            # square | half_sine | triangle

    [ball]                         # a flying ball (see neuromotor.physics.contact); optional
    radius = 0.11                  # m
    mass = 0.45                    # kg
    position = [1.5, 1.3, 2.3]     # world centre at launch (m)
    speed = 12.0                   # m/s, with either target (a body to aim at) or direction,
    target = "Chest2"              #   or give velocity = [vx, vy, vz] instead of speed
    launch = 1.0                   # s, clip time of release
    restitution = 0.6              # Newton's coefficient, 0..1
    friction = 0.5                 # Coulomb coefficient
    restitution_threshold = 0.25   # m/s: slower impacts do not bounce
    friction_directions = 8        # sides of the friction pyramid (>= 4)
    max_contacts = 4               # nearest contact candidates solved per step
    pgs_iterations = 40            # projected Gauss-Seidel sweeps
    ground = true                  # the ball also hits the ground plane (up . x = ground_height)
    ground_height = 0.0
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import tomllib
from typing import Any

from neuromotor.model.anatomy import UNIT_CHOICES
from neuromotor.physics.control import DEFAULT_KD, DEFAULT_KS, DEFAULT_TAU_FLOOR


class ConfigError(ValueError):
    """Invalid configuration; the message names the file and the field."""


@dataclasses.dataclass
class SimulationConfig:
    clip: str | None = None
    units: str | float = "auto"
    up_axis: int | None = None  # None: from the motion
    stature: float | None = None
    body_mass: float | None = None
    sex: str = "average"
    simulate_extremities: bool = False
    h: float = 1.0 / 120.0
    start: float = 0.0
    duration: float | None = None
    implicit: bool = True
    driven_joints: list[str] = dataclasses.field(default_factory=list)
    stabilization_steps: int = 2
    ks: float = DEFAULT_KS
    kd: float = DEFAULT_KD
    tau_floor: float = DEFAULT_TAU_FLOOR
    perturbations: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    ball: dict[str, Any] | None = None
    source: str = "<defaults>"

    def mass_options(self):
        from neuromotor.model.skeleton import MassModelOptions

        return MassModelOptions(body_mass=self.body_mass, sex=self.sex,
                                simulate_extremities=self.simulate_extremities)


DEFAULT_HIT = {
    "kind": "force",
    "body": "chest",  # a segment keyword: Chest2 on the embedded clip, the same place on any rig
    "point": [0.0, 0.1, 0.0],
    "direction": [0.0, 0.0, 1.0],
    "magnitude": 400.0,
    "start": 1.0,
    "duration": 0.1,
    "shape": "half_sine",
}


def read_toml(path) -> dict:
    """The TOML table of a config file; an unreadable, binary, empty or comment-only file is a
    :class:`ConfigError` naming the file (an empty config would silently run the defaults)."""
    path = pathlib.Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config: {e.strerror}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a text (UTF-8 TOML) config: byte 0x{raw[e.start]:02x} at offset "
                          f"{e.start}") from None
    if "\x00" in text:
        raise ConfigError(f"{path}: not a text (TOML) config: NUL byte at offset {text.index(chr(0))}")
    if not text.strip():
        raise ConfigError(f"{path}: config is empty")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML: {e}") from None
    if not data:
        raise ConfigError(f"{path}: config has no settings (only comments)")
    return data


class _Fields:
    """Typed getters over one table that name the field on error and reject unknown keys."""

    def __init__(self, table: dict, where: str, source: str):
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: {where} must be a table")
        self.table, self.where, self.source, self.used = table, where, source, set()

    def _name(self, key):
        return f"{self.where}.{key}" if self.where else key

    def fail(self, key, msg):
        raise ConfigError(f"{self.source}: field '{self._name(key)}' {msg}")

    def get(self, key, default=None):
        self.used.add(key)
        return self.table.get(key, default)

    def number(self, key, default, *, positive=False, nonneg=False):
        val = self.get(key, default)
        if val is None:
            return None
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
            self.fail(key, f"must be a finite number, got {val!r}")
        if positive and not val > 0:
            self.fail(key, f"must be > 0, got {val!r}")
        if nonneg and val < 0:
            self.fail(key, f"must be >= 0, got {val!r}")
        return float(val)

    def vector(self, key, default):
        val = self.get(key, default)
        if (not isinstance(val, list) or len(val) != 3
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in val)):
            self.fail(key, f"must be a list of 3 numbers, got {val!r}")
        return [float(x) for x in val]

    def choice(self, key, default, options):
        val = self.get(key, default)
        if val not in options:
            self.fail(key, f"must be one of {list(options)}, got {val!r}")
        return val

    def boolean(self, key, default):
        val = self.get(key, default)
        if not isinstance(val, bool):
            self.fail(key, f"must be true or false, got {val!r}")
        return val

    def string_list(self, key, default):
        val = self.get(key, default)
        if not isinstance(val, list) or not all(isinstance(x, str) for x in val):
            self.fail(key, f"must be a list of strings, got {val!r}")
        return list(val)

    def done(self, allowed_tables=()):
        extra = set(self.table) - self.used - set(allowed_tables)
        if extra:
            self.fail(sorted(extra)[0], f"is not a known field (known: {sorted(self.used)})")


def parse_perturbation(table: dict, where: str, source: str) -> dict[str, Any]:
    f = _Fields(table, where, source)
    kind = f.choice("kind", "force", ("force", "impulse"))
    body = f.get("body")
    if not isinstance(body, str):
        f.fail("body", f"must be a body (joint) name, got {body!r}")
    out = {
        "kind": kind,
        "body": body,
        "point": f.vector("point", None) if "point" in table else None,
        "direction": f.vector("direction", [1.0, 0.0, 0.0]),
        "magnitude": f.number("magnitude", None, nonneg=True),
        "start": f.number("start", 1.0, nonneg=True),
        "duration": f.number("duration", 0.1, positive=True),
        "shape": f.choice("shape", "half_sine", ("square", "half_sine", "triangle")),
    }
    if out["magnitude"] is None:
        f.fail("magnitude", "is required")
    if not any(out["direction"]):
        f.fail("direction", "must be non-zero")
    f.done()
    return out


def parse_ball(table: dict, source: str) -> dict[str, Any]:
    """The ``[ball]`` table (see the module docstring); errors name the field."""
    f = _Fields(table, "ball", source)
    out = {
        "radius": f.number("radius", 0.11, positive=True),
        "mass": f.number("mass", 0.45, positive=True),
        "position": f.vector("position", None) if "position" in table else f.fail("position", "is required"),
        "launch": f.number("launch", 0.0, nonneg=True),
        "restitution": f.number("restitution", 0.6, nonneg=True),
        "friction": f.number("friction", 0.5, nonneg=True),
        "restitution_threshold": f.number("restitution_threshold", 0.25, nonneg=True),
        "ground_height": f.number("ground_height", 0.0),
        "ground": f.boolean("ground", True),
    }
    if out["restitution"] > 1.0:
        f.fail("restitution", f"must be in [0, 1], got {out['restitution']!r}")
    for key, default, low in (("friction_directions", 8, 4), ("max_contacts", 4, 1), ("pgs_iterations", 40, 1)):
        val = f.get(key, default)
        if isinstance(val, bool) or not isinstance(val, int) or val < low:
            f.fail(key, f"must be an integer >= {low}, got {val!r}")
        out[key] = val
    given = [k for k in ("velocity", "speed", "direction", "target") if k in table]
    if "velocity" in table:
        if len(given) > 1:
            f.fail("velocity", f"give either velocity or speed with direction/target, not {given}")
        out["velocity"] = f.vector("velocity", None)
    else:
        out["speed"] = f.number("speed", None, nonneg=True)
        if out["speed"] is None:
            f.fail("speed", "is required (or give velocity = [vx, vy, vz])")
        if ("direction" in table) == ("target" in table):
            f.fail("direction", "give exactly one of direction (a vector) or target (a body name)")
        if "direction" in table:
            out["direction"] = f.vector("direction", None)
            if not any(out["direction"]):
                f.fail("direction", "must be non-zero")
        else:
            target = f.get("target")
            if not isinstance(target, str):
                f.fail("target", f"must be a body (joint) name, got {target!r}")
            out["target"] = target
    f.done()
    return out


def simulation_config(data: dict, source: str = "<dict>", base_dir=None) -> SimulationConfig:
    top = _Fields(data, "", source)
    cfg = SimulationConfig(source=source)
    clip = top.get("clip")
    if clip is not None:
        if not isinstance(clip, str):
            top.fail("clip", f"must be a path string, got {clip!r}")
        p = pathlib.Path(clip)
        if base_dir is not None and not p.is_absolute():
            p = pathlib.Path(base_dir) / p
        cfg.clip = str(p)
    units = top.get("units", "auto")
    if not (units == "auto" or (isinstance(units, str) and units in UNIT_CHOICES)
            or (isinstance(units, (int, float)) and not isinstance(units, bool) and math.isfinite(units)
                and units > 0)):
        top.fail("units", f"must be auto, {', '.join(UNIT_CHOICES)} or a positive number of metres per "
                          f"file unit, got {units!r}")
    cfg.units = units
    up = top.choice("up_axis", "auto", ("auto", 0, 1, 2))
    cfg.up_axis = None if up == "auto" else int(up)
    cfg.stature = top.number("stature", None, positive=True)
    if cfg.stature is not None and not 0.3 <= cfg.stature <= 3.0:
        top.fail("stature", f"must be a stature in metres between 0.3 and 3, got {cfg.stature!r}")
    cfg.body_mass = top.number("body_mass", None, positive=True)
    cfg.sex = top.choice("sex", "average", ("average", "male", "female"))
    cfg.simulate_extremities = top.boolean("simulate_extremities", False)
    sim = _Fields(top.get("sim", {}), "sim", source)
    cfg.h = sim.number("h", cfg.h, positive=True)
    cfg.start = sim.number("start", 0.0, nonneg=True)
    cfg.duration = sim.number("duration", None, positive=True)
    cfg.implicit = sim.boolean("implicit", True)
    cfg.driven_joints = sim.string_list("driven_joints", [])
    steps = sim.get("stabilization_steps", cfg.stabilization_steps)
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 5:
        sim.fail("stabilization_steps", f"must be an integer from 1 to 5, got {steps!r}")
    cfg.stabilization_steps = steps
    sim.done()
    gains = _Fields(top.get("gains", {}), "gains", source)
    cfg.ks = gains.number("ks", DEFAULT_KS, nonneg=True)
    cfg.kd = gains.number("kd", DEFAULT_KD, nonneg=True)
    cfg.tau_floor = gains.number("tau_floor", DEFAULT_TAU_FLOOR, nonneg=True)
    gains.done()
    perts = top.get("perturbation", [])
    if not isinstance(perts, list):
        top.fail("perturbation", "must be an array of tables ([[perturbation]])")
    cfg.perturbations = [parse_perturbation(p, f"perturbation[{i}]", source) for i, p in enumerate(perts)]
    if "ball" in data:
        cfg.ball = parse_ball(top.get("ball"), source)
    top.done(allowed_tables=("fit", "sweep", "experiment", "ball"))
    return cfg


def load_simulation_config(path) -> SimulationConfig:
    path = pathlib.Path(path)
    return simulation_config(read_toml(path), str(path), path.parent)
