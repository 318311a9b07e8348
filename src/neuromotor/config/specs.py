"""The typed, frozen specs that a config file becomes (see :mod:`neuromotor.config.parse`).

Every default is written here once; the parser reads it from the field, and a changed copy is
``dataclasses.replace(spec, field=value)``. :class:`PerturbationSpec` and :class:`BallSpec`
also read like the dicts they replace (``spec["body"]``, ``spec.get("point")``, ``dict(spec)``),
so code that indexes a perturbation by key keeps working.
"""

from __future__ import annotations

import dataclasses
import inspect
import pathlib
from collections.abc import Mapping
from types import MappingProxyType
from typing import ClassVar

from neuromotor.errors import ConfigError
from neuromotor.physics import balance as _balance, perturbation as _perturbation, reflex as _reflex
from neuromotor.physics.contact import ground as _ground
from neuromotor.physics.contact.ball import make_ball
from neuromotor.physics.contact.detection import ContactSettings
from neuromotor.physics.control import DEFAULT_KD, DEFAULT_KS, DEFAULT_TAU_FLOOR
from neuromotor.physics.options import Feedforward, JointLaw
from neuromotor.physics.precision import Precision

PERTURBATION_KINDS, PULSE_SHAPES = _perturbation.KINDS, _perturbation.SHAPES
SEXES = ("average", "male", "female")
CONTROLLERS = ("neuromotor", "pd")  # the paper's model, or the high-gain PD tracker
FIT_SOLVERS = ("optimistix_lm", "optimistix_gn", "optimistix_bfgs", "jaxopt_lm", "jaxopt_lbfgs")
JACOBIANS = ("forward", "reverse")
TARGET_KINDS = ("joint_angles", "body_positions", "features", "body_angle", "body_position")
# Targets on one body's orientation or one point's position, relative to the world or another body,
# read as the change since the case's onset (neuromotor.studies.fit.observables; docs/fitting.md).
BODY_TARGET_KINDS = ("body_angle", "body_position")
TIME_UNITS = _perturbation.TIME_UNITS  # seconds per unit (one table for every time column)
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3}  # metres per unit
FEATURE_NAMES = ("peak_deviation_deg", "time_to_peak_s", "recovery_time_s", "overshoot_deg", "peak_acceleration_deg_s2")
EXPERIMENT_KINDS = ("arm", "full_body", "contrast")
# What a fit may tune (neuromotor.studies.fit.parameters): the muscle feedback pair and the reflex paths.
# The postural loop's parameters ([balance] kp, kd, hip_kp, hip_kd, delay) fit as balance_<key>.
BALANCE_PARAMETERS = ("balance_kp", "balance_kd", "balance_hip_kp", "balance_hip_kd", "balance_delay")
FIT_PARAMETERS = (
    "ks",
    "kd",
    "reflex_gain",
    "reflex_delay",
    "long_latency_gain",
    "long_latency_delay",
    *BALANCE_PARAMETERS,
)
PARAMETER_UNITS = MappingProxyType(
    {
        "ks": "1/s^2",
        "kd": "1/s",
        "reflex_gain": "1/s^2",
        "reflex_delay": "s",
        "long_latency_gain": "1/s^2",
        "long_latency_delay": "s",
        "balance_kp": "m g H/rad",
        "balance_kd": "m g H s/rad",
        "balance_hip_kp": "m g H/rad",
        "balance_hip_kd": "m g H s/rad",
        "balance_delay": "s",
    }
)
# The recovery metrics (neuromotor.studies.metrics): the deviation's definition ([sim] metric, the first
# the default) and the recovery threshold max(RECOVERY_FRACTION * peak, RECOVERY_FLOOR_DEG).
DEVIATION_METRICS = ("geodesic", "euler")
# [sim] root: "driven" along the mocap (the paper), or "free" (no actuator, no constraint: only
# gravity, the ground, the perturbations and the joint torques move it).
ROOT_MODES = ("driven", "free")
RECOVERY_FRACTION = 0.2
RECOVERY_FLOOR_DEG = 0.5


