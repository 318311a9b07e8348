"""Every table of a config file, parsed in one place into the specs of :mod:`neuromotor.config.specs`.

Errors are :class:`~neuromotor.errors.ConfigError` naming the file and the field; unknown keys
are refused. Defaults come from the spec classes.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import numpy as np

from neuromotor.config.fields import Fields, read_toml, resolve
from neuromotor.config.specs import (
    BODY_TARGET_KINDS,
    CONTROLLERS,
    DEVIATION_METRICS,
    EXPERIMENT_KINDS,
    FEATURE_NAMES,
    FIT_SOLVERS,
    JACOBIANS,
    LENGTH_UNITS,
    PERTURBATION_KINDS,
    REFLEX_AXES,
    REFLEX_DELAY_LIMIT,
    REQUIRED,
    ROOT_MODES,
    SEXES,
    STEPPING_KEYS,
    TARGET_KINDS,
    TIME_UNITS,
    BalanceSpec,
    BallSpec,
    ExperimentSpec,
    FeatureTarget,
    FitSpec,
    FitTargetSpec,
    GainSetting,
    GroundSpec,
    PerturbationSpec,
    ReflexSpec,
    SimulationConfig,
    SolverOptions,
    Surrogate,
    SweepSpec,
    check_fit_parameters,
    default,
    reflex_grid,
)
from neuromotor.errors import ConfigError
from neuromotor.model.facing import DIRECTION_KEYWORDS
from neuromotor.physics.options import Feedforward, JointLaw
from neuromotor.physics.precision import Precision

# top-level tables beside [sim], [gains], [[perturbation]]
TABLES = ("fit", "sweep", "experiment", "ball", "reflex", "ground", "balance")


# ----------------------------------------------------------------------------- simulation


def parse_perturbation(table, where: str, source: str, base_dir=None) -> PerturbationSpec:
    """One ``[[perturbation]]`` table by its spec's fields and their rules
    (:class:`~neuromotor.config.specs.PerturbationSpec`): a field the kind does not read is an
    error naming it, a field the kind requires (:data:`~neuromotor.config.specs.REQUIRED`) too.
    A base motion is a pulse (magnitude, shape, duration) or a recorded series (``file``, read
    here: :func:`read_series`)."""
    f = Fields(table, where, source)
    kind = f.choice("kind", default(PerturbationSpec, "kind"), PERTURBATION_KINDS)
    values: dict = {"kind": kind}
    for field in dataclasses.fields(PerturbationSpec):
        name = field.name
        if name == "kind":
            continue
        if field.metadata["rule"] == "derived":  # a parsed spec's dict carries it: read again from file
            if name in table and "file" not in table:
                f.fail(name, "is read from the file field, not given")
            f.get(name)
            continue
        if not PerturbationSpec.reads(kind, name):
            if name in table:
                article = "an" if kind[0] in "aeiou" else "a"
                readers = [k for k in PERTURBATION_KINDS if PerturbationSpec.reads(k, name)]
                f.fail(name, f"does not apply to {article} {kind} (only kind = {' | '.join(readers)} reads it)")
            continue
        if name in REQUIRED[kind] and name not in table:
            f.fail(name, f"is required for kind = {kind!r}")
        values[name] = _perturbation_field(f, table, field, base_dir)
    if kind == "base":
        for name in ("tilt", "axis", "rotation"):  # a platform's tilt: not modelled
            if name in table:
                f.fail(
                    name,
                    'is not read by a base motion, which translates (along direction): a tilt is kind = "tilt"',
                )
        if values["file"] is None:
            for name in ("time_unit",):
                if name in table:
                    f.fail(name, "applies to a recorded base motion only (give file)")
            if "magnitude" not in table:
                f.fail("magnitude", "is required for a base pulse (or give file, a recorded acceleration)")
        else:
            for name in ("shape", "duration"):
                if name in table:
                    f.fail(name, "does not apply to a recorded base motion (file gives the samples)")
            values["record"] = read_series(values["file"], f.name("file"), source, values["time_unit"])
            values["file"] = str(values["file"])
    f.done()
    return PerturbationSpec(**values)


def read_series(path: pathlib.Path, field: str, source: str, time_unit: str) -> tuple[tuple, tuple]:
    """A recorded series from CSV: a header naming ``time`` and one value column (``#`` lines are
    comments), then rows of numbers with strictly increasing times. Times in ``time_unit``,
    returned in seconds; every error names the file, the line and the config field."""
    import csv

    where = f"{source}: field '{field}' = {str(path)!r}"
    try:
        text = pathlib.Path(path).read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{where}: cannot read: {getattr(e, 'strerror', None) or e}") from None
    rows = [(n + 1, r) for n, r in enumerate(csv.reader(text.splitlines())) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise ConfigError(f"{where}: no header row (time and an acceleration column)")
    line, header = rows[0]
    header = [h.strip() for h in header]
    if "time" not in header:
        raise ConfigError(f"{where}: line {line}: no 'time' column in the header {header}")
    if len(header) != 2:
        raise ConfigError(
            f"{where}: line {line}: the header must name 'time' and one acceleration column, got {header}"
        )
    it = header.index("time")
    times: list[float] = []
    values: list[float] = []
    for n, r in rows[1:]:
        if len(r) != 2:
            raise ConfigError(f"{where}: line {n}: expected 2 values, got {len(r)}")
        try:
            t, a = float(r[it]), float(r[1 - it])
        except ValueError:
            raise ConfigError(f"{where}: line {n}: not a number: {r}") from None
        if not (math.isfinite(t) and math.isfinite(a)):
            raise ConfigError(f"{where}: line {n}: not finite: {r}")
        if times and t <= times[-1]:
            raise ConfigError(
                f"{where}: line {n}: time {r[it].strip()} is not after the previous row's (times must increase)"
            )
        times.append(t)
        values.append(a)
    if len(times) < 2:
        raise ConfigError(f"{where}: needs at least 2 rows of samples, got {len(times)}")
    scale = TIME_UNITS[time_unit]
    return tuple(t * scale for t in times), tuple(values)


def _perturbation_field(f: Fields, table, field: dataclasses.Field, base_dir=None):
    """One field of a perturbation table by its rule (``field.metadata``)."""
    name, rule = field.name, field.metadata["rule"]
    fallback = default(PerturbationSpec, name)
    if rule == "body":
        value = f.get(name)
        if not isinstance(value, str) or not value:
            f.fail(name, f"must be a body (joint) name, got {value!r}")
        return value
    if rule == "file":
        return f.path(name, None, base_dir, "a CSV path") if name in table else None
    if rule == "vector":
        return f.vector(name, None) if f.get(name) is not None else fallback
    if rule == "direction":
        return f.direction(name, fallback)
    if rule == "choice":
        return f.choice(name, fallback, field.metadata["choices"])
    return f.number(name, fallback, nonneg=rule == "nonneg", positive=rule == "positive")


def _ball_velocity(f: Fields, table: dict) -> dict:
    """velocity, or speed with exactly one of direction / target."""
    given = [k for k in ("velocity", "speed", "direction", "target") if k in table]
    if "velocity" in table:
        if len(given) > 1:
            f.fail("velocity", f"give either velocity or speed with direction/target, not {given}")
        return {"velocity": f.vector("velocity", None)}
    out = {
        "speed": f.required(
            "speed", f.number("speed", None, nonneg=True), "is required (or give velocity = [vx, vy, vz])"
        )
    }
    if ("direction" in table) == ("target" in table):
        f.fail("direction", "give exactly one of direction (a vector) or target (a body name)")
    if "direction" in table:
        out["direction"] = f.direction("direction", None)
    else:
        target = f.get("target")
        if not isinstance(target, str):
            f.fail("target", f"must be a body (joint) name, got {target!r}")
        out["target"] = target
    return out


def parse_ball(table, source: str) -> BallSpec:
    """The ``[ball]`` table; errors name the field."""
    f = Fields(table, "ball", source)
    d = lambda name: default(BallSpec, name)
    if "position" not in table:
        f.fail("position", "is required")
    out = {"position": f.vector("position", None)}
    for key, rule in (
        ("radius", "positive"),
        ("mass", "positive"),
        ("launch", "nonneg"),
        ("restitution", "nonneg"),
        ("friction", "nonneg"),
        ("restitution_threshold", "nonneg"),
        ("ground_height", None),
    ):
        out[key] = f.number(key, d(key), **({rule: True} if rule else {}))
    out["ground"] = f.boolean("ground", d("ground"))
    if out["restitution"] > 1.0:
        f.fail("restitution", f"must be in [0, 1], got {out['restitution']!r}")
    for key, low in (("friction_directions", 4), ("max_contacts", 1), ("pgs_iterations", 1)):
        out[key] = f.integer(key, d(key), low)
    out.update(_ball_velocity(f, table))
    f.done()
    return BallSpec(**out)


def _body_fields(top: Fields, base_dir) -> dict:
    """Top-level keys: the clip and the body model."""
    from neuromotor.model.anatomy import UNIT_CHOICES

    clip = top.path("clip", None, base_dir)
    units = top.get("units", "auto")
    if not (
        units == "auto"
        or (isinstance(units, str) and units in UNIT_CHOICES)
        or (isinstance(units, (int, float)) and not isinstance(units, bool) and math.isfinite(units) and units > 0)
    ):
        top.fail(
            "units",
            f"must be auto, {', '.join(UNIT_CHOICES)} or a positive number of metres per file unit, got {units!r}",
        )
    up = top.choice("up_axis", "auto", ("auto", 0, 1, 2))
    stature = top.number("stature", None, positive=True)
    if stature is not None and not 0.3 <= stature <= 3.0:
        top.fail("stature", f"must be a stature in metres between 0.3 and 3, got {stature!r}")
    return dict(
        clip=None if clip is None else str(clip),
        units=units,
        up_axis=None if up == "auto" else int(up),
        stature=stature,
        body_mass=top.number("body_mass", None, positive=True),
        sex=top.choice("sex", default(SimulationConfig, "sex"), SEXES),
        simulate_extremities=top.boolean("simulate_extremities", False),
    )


def _sim_fields(top: Fields) -> dict:
    """The ``[sim]`` and ``[gains]`` tables."""
    d = lambda name: default(SimulationConfig, name)
    sim = top.sub("sim")
    out = dict(
        h=sim.number("h", d("h"), positive=True),
        start=sim.number("start", d("start"), nonneg=True),
        duration=sim.number("duration", None, positive=True),
        still=sim.number("still", None, nonneg=True),
        implicit=sim.boolean("implicit", d("implicit")),
        driven_joints=sim.string_list("driven_joints", []),
    )
    steps = sim.get("stabilization_steps", d("stabilization_steps"))
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 5:
        sim.fail("stabilization_steps", f"must be an integer from 1 to 5, got {steps!r}")
    out["stabilization_steps"] = steps
    out["dtype"] = Precision(sim.choice("dtype", d("dtype").value, [p.value for p in Precision]))
    out["feedforward"] = Feedforward(sim.choice("feedforward", d("feedforward").value, [f.value for f in Feedforward]))
    out["joint_law"] = JointLaw(sim.choice("joint_law", d("joint_law").value, [f.value for f in JointLaw]))
    out["metric"] = sim.choice("metric", d("metric"), DEVIATION_METRICS)
    out["root"] = sim.choice("root", d("root"), ROOT_MODES)
    sim.done()
    gains = top.sub("gains")
    for key in ("ks", "kd", "tau_floor"):
        out[key] = gains.number(key, d(key), nonneg=True)
    gains.done()
    return out


def parse_ground(top: Fields) -> GroundSpec:
    """The ``[ground]`` table (defaults: :class:`GroundSpec`); errors name the field."""
    f = top.sub("ground")
    d = lambda name: default(GroundSpec, name)
    enabled = None if f.get("enabled") is None else f.boolean("enabled", None)
    friction = f.number("friction", d("friction"), nonneg=True)
    restitution = f.number("restitution", d("restitution"), nonneg=True)
    if restitution > 1.0:
        f.fail("restitution", f"must be in [0, 1], got {restitution!r}")
    spec = GroundSpec(
        enabled=enabled,
        height=f.number("height", None),
        friction=friction,
        restitution=restitution,
        contacts_per_body=f.integer("contacts_per_body", d("contacts_per_body"), 1),
        max_contacts=f.integer("max_contacts", d("max_contacts"), 1),
        pgs_iterations=None if f.get("pgs_iterations") is None else f.integer("pgs_iterations", None, 1),
    )
    f.done()
    return spec


def parse_balance(top: Fields) -> BalanceSpec:
    """The ``[balance]`` table (defaults: :class:`BalanceSpec`); errors name the field."""
    f = top.sub("balance")
    d = lambda name: default(BalanceSpec, name)
    enabled = None if f.get("enabled") is None else f.boolean("enabled", None)
    out = {k: f.number(k, d(k), nonneg=True) for k in ("kp", "kd", "hip_kp", "hip_kd", "delay", "assist")}
    if f.get("max_delay") is None and out["delay"] > REFLEX_DELAY_LIMIT:
        f.fail("delay", f"must be at most {REFLEX_DELAY_LIMIT:g} s (the history buffer), got {out['delay']!r}")
    out["max_delay"] = f.number("max_delay", max(d("max_delay"), out["delay"]), positive=True)
    if out["max_delay"] > REFLEX_DELAY_LIMIT:
        f.fail("max_delay", f"must be at most {REFLEX_DELAY_LIMIT:g} s (the history buffer), got {out['max_delay']!r}")
    if out["delay"] > out["max_delay"]:
        f.fail("delay", f"= {out['delay']:g} s is longer than balance.max_delay = {out['max_delay']:g} s")
    out["stepping"] = f.boolean("stepping", d("stepping"))
    zero_ok = ("step_margin", "step_offset", "step_lift", "shift_fraction", "step_crouch")
    for k in STEPPING_KEYS:
        out[k] = f.number(k, d(k), nonneg=k in zero_ok, positive=k not in zero_ok)
    f.done()
    return BalanceSpec(enabled=enabled, **out)


def parse_reflex(top: Fields) -> ReflexSpec:
    """The ``[reflex]`` table (defaults: :class:`ReflexSpec`)."""
    f = top.sub("reflex")
    d = lambda name: default(ReflexSpec, name)
    out = {
        k: f.number(k, d(k), nonneg=True)
        for k in ("gain", "delay", "long_latency_gain", "long_latency_delay", "rate_weight")
    }
    out["width"] = f.number("width", d("width"), positive=True)
    for key in ("delay", "long_latency_delay"):
        if f.get("max_delay") is None and out[key] > REFLEX_DELAY_LIMIT:
            f.fail(key, f"must be at most {REFLEX_DELAY_LIMIT:g} s (the history buffer), got {out[key]!r}")
    out["max_delay"] = f.number(
        "max_delay", max(d("max_delay"), out["delay"], out["long_latency_delay"]), positive=True
    )
    if out["max_delay"] > REFLEX_DELAY_LIMIT:
        f.fail("max_delay", f"must be at most {REFLEX_DELAY_LIMIT:g} s (the history buffer), got {out['max_delay']!r}")
    for key in ("delay", "long_latency_delay"):
        if out[key] > out["max_delay"]:
            f.fail(key, f"= {out[key]:g} s is longer than reflex.max_delay = {out['max_delay']:g} s")
    out["one_sided"] = f.boolean("one_sided", d("one_sided"))
    f.done()
    return ReflexSpec(**out)


def simulation_config(data: dict, source: str = "<dict>", base_dir=None) -> SimulationConfig:
    """The simulation of a config: top level, ``[sim]``, ``[gains]``, ``[[perturbation]]``, ``[ball]``."""
    top = Fields(data, "", source)
    fields = _body_fields(top, base_dir)
    fields.update(_sim_fields(top))
    perts = top.get("perturbation", [])
    if not isinstance(perts, list):
        top.fail("perturbation", "must be an array of tables ([[perturbation]])")
    fields["perturbations"] = [
        parse_perturbation(p, f"perturbation[{i}]", source, base_dir) for i, p in enumerate(perts)
    ]
    if "ball" in data:
        fields["ball"] = parse_ball(top.get("ball"), source)
    if "reflex" in data:
        fields["reflex"] = parse_reflex(top)
    if "ground" in data:
        fields["ground"] = parse_ground(top)
        if "ball" in data and fields["ground"].pgs_iterations is not None:  # one LCP, one sweep count
            why = "cannot be set with a [ball]: the one contact LCP uses [ball] pgs_iterations"
            top.sub("ground").fail("pgs_iterations", why)
    if "balance" in data:
        fields["balance"] = parse_balance(top)
    top.done(allowed_tables=TABLES)
    if "ball" in data:
        fields["ball"] = _ball_in_window(top, data["ball"], fields["ball"], fields["start"])
    cfg = SimulationConfig(source=source, **fields)
    if cfg.ball is not None and cfg.ground_on:  # one ground for the ball and the bodies (studies.simulate.prepare)
        ball = top.sub("ball")
        if "ground_height" in data["ball"]:
            ball.fail(
                "ground_height",
                "cannot be set when the bodies touch the ground: the ball bounces on it (set [ground] height)",
            )
        if not cfg.ball.ground:
            ball.fail(
                "ground", "= false with the bodies on the ground: the ball would fall through the floor they stand on"
            )
    return cfg


def _ball_in_window(top: Fields, table: dict, ball: BallSpec, start: float) -> BallSpec:
    """The ball released at the window's start unless ``launch`` says when: a ball cannot be
    released before the simulation does (its flight would start late, its onset would not)."""
    if "launch" not in table:
        return dataclasses.replace(ball, launch=start)
    if ball.launch < start - 1e-9:
        top.sub("ball").fail("launch", f"= {ball.launch:g} s is before the simulation starts (sim.start = {start:g} s)")
    return ball


def load_simulation_config(path) -> SimulationConfig:
    path = pathlib.Path(path)
    return simulation_config(read_toml(path), str(path), path.parent)


# ----------------------------------------------------------------------------- gains


def gain_settings(f: Fields, key: str, cfg: SimulationConfig) -> list[GainSetting] | None:
    """``[[<table>.<key>]]`` tables of explicit controllers (label, controller, ks, kd)."""
    tables = f.tables(key, f.name(key))
    if tables is None:
        return None
    out = []
    for i, t in enumerate(tables):
        g = Fields(t, f"{f.name(key)}[{i}]", f.source)
        out.append(
            GainSetting(
                g.number("ks", cfg.ks, nonneg=True),
                g.number("kd", cfg.kd, nonneg=True),
                g.choice("controller", "neuromotor", CONTROLLERS),
                str(g.get("label", "")),
            )
        )
        g.done()
    return out


def read_fitted(value, source: str = "fitted") -> tuple[float, float]:
    """(ks, kd) from ``[ks, kd]`` or a JSON file holding ``ks`` and ``kd`` (at any nesting)."""
    if isinstance(value, (list, tuple)) and len(value) == 2:
        return float(value[0]), float(value[1])
    path = pathlib.Path(value)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{source}: cannot read the fitted gains from {path}: {e}") from None

    def find(d):
        if isinstance(d, dict):
            if isinstance(d.get("ks"), (int, float)) and isinstance(d.get("kd"), (int, float)):
                return float(d["ks"]), float(d["kd"])
            for v in d.values():
                hit = find(v)
                if hit:
                    return hit
        return None

    hit = find(data)
    if hit is None:
        raise ConfigError(f"{source}: {path} holds no numeric 'ks' and 'kd'")
    return hit


# ----------------------------------------------------------------------------- sweep


def output_dir(path: str, base_dir) -> pathlib.Path:
    """An output folder: relative to the config's folder (resolved), or as given."""
    out = pathlib.Path(path)
    if base_dir is not None and not out.is_absolute():
        out = (pathlib.Path(base_dir) / out).resolve()
    return out