def check_fit_parameters(
    names, has_reflex: bool, source: str, field: str = "fit.parameters", has_balance: bool = False
) -> tuple[str, ...]:
    """The fitted parameters of a config, checked: at least one, known, distinct, the reflex
    ones only with a ``[reflex]`` table and the balance ones only with the postural loop on."""
    from neuromotor.errors import ConfigError

    names = tuple(names)
    if not names:
        raise ConfigError(f"{source}: field '{field}' must name at least one parameter of {list(FIT_PARAMETERS)}")
    for i, n in enumerate(names):
        if n not in FIT_PARAMETERS:
            raise ConfigError(f"{source}: field '{field}[{i}]' is {n!r}; choose from {list(FIT_PARAMETERS)}")
        if n in BALANCE_PARAMETERS:
            if not has_balance:
                raise ConfigError(
                    f"{source}: field '{field}[{i}]' = {n!r} needs the postural loop: "
                    '[sim] root = "free" on the ground, with [balance] on'
                )
        elif n not in ("ks", "kd") and not has_reflex:
            raise ConfigError(f"{source}: field '{field}[{i}]' = {n!r} needs a [reflex] table in the config")
    if len(set(names)) != len(names):
        raise ConfigError(f"{source}: field '{field}' names a parameter twice: {list(names)}")
    return names


def default(cls, name: str):
    """The default of field ``name`` of dataclass ``cls`` (the one place it is written)."""
    f = cls.__dataclass_fields__[name]
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


class _KeyView(Mapping):
    """Read access by key, like the dict the spec replaces; ``_optional`` keys are absent
    while None (a ball given by velocity has no ``speed`` key)."""

    _optional: ClassVar[tuple[str, ...]] = ()

    def _keys(self) -> list[str]:
        return [
            f.name
            for f in dataclasses.fields(self)  # type: ignore[arg-type]  # mixed into dataclasses
            if not (f.name in self._optional and getattr(self, f.name) is None)
        ]

    def __getitem__(self, key):
        if key not in self._keys():
            raise KeyError(key)
        return getattr(self, key)

    def __iter__(self):
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())

    def __eq__(self, other):
        return isinstance(other, Mapping) and dict(self) == dict(other)

    __hash__ = None  # type: ignore[assignment]  # unhashable, as the dict it replaces


def _rule(rule: str, **more) -> dict:
    """How the parser reads a field (:func:`neuromotor.config.parse.parse_perturbation`): ``body``
    (a name), ``vector`` (3 numbers or absent), ``direction`` (3 numbers, not all zero),
    ``number``, ``nonneg``, ``positive``, ``choice`` (of ``choices``), ``file`` (a CSV path),
    ``derived`` (set by the parser, not read); a ``direction`` may also be a keyword of the
    character's frame (:data:`neuromotor.model.facing.DIRECTION_KEYWORDS`)."""
    return {"rule": rule, **more}


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class PerturbationSpec(_KeyView):
    """One ``[[perturbation]]``: a force pulse or an impulse at a point on a body, or a base motion
    (an acceleration added to the driven root's path: a pulse, or a recorded series from a CSV
    ``file``). Each field's default and parsing rule is written here once; which kind reads which
    field, and in which unit, is :data:`neuromotor.physics.perturbation.KIND_FIELDS` and ``UNITS``;
    which fields a kind requires is :data:`REQUIRED`."""

    # Keys absent while None (a base motion has no body; a pulse no file), as in the TOML table.
    _optional: ClassVar[tuple[str, ...]] = ("body", "magnitude", "file", "unit", "record", "pivot")

    kind: str = dataclasses.field(default="force", metadata=_rule("choice", choices=_perturbation.KINDS))
    # A body (joint) name, or a segment keyword (chest); required by the kinds that push a body.
    body: str | None = dataclasses.field(default=None, metadata=_rule("body"))
    # Body frame, m, from the joint origin; None: the body's COM.
    point: list[float] | None = dataclasses.field(default=None, metadata=_rule("vector"))
    # World, or a keyword of the character's frame at ``start`` (forward, backward, left, right, up,
    # down); a tilt's axis (right-hand rule: right tilts the toes up).
    direction: list[float] | str = dataclasses.field(
        default_factory=lambda: [1.0, 0.0, 0.0], metadata=_rule("direction")
    )
    # In the kind's unit (N, N s, or the base motion's ``unit``); a recorded base series: a factor
    # on its values (default 1).
    magnitude: float | None = dataclasses.field(default=None, metadata=_rule("nonneg"))
    start: float = dataclasses.field(default=1.0, metadata=_rule("nonneg"))  # s, clip time
    duration: float = dataclasses.field(default=0.1, metadata=_rule("positive"))  # s
    shape: str = dataclasses.field(default="half_sine", metadata=_rule("choice", choices=_perturbation.SHAPES))
    # A tilt: the point it turns the ground about (world, m); None: the ground point under the
    # whole-body COM of the run's first pose.
    pivot: list[float] | None = dataclasses.field(default=None, metadata=_rule("vector"))
    # A base motion: a CSV of time and acceleration (instead of magnitude, shape and duration), the
    # acceleration's unit (g or m/s^2, required) and the file's time unit. The file's time 0 sits
    # at ``start``.
    file: str | None = dataclasses.field(default=None, metadata=_rule("file"))
    unit: str | None = dataclasses.field(
        default=None, metadata=_rule("choice", choices=tuple(_perturbation.ACCELERATION_UNITS))
    )
    time_unit: str = dataclasses.field(default="s", metadata=_rule("choice", choices=tuple(TIME_UNITS)))
    # The file's samples as read (times in s from the file's 0, values in ``unit``); set by the parser.
    record: tuple[tuple[float, ...], tuple[float, ...]] | None = dataclasses.field(
        default=None, metadata=_rule("derived")
    )

    def _keys(self) -> list[str]:
        """The keys of the fields its kind reads (so ``dict(spec)`` parses back to the same spec)."""
        return [k for k in super()._keys() if self.reads(self.kind, k)]

    def __post_init__(self):
        if self.kind == "base" and self.file is not None and self.magnitude is None:
            object.__setattr__(self, "magnitude", 1.0)

    @classmethod
    def of(cls, value) -> PerturbationSpec:
        return value if isinstance(value, cls) else cls(**dict(value))

    @staticmethod
    def reads(kind: str, name: str) -> bool:
        """Whether a perturbation of ``kind`` reads field ``name``."""
        return name in ("kind", "record") or name in _perturbation.KIND_FIELDS[kind]

    @property
    def recorded(self) -> bool:
        """A base motion read from a file."""
        return self.kind == "base" and self.file is not None

    @property
    def magnitude_unit(self) -> str:
        """The unit of ``magnitude``: N, N s, g or m/s^2 (a recorded series: its values')."""
        if self.kind == "base":
            return str(self.unit)
        return _perturbation.UNITS[self.kind]

    def label(self, magnitude: float | None = None) -> str:
        """How figures name it, in the user's units: "40 N s impulse", "400 N half_sine pulse",
        "15 g half_sine base pulse", "base acceleration 1 x t1.csv"."""
        m = self.magnitude if magnitude is None else magnitude
        if self.recorded:
            return f"base acceleration {m:g} x {pathlib.Path(str(self.file)).name}"
        what = f"{self.shape} pulse" if self.reads(self.kind, "shape") else self.kind
        if self.kind == "base":
            what = f"{self.shape} base pulse"
        if self.kind == "tilt":
            what = f"{self.shape} tilt"
        return f"{m:g} {self.magnitude_unit} {what}"

    @property
    def place(self) -> str:
        """Where it acts, for titles: "on Chest2", "on the base" (a base motion), "of the ground"."""
        return {"base": "on the base", "tilt": "of the ground"}.get(self.kind, f"on {self.body}")

    @property
    def span(self) -> float:
        """Seconds it acts as configured (an impulse: 0; it acts within one step; a recorded
        series: from its first sample to its last)."""
        if self.recorded:
            assert self.record is not None
            return float(self.record[0][-1] - self.record[0][0])
        return self.duration if self.reads(self.kind, "duration") else 0.0

    def acting(self, h: float) -> tuple[float, float]:
        """Clip seconds [t0, t1) it pushes at step ``h`` (an impulse: the step centred on ``start``;
        a recorded series: its samples' span, its time 0 at ``start``)."""
        if self.recorded:
            assert self.record is not None
            t0 = float(self.start) + float(self.record[0][0])
            return _perturbation.acting_interval(self.kind, t0, self.span, h)
        return _perturbation.acting_interval(self.kind, float(self.start), float(self.duration), h)


# The fields a kind cannot go without (a base pulse also needs magnitude; a recorded one a file).
REQUIRED = {
    "force": ("body", "magnitude"),
    "impulse": ("body", "magnitude"),
    "base": ("unit",),
    "tilt": ("direction", "magnitude"),
}


def onset(perturbations, ball=None, default: float | None = None) -> float:
    """Clip time (s) the response is measured from (recovery time, the features of a fit): the
    earliest configured start of ``perturbations`` (an impulse's own ``start``, not the one-step
    pulse it becomes) and of the ball's launch; ``default`` when there are none."""
    starts = [float(p["start"]) for p in perturbations]
    if ball is not None:
        starts.append(float(ball["launch"]))
    if not starts:
        if default is None:
            raise ValueError("no perturbation to measure a response from")
        return float(default)
    return min(starts)