def _sweep_magnitudes(f: Fields, cfg: SimulationConfig) -> tuple[str, list[float]]:
    """The kind of sweep (force pulse or ball speed) and its magnitudes."""
    if cfg.ball is not None:
        if cfg.perturbations:
            raise ConfigError(
                f"{cfg.source}: field 'perturbation': a sweep of a [ball] config varies the ball speed "
                "(sweep.magnitudes in m/s); remove the [[perturbation]] tables, or the [ball] "
                "table to sweep the force pulse"
            )
        for key in ("bodies", "directions", "starts"):
            if key in f.table:
                f.fail(
                    key,
                    "does not apply to a ball sweep: sweep.magnitudes are ball speeds (m/s); "
                    "aim and launch time come from [ball]",
                )
        ball = cfg.ball
        speed = float(np.linalg.norm(ball.velocity)) if ball.velocity is not None else ball.speed
        mags = f.number_list("magnitudes", [speed], nonneg=True)
        if ball.target is not None and any(m <= 0 for m in mags):
            f.fail("magnitudes", "ball speeds must be > 0 when the ball aims at a target (ball.target)")
        return "ball", mags
    if not cfg.perturbations:
        raise ConfigError(
            f"{cfg.source}: field 'perturbation' is required: a sweep varies perturbation[0] "
            "(or give a [ball] table to sweep the ball speed)"
        )
    return "force", f.number_list("magnitudes", [cfg.perturbations[0].magnitude], nonneg=True)