DEFAULT_HIT = PerturbationSpec(
    kind="force",
    body="chest",  # a segment keyword: Chest2 on the embedded clip, the same place on any rig
    point=[0.0, 0.1, 0.0],
    direction=[0.0, 0.0, 1.0],
    magnitude=400.0,
    start=1.0,
    duration=0.1,
    shape="half_sine",
)


_BALL = inspect.signature(make_ball).parameters  # the ball's physical defaults live with the physics


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class BallSpec(_KeyView):
    """The ``[ball]`` table: a ball thrown at the character (see :mod:`neuromotor.physics.contact`).
    Its velocity is ``velocity``, or ``speed`` along ``direction`` or aimed at ``target``."""

    _optional: ClassVar[tuple[str, ...]] = ("velocity", "speed", "direction", "target")

    radius: float = _BALL["radius"].default  # m
    mass: float = _BALL["mass"].default  # kg
    position: list[float]  # world centre at launch (m)
    launch: float = _BALL["launch"].default  # s, clip time of release
    restitution: float = _BALL["restitution"].default  # Newton's coefficient, 0..1
    friction: float = _BALL["friction"].default  # Coulomb coefficient
    restitution_threshold: float = ContactSettings.restitution_threshold  # m/s: slower impacts do not bounce
    ground_height: float = ContactSettings.ground_height
    ground: bool = ContactSettings.ground  # the ball also hits the ground plane
    friction_directions: int = ContactSettings.friction_directions  # sides of the friction pyramid
    max_contacts: int = ContactSettings.max_contacts  # nearest contact candidates solved per step
    pgs_iterations: int = ContactSettings.pgs_iterations  # projected Gauss-Seidel sweeps
    velocity: list[float] | None = None
    speed: float | None = None  # m/s
    direction: list[float] | str | None = None  # world, or a keyword of the character's frame at launch
    target: str | None = None  # a body to aim at

    @classmethod
    def of(cls, value) -> BallSpec | None:
        return value if value is None or isinstance(value, cls) else cls(**dict(value))

    @property
    def launch_speed(self) -> float:
        """m/s: ``speed``, or the norm of ``velocity``."""
        if self.velocity is not None:
            return float(sum(v * v for v in self.velocity) ** 0.5)
        assert self.speed is not None  # the parser requires velocity or speed
        return float(self.speed)

    def label(self, speed: float | None = None) -> str:
        """How figures name it: "1 kg ball at 14 m/s"."""
        return f"{self.mass:g} kg ball at {self.launch_speed if speed is None else speed:g} m/s"


@dataclasses.dataclass(frozen=True, kw_only=True)
class GroundSpec:
    """The ``[ground]`` table: the plane under the character's bodies
    (:mod:`neuromotor.physics.contact.ground`). Without the table: the defaults, on with
    ``[sim] root = "free"``, off with the driven root (the paper)."""

    enabled: bool | None = None  # None: on with root = "free", off with the driven root
    height: float | None = None  # m along the up axis; None: the floor of the motion run (capture_floor)
    friction: float = _ground.DEFAULT_FRICTION  # Coulomb coefficient
    restitution: float = 0.0  # Newton's coefficient, 0..1
    contacts_per_body: int = _ground.DEFAULT_PER_BODY  # each body's lowest vertices that may touch
    max_contacts: int = _ground.DEFAULT_MAX_CONTACTS  # lowest of them solved per step
    pgs_iterations: int | None = None  # PGS sweeps per step; None: 40 (with a [ball]: [ball] pgs_iterations)

    def on(self, root: str) -> bool:
        """Whether the bodies touch the ground with this root mode."""
        return root == "free" if self.enabled is None else self.enabled


@dataclasses.dataclass(frozen=True)
class BalanceSpec:
    """The ``[balance]`` table: the postural loop, the standing feedforward and the assist
    (:mod:`neuromotor.physics.balance`, where the literature behind the defaults is cited).
    Without the table: on with ``[sim] root = "free"`` on the ground, off with the driven root."""

    enabled: bool | None = None  # None: on with a free root on the ground
    kp: float = _balance.KP  # ankle stiffness, m g H per rad (Peterka 2002: 1.2-1.5)
    kd: float = _balance.KD  # ankle damping, m g H s per rad
    hip_kp: float = _balance.HIP_KP  # pelvis uprightness at the hips, m g H per rad
    hip_kd: float = _balance.HIP_KD  # m g H s per rad
    delay: float = _balance.DELAY  # s (100-200 ms)
    assist: float = 0.0  # 1/s^2: spring-damper on the pelvis toward its captured path; 0: off
    max_delay: float = _balance.MAX_DELAY  # s: the history buffer
    # Stepping when the capture point leaves the support (neuromotor.physics.balance, "Stepping").
    stepping: bool = False  # off: it steps but does not recover yet (docs/balance.md, "Stepping")
    step_margin: float = _balance.STEP_MARGIN  # m beyond the soles' segment
    step_offset: float = _balance.STEP_OFFSET  # m beyond the capture point
    max_step: float = _balance.MAX_STEP  # m
    swing_time: float = _balance.SWING_TIME  # s
    step_lift: float = _balance.STEP_LIFT  # m
    weight_shift: float = _balance.WEIGHT_SHIFT  # s before lift-off
    shift_fraction: float = _balance.SHIFT_FRACTION  # of the way to the stance foot
    step_crouch: float = _balance.STEP_CROUCH  # m
    step_blend: float = _balance.STEP_BLEND  # s

    def on(self, root: str, ground_on: bool) -> bool:
        return (root == "free" and ground_on) if self.enabled is None else self.enabled

    def values(self) -> dict:
        """The keyword arguments of :func:`neuromotor.physics.balance.make_balance`."""
        out = {k: getattr(self, k) for k in ("kp", "kd", "hip_kp", "hip_kd", "delay", "assist", "max_delay")}
        out["stepping"] = self.stepping_values() if self.stepping else None
        return out

    def stepping_values(self) -> dict:
        """The keyword arguments of :func:`neuromotor.physics.balance.make_stepping`."""
        return {k.removeprefix("step_"): getattr(self, k) for k in STEPPING_KEYS}


STEPPING_KEYS = (
    "step_margin",
    "step_offset",
    "max_step",
    "swing_time",
    "step_lift",
    "weight_shift",
    "shift_fraction",
    "step_crouch",
    "step_blend",
)


@dataclasses.dataclass(frozen=True)
class GainSetting:
    """One controller: the paper's model ("neuromotor") or the high-gain PD tracker ("pd") at
    the gains (ks, kd). The one way gains are set: :func:`neuromotor.studies.gains.gains_for`."""

    ks: float
    kd: float
    controller: str = "neuromotor"
    label: str = ""

    @property
    def name(self) -> str:
        return self.label or f"{self.controller} ks={self.ks:g} kd={self.kd:g}"


@dataclasses.dataclass(frozen=True)
class ReflexSpec:
    """The ``[reflex]`` table: the delayed stretch reflex (:mod:`neuromotor.physics.reflex`, where
    the literature behind the defaults is cited). Without the table there is no reflex (the paper)."""

    gain: float = _reflex.SPINAL_GAIN  # 1/s^2, spinal path
    delay: float = _reflex.SPINAL_DELAY  # s
    long_latency_gain: float = 0.0  # 1/s^2: the supraspinal path is off by default
    long_latency_delay: float = _reflex.LONG_LATENCY_DELAY  # s
    rate_weight: float = _reflex.RATE_WEIGHT  # s
    one_sided: bool = False  # only while the loaded muscle is being stretched
    width: float = _reflex.RAMP_WIDTH  # rad, of the one-sided ramp
    max_delay: float = _reflex.MAX_DELAY  # s: the longest delay the history holds (at most DELAY_LIMIT)

    def build(self, h: float):
        """The :class:`~neuromotor.physics.reflex.Reflex` of this table at step ``h``."""
        return _reflex.make_reflex(
            h,
            self.gain,
            self.delay,
            self.long_latency_gain,
            self.long_latency_delay,
            self.rate_weight,
            self.one_sided,
            self.width,
            self.max_delay,
        )