def _sweep_axes(f: Fields) -> dict:
    """Bodies, directions and start times of the grid (None: perturbation[0]'s)."""
    bodies = f.get("bodies", None)
    if bodies is not None and (
        not isinstance(bodies, list) or not bodies or not all(isinstance(b, str) for b in bodies)
    ):
        f.fail("bodies", f"must be a non-empty list of body names, got {bodies!r}")
    directions = f.get("directions", None)
    if directions is not None:
        ok = (
            isinstance(directions, list)
            and directions
            and all(
                d in DIRECTION_KEYWORDS
                if isinstance(d, str)
                else isinstance(d, list)
                and len(d) == 3
                and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in d)
                and any(d)
                for d in directions
            )
        )
        if not ok:
            f.fail(
                "directions",
                f"must be a non-empty list of finite, non-zero [x, y, z] or keywords {list(DIRECTION_KEYWORDS)}, "
                f"got {directions!r}",
            )
    return dict(
        bodies=bodies,
        directions=[d if isinstance(d, str) else list(map(float, d)) for d in directions] if directions else None,
        starts=f.number_list("starts", None, nonneg=True, allow_range=False),
    )


def _sweep_gains(f: Fields, cfg: SimulationConfig) -> list[GainSetting]:
    """``[[sweep.gains]]`` or the product of the ``ks`` and ``kd`` lists."""
    ks = f.number_list("ks", [cfg.ks], nonneg=True)
    kd = f.number_list("kd", [cfg.kd], nonneg=True)
    if "gains" in f.table and ("ks" in f.table or "kd" in f.table):
        f.fail("gains", "give either [[sweep.gains]] tables or ks/kd lists, not both")
    explicit = gain_settings(f, "gains", cfg)
    return explicit if explicit is not None else [GainSetting(a, b) for a in ks for b in kd]