@dataclasses.dataclass(frozen=True, kw_only=True)
class SimulationConfig:
    """The character, the step, the gains and the perturbations of one simulation."""

    clip: str | None = None  # None: the embedded clip
    units: str | float = "auto"
    up_axis: int | None = None  # None: from the motion
    stature: float | None = None
    body_mass: float | None = None
    sex: str = "average"
    simulate_extremities: bool = False
    h: float = 1.0 / 120.0
    start: float = 0.0
    duration: float | None = None  # None: to the clip's end (with ``still``: the clip's duration)
    still: float | None = None  # clip time (s) of a pose held still over the window; None: the clip plays
    implicit: bool = True
    driven_joints: list[str] = dataclasses.field(default_factory=list)  # body names or keywords (trunk, arms, ...)
    stabilization_steps: int = 2  # Newton steps of post-stabilization (StepOptions.stabilization_steps)
    dtype: Precision = Precision.FLOAT64  # float64, or float32 for sweeps (docs/float32.md)
    feedforward: Feedforward = Feedforward.DISCRETE  # StepOptions.feedforward: discrete | continuous (Eq. 3)
    joint_law: JointLaw = JointLaw.ROTATION  # StepOptions.joint_law: rotation | euler (per Euler DOF)
    metric: str = "geodesic"  # the deviation d(t): geodesic joint angles, or "euler" (per-DOF; studies.metrics)
    ks: float = DEFAULT_KS
    kd: float = DEFAULT_KD
    tau_floor: float = DEFAULT_TAU_FLOOR
    perturbations: list[PerturbationSpec] = dataclasses.field(default_factory=list)
    ball: BallSpec | None = None
    reflex: ReflexSpec | None = None  # None: no delayed reflex (the paper's controller)
    root: str = "driven"  # [sim] root: "driven" (the paper) or "free" (StepOptions.free_root)
    ground: GroundSpec = dataclasses.field(default_factory=GroundSpec)  # [ground]
    balance: BalanceSpec = dataclasses.field(default_factory=BalanceSpec)  # [balance]
    source: str = "<defaults>"

    def __post_init__(self):
        object.__setattr__(self, "dtype", Precision(self.dtype))
        object.__setattr__(self, "feedforward", Feedforward(self.feedforward))
        object.__setattr__(self, "joint_law", JointLaw(self.joint_law))
        if self.metric not in DEVIATION_METRICS:
            raise ConfigError(
                f"{self.source}: field 'sim.metric' must be one of {list(DEVIATION_METRICS)}, got {self.metric!r}"
            )
        object.__setattr__(self, "perturbations", [PerturbationSpec.of(p) for p in self.perturbations])
        object.__setattr__(self, "ball", BallSpec.of(self.ball))
        if self.root not in ROOT_MODES:
            raise ConfigError(f"{self.source}: field 'sim.root' must be one of {list(ROOT_MODES)}, got {self.root!r}")
        self._check_tilts()
        if self.balance.enabled and not (self.root == "free" and self.ground_on):
            raise ConfigError(
                f"{self.source}: field 'balance.enabled': the postural loop needs [sim] root = \"free\" "
                "with the ground on (a driven root is held on its path: the loop would only bend the joints)"
            )

    def _check_tilts(self) -> None:
        """A tilt turns the ground under a free root: one platform (one pivot), no ball (whose
        ground does not tilt). A platform's translation under a free root moves the ground: no
        ball either (the ball's ground stays)."""
        if self.ball is not None and self.root == "free" and self.ground_on:
            for i, p in enumerate(self.perturbations):
                if p.kind == "base":
                    raise ConfigError(
                        f"{self.source}: field 'perturbation[{i}].kind': a moving platform with a [ball] is "
                        "not modelled (the ball's ground does not move)"
                    )
        tilts = [(i, p) for i, p in enumerate(self.perturbations) if p.kind == "tilt"]
        for i, _ in tilts:
            where = f"{self.source}: field 'perturbation[{i}].kind'"
            if not (self.root == "free" and self.ground_on):
                raise ConfigError(
                    f'{where}: a tilt turns the ground under the feet, which needs [sim] root = "free" '
                    "with the ground on (a driven root stands on nothing)"
                )
            if self.ball is not None:
                raise ConfigError(f"{where}: a tilt with a [ball] is not modelled (the ball's ground does not tilt)")
        pivots = {None if p.pivot is None else tuple(float(x) for x in p.pivot) for _, p in tilts}
        if len(pivots) > 1:
            i = tilts[-1][0]
            raise ConfigError(
                f"{self.source}: field 'perturbation[{i}].pivot': the tilts of a run turn one platform: "
                "give every tilt the same pivot, or none (the default)"
            )

    @property
    def ground_on(self) -> bool:
        """Whether the bodies touch the ground (``[ground] enabled``, by default with a free root)."""
        return self.ground.on(self.root)

    @property
    def balance_on(self) -> bool:
        """Whether the postural loop runs (``[balance] enabled``, by default with a free root on the ground)."""
        return self.balance.on(self.root, self.ground_on)

    @property
    def gains(self) -> GainSetting:
        return GainSetting(self.ks, self.kd)

    def with_gains(self, ks: float | None = None, kd: float | None = None) -> SimulationConfig:
        """The config at other gains (None keeps a gain): numbers only; ``prepare`` puts them on the
        controller through :func:`neuromotor.studies.gains.gains_for`."""
        return dataclasses.replace(self, ks=self.ks if ks is None else ks, kd=self.kd if kd is None else kd)

    def mass_options(self):
        from neuromotor.model.skeleton import MassModelOptions

        return MassModelOptions(body_mass=self.body_mass, sex=self.sex, simulate_extremities=self.simulate_extremities)


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """Stopping rules. optimistix: relative/absolute change of y and of the objective
    (``rtol``, ``atol``). jaxopt: gradient norm below ``gtol`` times its value at the start."""

    max_steps: int = 100
    rtol: float = 1e-9
    atol: float = 1e-10
    gtol: float = 1e-9