def _sweep_reflex(f: Fields, cfg: SimulationConfig, kind: str) -> tuple[ReflexSpec, ...] | None:
    """The reflex settings of the grid: the product of the reflex axes over the config's
    ``[reflex]``. The history is extended to the grid's longest delay (one static length for
    the whole batch), up to the 1 s that ``reflex.max_delay`` allows."""
    axes = {k: f.number_list(k, None, nonneg=True) for k in REFLEX_AXES}
    given = [k for k, v in axes.items() if v is not None]
    if not given:
        return None
    if cfg.reflex is None:
        f.fail(given[0], "needs a [reflex] table in the config (the reflex it varies)")
    if kind == "ball":
        f.fail(given[0], "does not apply to a ball sweep (reflex axes sweep force pulses)")
    for key in ("reflex_delay", "long_latency_delay"):
        if max(axes[key] or [0.0]) > REFLEX_DELAY_LIMIT:
            f.fail(
                key,
                f"delays must be at most {REFLEX_DELAY_LIMIT:g} s (the reflex history buffer), got {max(axes[key])!r}",
            )
    return reflex_grid(cfg.reflex, **axes)


def _sweep_fitted(f: Fields, base_dir) -> tuple[float, float] | None:
    fitted = f.get("fitted", None)
    if fitted is None:
        return None
    if isinstance(fitted, str):
        return read_fitted(str(resolve(fitted, base_dir)), f"{f.source}: field 'sweep.fitted'")
    if (
        isinstance(fitted, list)
        and len(fitted) == 2
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in fitted)
    ):
        return read_fitted(fitted)
    f.fail("fitted", f"must be a JSON path or [ks, kd], got {fitted!r}")


def sweep_spec(data: dict, cfg: SimulationConfig, base_dir=None) -> SweepSpec:
    """The ``[sweep]`` table of a config (layout in :mod:`neuromotor.studies.sweep`)."""
    f = Fields(data.get("sweep", {}), "sweep", cfg.source)
    kind, mags = _sweep_magnitudes(f, cfg)
    axes = _sweep_axes(f)
    gains = _sweep_gains(f, cfg)
    reflexes = _sweep_reflex(f, cfg, kind)
    chunk = f.integer("chunk", default(SweepSpec, "chunk"), 1, "must be a positive integer")
    inner = f.integer("inner_batch", default(SweepSpec, "inner_batch"), 1, "must be a positive integer")
    out = f.string("output", None, "a path string")
    fitted = _sweep_fitted(f, base_dir)
    f.done()
    output = None if out is None else output_dir(out, base_dir)
    return SweepSpec(
        mags, gains, chunk=chunk, inner_batch=inner, output=output, fitted=fitted, kind=kind, reflexes=reflexes, **axes
    )


def load_sweep_config(path) -> tuple[SimulationConfig, SweepSpec]:
    path = pathlib.Path(path)
    data = read_toml(path)
    cfg = simulation_config(data, str(path), path.parent)
    return cfg, sweep_spec(data, cfg, path.parent)