@dataclasses.dataclass(frozen=True)
class Surrogate:
    """Smoothing of the feature surrogates: ``beta`` (1/deg) sharpens the soft peak, ``width``
    is the sigmoid width as a fraction of the threshold, the recovery threshold is
    ``max(fraction * peak, floor_deg)``, ``accel_beta`` (s^2/deg) sharpens the peak acceleration."""

    beta: float = 20.0
    width: float = 0.1
    fraction: float = RECOVERY_FRACTION
    floor_deg: float = RECOVERY_FLOOR_DEG
    accel_beta: float = 0.1


@dataclasses.dataclass(frozen=True)
class FeatureTarget:
    """One feature of one case: the value, its standard deviation and where it comes from."""

    value: float
    sd: float
    source: str

    def as_dict(self) -> dict:
        return {"value": self.value, "sd": self.sd, "source": self.source}


@dataclasses.dataclass(frozen=True)
class FitTargetSpec:
    """One ``[fit.target]`` (or one entry of ``[[fit.target]]``): a trajectory file (joint angles,
    body positions), feature values, or a body's angle or a point's displacement about/along an
    axis (``body_angle``, ``body_position``: one series per case, trial or corridor)."""

    kind: str
    file: pathlib.Path | None = None
    names: tuple[str, ...] = ()  # dofs (joint angles, features) or bodies; () = every column / DOF
    angle_unit: str = "rad"
    weights: dict = dataclasses.field(default_factory=dict)
    surrogate: Surrogate = Surrogate()
    cases: tuple[dict, ...] = ()  # features: per case, feature name -> FeatureTarget
    # Clip time (s) of the file's time 0: a BVH trial's frame 0 (default 0); for body_angle and
    # body_position None = each case's onset (the perturbation's start).
    time_offset: float | None = 0.0
    # body_angle / body_position only:
    files: tuple[pathlib.Path, ...] = ()  # one per [[perturbation]] case (instead of file with a case column)
    body: str = ""  # a body name or a segment keyword
    relative_to: str = "world"  # "world" or a body name / keyword
    axis: str | tuple[float, ...] | None = None  # a direction keyword of the character's frame, or 3 numbers
    point: tuple[float, ...] | None = None  # body_position: body frame, from the joint origin (None: the COM)
    time_unit: str = "s"  # of the file's time column: s | ms
    length_unit: str = "m"  # body_position: m | mm
    column: str | None = None  # the file's data column (None: its only one)
    weight: float = 1.0  # multiplies every residual of this target

    @property
    def paths(self) -> tuple[pathlib.Path, ...]:
        """Every file this target reads."""
        return self.files or ((self.file,) if self.file is not None else ())

    @property
    def label(self) -> str:
        """A short name for reports and plots."""
        if self.kind in BODY_TARGET_KINDS:
            axis = self.axis if isinstance(self.axis, str) else list(self.axis or ())
            rel = "" if self.relative_to == "world" else f" rel. {self.relative_to}"
            what = "angle about" if self.kind == "body_angle" else "displacement along"
            return f"{self.body}{rel}: {what} {axis}"
        return self.kind


@dataclasses.dataclass(frozen=True)
class FitSpec:
    """The ``[fit]`` table. ``target`` is the first of ``targets`` (``[fit.target]`` gives one,
    ``[[fit.target]]`` several, fitted together)."""

    target: FitTargetSpec
    solver: str = "optimistix_lm"
    options: SolverOptions = SolverOptions()
    jacobian: str = "forward"
    window: tuple[float, float] | None = None  # clip seconds
    # The fitted parameters (studies.fit.parameters): any of ks, kd, reflex_gain, reflex_delay,
    # long_latency_gain, long_latency_delay; they start from the config's [gains] and [reflex].
    parameters: tuple[str, ...] = ("ks", "kd")
    targets: tuple[FitTargetSpec, ...] = ()  # every target; () = (target,)
    # Leave-one-out over the cases (a fit on the others, predicting the one left out); None: on
    # for 2 to LEAVE_ONE_OUT_MAX_CASES cases.
    leave_one_out: bool | None = None

    def __post_init__(self):
        if not self.targets:
            object.__setattr__(self, "targets", (self.target,))