# ----------------------------------------------------------------------------- experiment


def experiment_spec(
    data: dict, cfg: SimulationConfig, base_dir=None, default_kind: str | None = None
) -> ExperimentSpec:
    """The ``[experiment]`` table (layout in :mod:`neuromotor.studies.experiments`)."""
    f = Fields(data.get("experiment", {}), "experiment", cfg.source)
    d = lambda name: default(ExperimentSpec, name)
    kind = f.choice("kind", default_kind, EXPERIMENT_KINDS)
    out = f.string("output", f"out/exp_{kind}", "a path string")
    frames = f.integer("frames", d("frames"), 1, "must be a positive integer")
    video = f.get("video", d("video"))
    if not isinstance(video, str) or (video and not video.endswith((".mp4", ".gif"))):
        f.fail("video", f'must be a file name ending .mp4 or .gif, or "", got {video!r}')
    arm = tuple(f.string_list("arm", list(d("arm"))))
    mags = f.number_list("magnitudes", None, nonneg=True)
    controllers = gain_settings(f, "controller", cfg)
    f.done()
    if not cfg.perturbations and cfg.ball is None:
        raise ConfigError(
            f"{cfg.source}: field 'perturbation' is required (or a [ball]): every experiment hits the character"
        )
    return ExperimentSpec(
        kind,
        output_dir(out, base_dir),
        frames,
        video,
        arm,
        d("controllers") if controllers is None else tuple(controllers),
        None if mags is None else tuple(mags),
    )


def load_experiment(path, default_kind: str | None = None) -> tuple[SimulationConfig, ExperimentSpec]:
    path = pathlib.Path(path)
    data = read_toml(path)
    cfg = simulation_config(data, str(path), path.parent)
    return cfg, experiment_spec(data, cfg, path.parent, default_kind)


# ----------------------------------------------------------------------------- fit


def _fit_window(f: Fields):
    window = f.get("window")
    if window is not None and (
        not isinstance(window, list)
        or len(window) != 2
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in window)
    ):
        f.fail("window", f"must be [t0, t1] in clip seconds, got {window!r}")
    return None if window is None else tuple(window)


def _feature_case(case, i: int, source: str) -> dict:
    """One ``[[fit.target.case]]``: feature name -> :class:`FeatureTarget`."""
    c = Fields(case, f"fit.target.case[{i}]", source)
    row = {}
    for feat in FEATURE_NAMES:
        if c.get(feat) is None:
            continue
        g = c.sub(feat)
        value = g.required("value", g.number("value", None))
        sd = g.required(
            "sd", g.number("sd", None, positive=True), "is required (the residual is (simulated - value) / sd)"
        )
        cite = g.get("source", "")
        if not isinstance(cite, str) or not cite.strip():
            g.fail("source", "is required: cite where the number comes from, or say it is illustrative")
        g.done()
        row[feat] = FeatureTarget(value, sd, cite)
    c.done()
    if not row:
        c.fail(FEATURE_NAMES[0], f"one of {list(FEATURE_NAMES)} is required")
    return row


def _feature_target(t: Fields, n_perturbations: int) -> FitTargetSpec:
    d = lambda name: default(Surrogate, name)
    dofs = tuple(t.string_list("dofs", []))
    surrogate = Surrogate(
        beta=t.number("beta", d("beta"), positive=True),
        width=t.number("width", d("width"), positive=True),
        fraction=t.number("recovery_fraction", d("fraction"), positive=True),
        floor_deg=t.number("recovery_floor_deg", d("floor_deg"), nonneg=True),
        accel_beta=t.number("accel_beta", d("accel_beta"), positive=True),
    )
    cases = t.get("case", [])
    if not isinstance(cases, list) or not cases:
        t.fail("case", "must be one or more [[fit.target.case]] tables (one per [[perturbation]])")
    t.done()
    if len(cases) != n_perturbations:
        t.fail("case", f"has {len(cases)} entries but there are {n_perturbations} [[perturbation]] entries")
    rows = tuple(_feature_case(c, i, t.source) for i, c in enumerate(cases))
    return FitTargetSpec("features", names=dofs, surrogate=surrogate, cases=rows)


def _target_files(t: Fields, n_perturbations: int, what: str) -> tuple[str | None, list[str]]:
    """``file`` or ``files`` (one per ``[[perturbation]]``), exactly one of them: (file, every name)."""
    file, files = t.get("file"), t.get("files")
    if (file is None) == (files is None):
        t.fail("file", f"or 'files' is required (not both): {what}, or one file per [[perturbation]]")
    if files is None:
        if not isinstance(file, str):
            t.fail("file", f"must be the path of a target file, got {file!r}")
        return file, [file]
    if not isinstance(files, list) or not files or not all(isinstance(x, str) for x in files):
        t.fail("files", f"must be a list of paths, one per [[perturbation]], got {files!r}")
    if len(files) != n_perturbations:
        t.fail("files", f"has {len(files)} entries but there are {n_perturbations} [[perturbation]] entries")
    return None, list(files)


def _trajectory_target(t: Fields, kind: str, base_dir, n_perturbations: int) -> FitTargetSpec:
    file, every = _target_files(t, n_perturbations, "an NPZ, CSV or BVH file with a case column")
    bvh = [name.lower().endswith(".bvh") for name in every]
    names = tuple(t.string_list("dofs" if kind == "joint_angles" else "bodies", []))
    unit = t.choice("angle_unit", default(FitTargetSpec, "angle_unit"), ("rad", "deg"))
    weights = t.get("weights", {})
    if not isinstance(weights, dict):
        t.fail("weights", f"must be a table of name = weight, got {weights!r}")
    offset = t.number("time_offset", default(FitTargetSpec, "time_offset"))
    if any(bvh) and "angle_unit" in t.table:
        t.fail("angle_unit", "does not apply to a BVH target (its rotation channels are degrees, read as such)")
    if "time_offset" in t.table and not all(bvh):
        t.fail("time_offset", "applies to a BVH target only (other targets give clip times)")
    t.done()
    paths = tuple(resolve(x, base_dir) for x in every) if file is None else ()
    return FitTargetSpec(
        kind,
        None if file is None else resolve(file, base_dir),
        names,
        unit,
        dict(weights),
        time_offset=offset,
        files=paths,
    )