LEAVE_ONE_OUT_MAX_CASES = 8


# The reflex axes of a sweep: [sweep] key -> ReflexSpec field.
REFLEX_DELAY_LIMIT = _reflex.DELAY_LIMIT  # s
REFLEX_AXES = {
    "reflex_gain": "gain",
    "reflex_delay": "delay",
    "long_latency_gain": "long_latency_gain",
    "long_latency_delay": "long_latency_delay",
}


def reflex_grid(base: ReflexSpec, **axes) -> tuple[ReflexSpec, ...]:
    """Every combination of the reflex axes (keys of :data:`REFLEX_AXES`, lists of values; the
    first key outermost) over ``base``. All share one history length: ``max_delay`` is raised to
    the grid's longest delay (the batch has one static buffer)."""
    delays = [float(d) for k in ("reflex_delay", "long_latency_delay") for d in axes.get(k) or ()]
    out = [dataclasses.replace(base, max_delay=max([base.max_delay, base.delay, base.long_latency_delay, *delays]))]
    for key, values in axes.items():
        if values is not None:
            out = [
                dataclasses.replace(r, **{REFLEX_AXES[key]: float(v)})  # type: ignore[arg-type]  # a float field
                for r in out
                for v in values
            ]
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """The grid: every combination of gain setting, body, direction, start and magnitude."""

    magnitudes: list[float]
    gains: list[GainSetting]
    bodies: list[str] | None = None  # None: the config's perturbation[0] value
    directions: list[list[float] | str] | None = None  # vectors or keywords of the character's frame
    starts: list[float] | None = None
    chunk: int = 64
    inner_batch: int = 1
    output: pathlib.Path | None = None
    fitted: tuple[float, float] | None = None
    kind: str = "force"  # "ball": magnitudes are ball speeds (m/s) of the config's [ball]
    # The reflex settings of the grid (sweep.reflex_gain x reflex_delay x long_latency_gain x
    # long_latency_delay over the config's [reflex]); all share the grid's longest max_delay.
    reflexes: tuple[ReflexSpec, ...] | None = None

    def runs(self, base, others=()) -> list[dict]:
        """Flat list of run descriptions (dicts), gain setting outermost, then the reflex
        setting (key ``reflex``, when the grid varies it), magnitude innermost. Key
        ``perturbation``: ``base`` (perturbation[0]) with the run's axis values;
        ``perturbations``: it and ``others`` (the config's other perturbations, which every run
        keeps), for the one builder (:func:`neuromotor.physics.perturbation.build_pulses`); ``onset``: the
        run's :func:`onset` with ``others`` (the config's other perturbations, which every run keeps)."""
        out, base = [], PerturbationSpec.of(base)
        for g in self.gains:
            for rx in self.reflexes or [None]:
                for body in self.bodies or [base.body]:
                    for d in self.directions or [base["direction"]]:
                        for start in self.starts or [base["start"]]:
                            for m in self.magnitudes:
                                # An axis replaces a field; the point stays the user's (None: each
                                # body's own COM), resolved by the one builder.
                                d = d if isinstance(d, str) else list(d)
                                p = dataclasses.replace(
                                    base, body=body, direction=d, start=float(start), magnitude=float(m)
                                )
                                run = dict(
                                    gain=g,
                                    body=body,
                                    direction=d,
                                    start=float(start),
                                    magnitude=float(m),
                                    duration=p.span,
                                    kind=p.kind,
                                    perturbation=p,
                                    perturbations=[p, *others],
                                    onset=onset([p, *others]),
                                )
                                out.append(run if rx is None else dict(run, reflex=rx))
        return out


DEFAULT_CONTRAST = (
    GainSetting(400.0, 20.0, "neuromotor", "feedforward + low-gain feedback (paper)"),
    GainSetting(10000.0, 200.0, "pd", "high-gain PD tracker (Zordan & Hodgins)"),
    GainSetting(400.0, 20.0, "pd", "PD tracker at the low gains"),
)


@dataclasses.dataclass(frozen=True)
class ExperimentSpec:
    """The ``[experiment]`` table: which of the paper's experiments, and its outputs."""

    kind: str  # arm | full_body | contrast
    output: pathlib.Path
    frames: int = 6
    video: str = "video.gif"
    arm: tuple[str, ...] = ("LeftShoulder", "LeftElbow", "LeftWrist")
    controllers: tuple[GainSetting, ...] = DEFAULT_CONTRAST
    magnitudes: tuple[float, ...] | None = None