def _body_target(t: Fields, kind: str, base_dir, n_perturbations: int) -> FitTargetSpec:
    """``body_angle`` / ``body_position``: one series per case from ``file`` (a ``case`` column
    numbers the cases) or ``files`` (one per ``[[perturbation]]``); the units are required."""
    file, every = _target_files(t, n_perturbations, "a CSV with a case column")
    paths = tuple(resolve(x, base_dir) for x in every) if file is None else ()
    for i, name in enumerate(every):
        if not name.lower().endswith(".csv"):
            t.fail("file" if file is not None else f"files[{i}]", f"must be a .csv file, got {name!r}")
    body = t.string("body", None, "a body name or segment keyword")
    if not body:
        t.fail("body", "is required (a body name or a segment keyword such as 'head')")
    relative_to = t.string("relative_to", "world", "'world' or a body name or segment keyword")
    axis = (
        t.direction("axis", None)
        if "axis" in t.table
        else t.fail("axis", "is required (a direction keyword or 3 numbers)")
    )
    point = None
    if kind == "body_position" and "point" in t.table:
        point = tuple(t.vector("point", None))
    t.get("point")
    units = {"time_unit": list(TIME_UNITS)}
    units.update({"angle_unit": ["deg", "rad"]} if kind == "body_angle" else {"length_unit": list(LENGTH_UNITS)})
    for key, options in units.items():
        if key not in t.table:
            t.fail(key, f"is required: one of {options} (the unit of the file's {key.split('_')[0]} column)")
    other = "length_unit" if kind == "body_angle" else "angle_unit"
    if other in t.table:
        t.fail(
            other,
            f"does not apply to kind = {kind!r} (its unit field is {next(k for k in units if k != 'time_unit')!r})",
        )
    if "point" in t.table and kind == "body_angle":
        t.fail("point", "applies to kind = 'body_position' only")
    time_unit = t.choice("time_unit", None, list(TIME_UNITS))
    angle_unit = t.choice("angle_unit", None, ["deg", "rad"]) if kind == "body_angle" else "rad"
    length_unit = t.choice("length_unit", None, list(LENGTH_UNITS)) if kind == "body_position" else "m"
    offset = t.number("time_offset", None)
    column = t.string("column", None, "the name of a data column of the file")
    weight = t.number("weight", 1.0, positive=True)
    t.done()
    return FitTargetSpec(
        kind,
        file=resolve(file, base_dir) if file is not None else None,
        angle_unit=angle_unit,
        time_offset=offset,
        files=paths,
        body=body,
        relative_to=relative_to,
        axis=axis if isinstance(axis, str) else tuple(axis),
        point=point,
        time_unit=time_unit,
        length_unit=length_unit,
        column=column,
        weight=weight,
    )


def _fit_target(table, where: str, source: str, base_dir, n_perturbations: int) -> FitTargetSpec:
    t = Fields(table, where, source)
    kind = t.choice("kind", None, TARGET_KINDS)
    if kind == "features":
        return _feature_target(t, n_perturbations)
    if kind in BODY_TARGET_KINDS:
        return _body_target(t, kind, base_dir, n_perturbations)
    return _trajectory_target(t, kind, base_dir, n_perturbations)


def fit_spec(data: dict, cfg: SimulationConfig, base_dir=None) -> FitSpec:
    """The ``[fit]`` table (layout in docs/fitting.md)."""
    source = cfg.source
    if "fit" not in data:
        raise ConfigError(f"{source}: a fit config needs a [fit] table")
    if cfg.ball is not None:  # the fit's forward model has the ground's contacts, not a ball's
        raise ConfigError(
            f"{source}: field 'ball': a fit simulates its [[perturbation]] cases without a ball, "
            "so it cannot take a [ball] (remove it; a ball-speed sweep maps a ball's effect)"
        )
    f = Fields(data["fit"], "fit", source)
    d = lambda name: default(SolverOptions, name)
    solver = f.choice("solver", default(FitSpec, "solver"), FIT_SOLVERS)
    opts = SolverOptions(
        max_steps=f.integer("max_steps", d("max_steps"), 1),
        rtol=f.number("rtol", d("rtol"), positive=True),
        atol=f.number("atol", d("atol"), positive=True),
        gtol=f.number("gtol", d("gtol"), positive=True),
    )
    jacobian = f.choice("jacobian", default(FitSpec, "jacobian"), JACOBIANS)
    names = check_fit_parameters(
        f.string_list("parameters", list(default(FitSpec, "parameters"))),
        cfg.reflex is not None,
        source,
        has_balance=cfg.balance_on,
    )
    window = _fit_window(f)
    n_cases = len(cfg.perturbations)
    loo = f.get("leave_one_out", None)
    if loo is not None:
        loo = f.boolean("leave_one_out", None)
        if loo and n_cases < 2:
            f.fail("leave_one_out", f"needs 2 or more [[perturbation]] cases, there are {n_cases}")
    raw = f.get("target", None)
    if raw is None:
        f.fail("target", "is required ([fit.target] table, or [[fit.target]] tables)")
    f.done()
    if isinstance(raw, list):  # [[fit.target]]: several targets fitted together
        if not raw:
            f.fail("target", "must hold at least one [[fit.target]] table")
        targets = tuple(_fit_target(t, f"fit.target[{i}]", source, base_dir, n_cases) for i, t in enumerate(raw))
        if len(targets) > 1 and any(t.kind == "features" for t in targets):
            i = next(i for i, t in enumerate(targets) if t.kind == "features")
            f.fail(f"target[{i}].kind", "= 'features' cannot be fitted together with other targets (use it alone)")
    else:
        targets = (_fit_target(raw, "fit.target", source, base_dir, n_cases),)
    return FitSpec(targets[0], solver, opts, jacobian, window, names, targets, loo)
