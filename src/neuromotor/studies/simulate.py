"""The end-to-end pipeline: clip -> model -> inverse dynamics -> perturbed and unperturbed rollouts.

setup = prepare(SimulationConfig())          # embedded clip, default gains, no hit
result = run(setup)
result.metrics["peak_deviation_deg"]
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from neuromotor import compiler
from neuromotor.config import ConfigError, SimulationConfig
from neuromotor.config.specs import PerturbationSpec, onset
from neuromotor.io.runfile import read_run_info, save_npz_atomic  # noqa: F401  (re-exported)
from neuromotor.model.facing import resolve_direction
from neuromotor.model.kinematics import Trajectory, still_trajectory
from neuromotor.model.load import DEFAULT_CLIP_NAME, default_clip_path, load_character  # noqa: F401  (re-exported)
from neuromotor.model.skeleton import (
    GROUP_KEYWORDS,
    RESTRAINT_KEYWORDS,
    Character,
    Model,
    keyword_bodies,
    keyword_body,
    unknown_body,
)
from neuromotor.physics.contact import ContactRollout, Ground
from neuromotor.physics.control import Gains, make_gains
from neuromotor.physics.dynamics import (
    Feedforward,
    Params,
    Reference,
    Rollout,
    SimModel,
    StepOptions,
    check_rollout,
    make_reference,
    simulate,
)
from neuromotor.physics.perturbation import ForcePulses, build_pulses, unperturbed
from neuromotor.physics.precision import Precision
from neuromotor.studies import metrics as mx
from neuromotor.studies.balance import balance_for, balance_metrics, com_path, fold_support
from neuromotor.studies.ball_hit import BallSetup, ball_metrics, ball_rollouts, ball_setup
from neuromotor.studies.gains import gains_for
from neuromotor.studies.ground import (
    feet_warnings,
    ground_metrics,
    ground_rollouts,
    ground_setup,
    height_warnings,
    labelled_feet,
    lcp_figures,
    platform_offset,
    tilt_pivot,
)


@dataclasses.dataclass(frozen=True)
class Setup:
    """Everything a rollout needs; ``model``, ``gains``, ``pulses`` and ``ref`` are pytrees.
    Immutable: ``dataclasses.replace(setup, gains=...)`` makes a changed copy. A run is
    ``simulate(setup.sim_model, setup.params)``."""

    character: Character
    traj: Trajectory
    ref: Reference
    gains: Gains
    options: StepOptions
    pulses: ForcePulses
    config: SimulationConfig
    ball: BallSetup | None = None  # a [ball] config: the flying ball and its contacts
    warnings: tuple[str, ...] = ()  # the clip's (see Character.warnings) and the run's, one line each
    window: ActingWindow | None = None  # where a perturbation can act (sweep axes are checked against it)
    capture: Trajectory | None = None  # the clip's trajectory when ``traj`` holds a still pose (None: traj)
    ground: Ground | None = None  # the bodies touch the ground ([ground]; on by default with [sim] root = "free")

    @property
    def model(self) -> Model:
        return self.character.model

    @property
    def sim_model(self) -> SimModel:
        """What stays fixed over this setup's rollouts: the model, the reference, the options."""
        return SimModel(self.character.model, self.ref, self.options)

    @property
    def direction_of(self):
        """(direction, clip time) -> world unit vector for this setup's character (a held pose:
        its frame): the one lookup every command builds its perturbations with."""
        return direction_lookup(self.character, self.config.source, self.config.still)

    @property
    def tilt_pivot(self) -> np.ndarray | None:
        """Where a tilt without its own ``pivot`` turns this setup's ground (every command's)."""
        return tilt_pivot(self.model, self.ref, self.ground)

    @property
    def params(self) -> Params:
        """What the rollouts vary: this setup's gains and pulses."""
        return Params(self.gains, self.pulses)

    @property
    def clip_trajectory(self) -> Trajectory:
        """The clip's own trajectory, also when ``traj`` holds a still pose: where the anatomy's
        facing, the feet's friction axes and the capture's residuals are read."""
        return self.traj if self.capture is None else self.capture


# With the paper's continuous feedforward (Eq. 3), a driven root turning more than this per step
# (rad) makes the replay drift by degrees (the Bandai-Namco kick spins at 11 rad/s: 1.97 deg RMS at
# h = 1/120 s, 0.72 deg at 1/360 s; docs/body-model.md). The discrete feedforward replays it exactly.
MAX_ROOT_TURN_PER_STEP = 0.05


def step_warnings(ref: Reference, h: float, feedforward: Feedforward | str = Feedforward.DISCRETE) -> tuple[str, ...]:
    """A warning when the driven root turns faster than the time step follows well (only with
    the continuous feedforward: the discrete one is the step's own inverse)."""
    if Feedforward(feedforward) is Feedforward.DISCRETE:
        return ()
    omega = float(np.max(np.linalg.norm(np.asarray(ref.root_omega), axis=-1)))
    if omega * h <= MAX_ROOT_TURN_PER_STEP:
        return ()
    h_good = MAX_ROOT_TURN_PER_STEP / omega
    return (
        f"the root turns at up to {omega:.1f} rad/s, {omega * h:.3f} rad per step of h = {h:.4g} s: the "
        f"replay may drift by degrees; sim.h <= {h_good:.4g} s keeps it within about a degree "
        f'(or sim.feedforward = "discrete", which replays it exactly)',
    )


def point_warnings(perturbations, character: Character, index, source: str = "config") -> tuple[str, ...]:
    """A warning for each pulse applied at a point far outside its body (more than twice the
    body's own reach from its joint, its polyhedron's farthest vertex, and 0.1 m beyond it): the
    point is metres in the body's frame, and a point given in another unit makes a lever that
    turns the body hard without any error."""
    out = []
    for i, p in enumerate(perturbations):
        if p.point is None or p.body is None:
            continue
        b = index(p.body)
        shape = character.shapes[b] if b < len(character.shapes) else None
        if shape is None:
            continue
        reach = float(np.max(np.linalg.norm(np.asarray(shape.vertices, np.float64).reshape(-1, 3), axis=-1)))
        dist = float(np.linalg.norm(np.asarray(p.point, np.float64)))
        if dist > max(2.0 * reach, reach + 0.1):
            name = character.model.body_names[b]
            out.append(
                f"{source}: perturbation[{i}].point is {dist:.3g} m from {name}'s joint, {dist / reach:.0f}x the "
                f"body's reach ({reach:.2f} m): the push acts on a lever that long (metres, body frame)"
            )
    return tuple(out)


def body_lookup(model: Model, source: str = "config", character: Character | None = None):
    """Name -> body index: a body (joint) name, or a segment keyword such as ``chest``."""

    def index(name: str) -> int:
        if name in model.body_names:
            return model.body_names.index(name)
        b = keyword_body(character, name) if character is not None else None
        if b is None:
            raise ConfigError(f"{source}: {unknown_body(model, character, name)}")
        return b

    return index


def direction_lookup(character: Character | None, source: str = "config", still: float | None = None):
    """(direction, clip time) -> world unit vector: 3 numbers, or a keyword of the character's
    frame at that time (:func:`neuromotor.model.facing.character_axes`), the one rule for the
    direction of every perturbation kind and of the ball. With ``still`` (``[sim] still``), the
    frame of the held pose, whatever the time."""

    def direction(value, time: float) -> np.ndarray:
        at = float(time) if still is None else float(still)
        return resolve_direction(value, character, at, f"{source}: field 'direction'")

    return direction


@dataclasses.dataclass(frozen=True)
class ActingWindow:
    """The one refusal rule: a perturbation must act in the simulated window [t0, t1) of the
    clip and not on a driven body (the root, ``[sim] driven_joints``), where it would do
    nothing. Every command checks with it before any computation."""

    source: str
    t0: float
    t1: float
    h: float
    clip_end: float
    driven: tuple[int, ...]
    index: Callable[[str], int]
    driven_by: Mapping[int, str] = dataclasses.field(default_factory=dict)  # body -> its driven_joints entry
    still: float | None = None  # [sim] still: the clip time of the held pose
    body_names: tuple[str, ...] = ()

    @property
    def text(self) -> str:
        if self.still is not None:
            held = f"the pose at clip time {self.still:.3f} s held still"
            return f"the simulated window {self.t0:.3f} to {self.t1:.3f} s ({held})"
        return f"the simulated window {self.t0:.3f} to {self.t1:.3f} s (the clip ends at {self.clip_end:.3f} s)"

    def check(self, p, body_field: str, start_field: str) -> None:
        """ConfigError (naming the field) when perturbation ``p`` cannot act."""
        p = PerturbationSpec.of(p)
        b = None if p.body is None else self.index(p.body)  # a base motion pushes no body
        if b is not None and b in self.driven:
            why = f"by sim.driven_joints entry {self.driven_by[b]!r}" if b in self.driven_by else "the root always is"
            name = self.body_names[b] if b < len(self.body_names) else p["body"]
            body = "" if name == p["body"] else f" (body {name})"
            raise ConfigError(
                f"{self.source}: field '{body_field}' = {p['body']!r}{body} is a driven body ({why}): "
                "a push on it does nothing"
            )
        start, end = float(p.start), p.acting(self.h)[1]
        if start >= self.t1 - 1e-9:
            raise ConfigError(
                f"{self.source}: field '{start_field}' = {start:g} s is at or after the end of {self.text}"
            )
        if end <= self.t0:
            raise ConfigError(
                f"{self.source}: field '{start_field}' = {start:g} s: the perturbation is over "
                f"before {self.text} begins"
            )


def config_character(config: SimulationConfig) -> tuple[Character, Trajectory]:
    """The character and trajectory of a config's clip, read with its units, up axis, stature
    and body options."""
    return load_character(config.clip, config.units, config.up_axis, config.stature, config.mass_options())


def prepare(config: SimulationConfig, character: Character | None = None, traj: Trajectory | None = None) -> Setup:
    if config.dtype is Precision.FLOAT64 and not jax.config.jax_enable_x64:  # type: ignore[attr-defined]
        raise ConfigError(
            f"{config.source}: field 'sim.dtype' is float64 but JAX runs with x64 off "
            '(JAX_ENABLE_X64 is set to false): unset it, or set [sim] dtype = "float32"'
        )
    if character is None:
        character, traj = config_character(config)
    assert traj is not None, "prepare: a character comes with its trajectory"
    model, clip = character.model, character.clip
    capture, still = traj, still_time(config, clip.duration)
    if still is not None:
        traj = still_trajectory(capture, still)
    n_steps = window_steps(config, clip.duration)
    index = body_lookup(model, config.source, character)
    driven_by = driven_bodies(character, config.driven_joints, config.source)
    driven = tuple(sorted(driven_by))
    window = ActingWindow(
        config.source,
        config.start,
        config.start + n_steps * config.h,
        config.h,
        clip.duration,
        driven if config.root == "free" else (0, *driven),  # a free root can be pushed
        index,
        driven_by,
        still,
        model.body_names,
    )
    for i, p in enumerate(config.perturbations):
        window.check(p, f"perturbation[{i}].body", f"perturbation[{i}].start")
    if config.ball is not None and float(config.ball.get("launch", 0.0)) < window.t0 - 1e-9:
        raise ConfigError(  # its flight would start at t0, its onset (the figures' clock) would not
            f"{config.source}: field 'ball.launch' = {float(config.ball['launch']):g} s is before {window.text}"
        )
    if config.ball is not None and float(config.ball.get("launch", 0.0)) >= window.t1 - 1e-9:
        raise ConfigError(
            f"{config.source}: field 'ball.launch' = {float(config.ball['launch']):g} s is at "
            f"or after the end of {window.text}"
        )
    options = StepOptions(
        h=config.h,
        n_steps=n_steps,
        driven=driven,
        implicit=config.implicit,
        stabilization_steps=config.stabilization_steps,
        dtype=config.dtype,
        feedforward=config.feedforward,
        joint_law=config.joint_law,
    )
    # The feedforward is the capture's inverse dynamics with the driven root (the paper's); a free
    # root then runs without the root's rows: nothing holds the pelvis but the ground.
    ref = make_reference(model, traj, config.start, options)
    if config.root == "free":
        options = dataclasses.replace(options, free_root=True)
    template = _initial_gains(
        model, traj, jnp.asarray(config.start), ref.local_axes[0], ref.activation, config.tau_floor
    )
    gains = gains_for(template, config.gains, reflex=None if config.reflex is None else config.reflex.build(config.h))
    ball = ball_setup(config.ball, character, traj, index, config.source, still) if config.ball else None
    warnings = tuple(character.warnings) + step_warnings(ref, config.h, config.feedforward)
    warnings += point_warnings(config.perturbations, character, index, config.source)
    if config.ground_on:
        warnings += feet_warnings(character, config.source)
    directions = direction_lookup(character, config.source, still)
    ground = ground_setup(config.ground, character, traj, capture) if config.ground_on else None
    if ground is not None and config.ground.height is not None:
        warnings += height_warnings(character, traj, float(ground.height), config.source)
    pivot = tilt_pivot(model, ref, ground)
    pulses = build_pulses(config.perturbations, model, config.h, index, directions, ref.time, pivot)
    if config.balance_on and not labelled_feet(character):
        raise ConfigError(
            f"{config.source}: field 'balance': the postural loop stands on the rig's feet, and this rig has "
            "none labelled (see neuromotor inspect); set [balance] enabled = false to run without it"
        )
    if config.balance_on:  # the postural loop of the held (first) pose: neuromotor.physics.balance
        bal = balance_for(character, ref.init, config.h, **config.balance.values())
        ref, bal = fold_support(model, ref, bal)  # the legs carry the trunk: part of the feedforward
        gains = dataclasses.replace(gains, balance=bal)
    if ball is not None and ground is not None:  # one scene: the ball and the bodies on one ground
        settings = dataclasses.replace(ball.settings, ground_height=float(ground.height))
        ball = dataclasses.replace(ball, ground=ground, settings=settings)
    return Setup(
        character,
        traj,
        ref,
        gains,
        options,
        pulses,
        config,
        ball,
        warnings,
        window,
        capture=None if still is None else capture,
        ground=ground,
    )


def still_time(config: SimulationConfig, clip_duration: float) -> float | None:
    """``[sim] still`` checked against the clip: a clip time in [0, clip duration], or None."""
    still = config.still
    if still is None:
        return None
    field = f"{config.source}: field 'sim.still'"
    if isinstance(still, bool) or not isinstance(still, (int, float)) or not np.isfinite(still):
        raise ConfigError(f"{field} must be a clip time in seconds, got {still!r}")
    if not 0.0 <= still <= clip_duration + 1e-9:
        raise ConfigError(f"{field} = {still:g} s is outside the clip (0 to {clip_duration:.3f} s)")
    return float(min(still, clip_duration))


def window_steps(config: SimulationConfig, clip_duration: float) -> int:
    """The number of steps of the simulated window from ``sim.start``. The clip plays: to the
    clip's end by default, and never past it. A still pose (``sim.still``) needs no frames: any
    ``sim.duration``, by default the clip's duration."""
    source = config.source
    if config.still is not None:
        duration = clip_duration if config.duration is None else config.duration
        n_steps = int(round(duration / config.h))
    else:
        duration = clip_duration - config.start if config.duration is None else config.duration
        if config.start + duration > clip_duration + 1e-9:
            raise ConfigError(
                f"{source}: sim.start + sim.duration = {config.start + duration:.3f} s "
                f"runs past the clip's end ({clip_duration:.3f} s); sim.still holds a pose for any duration"
            )
        # Rounded down when rounding up would run past the clip's end (by less than a step).
        n_steps = min(int(round(duration / config.h)), int(np.floor((clip_duration - config.start) / config.h + 1e-9)))
    if n_steps < 1:
        raise ConfigError(f"{source}: sim.duration is shorter than one step")
    return n_steps


def driven_bodies(character: Character, names: Sequence[str], source: str = "config") -> dict[int, str]:
    """``[sim] driven_joints`` resolved: each driven body (the root left out: it always is) and
    the entry that names it. An entry is a body (joint) name or a keyword of
    :func:`~neuromotor.model.skeleton.keyword_bodies` (``trunk``, ``pelvis``, ``legs``, ``arms``,
    ``head``, or a single body such as ``chest`` or ``left_hand``)."""
    model = character.model
    out: dict[int, str] = {}
    for i, name in enumerate(names):
        field = f"{source}: field 'sim.driven_joints[{i}]' = {name!r}"
        if not isinstance(name, str):
            raise ConfigError(f"{field} must be a body name or a keyword")
        if name in model.body_names:
            bodies: tuple[int, ...] = (model.body_names.index(name),)
        else:
            found = keyword_bodies(character, name)
            if found is None:
                raise ConfigError(
                    f"{field} matches no body; bodies are {', '.join(model.body_names)}, "
                    f"keywords are {', '.join(RESTRAINT_KEYWORDS)}"
                )
            if not found:
                labels = GROUP_KEYWORDS.get(name) or ()
                what = f"no body is labelled {' or '.join(labels)}" if labels else "no such body"
                raise ConfigError(f"{field} matches no body on this rig ({what}; neuromotor inspect shows the labels)")
            bodies = found
        for b in bodies:
            if b != 0:
                out.setdefault(b, name)
    return out


@compiler.jit
def _initial_gains(model: Model, traj: Trajectory, t0, local_axes, activation, tau_floor) -> Gains:
    """The template gains: :func:`make_gains` at the clip's start, the spline evaluation included
    (one program rather than a dozen eagerly compiled scalar ops); a run's (ks, kd) and reflex
    are put on them by :func:`~neuromotor.studies.gains.gains_for`."""
    return make_gains(model, traj.q(t0), local_axes, activation, tau_floor=tau_floor)


_zero = compiler.jit(unperturbed)


simulate_jit = compiler.jit(simulate)  # simulate_jit(sim, params): the StepOptions inside sim are static


@dataclasses.dataclass
class RunResult:
    perturbed: Rollout
    unperturbed: Rollout
    metrics: dict
    ball: ContactRollout | None = None  # the ball run: its state and contact record
    ground: ContactRollout | None = None  # a run on the ground without a ball: its contact record


def run(setup: Setup, check: bool = True) -> RunResult:
    """Perturbed and unperturbed rollouts plus the recovery metrics."""
    if setup.ball is not None:
        pert, base = ball_rollouts(setup, _zero(setup.pulses), check)
        n_ball = setup.ball.n_candidates
        metrics = run_metrics(setup, pert.run, base.run) | ball_metrics(pert, setup.ball)
        if setup.ground is not None:  # the bodies' ground: falls, sway and response as without a ball
            metrics |= ground_metrics(pert, n_ball)
            metrics |= balance_metrics(setup, pert, platform_offset(setup), com_path(setup.model, base.run.states.pos))
        metrics |= lcp_figures(pert.contact.step_residual, pert.contact.touching)
        return RunResult(pert.run, base.run, metrics, pert)
    if setup.ground is not None:
        pert, base = ground_rollouts(setup, _zero(setup.pulses), check)
        extra = ground_metrics(pert, 0) | lcp_figures(pert.contact.step_residual, pert.contact.touching)
        extra |= balance_metrics(setup, pert, platform_offset(setup), com_path(setup.model, base.run.states.pos))
        return RunResult(pert.run, base.run, run_metrics(setup, pert.run, base.run) | extra, ground=pert)
    model, sim = setup.model, setup.sim_model
    pert = simulate_jit(sim, setup.params)
    base = simulate_jit(sim, Params(setup.gains, _zero(setup.pulses)))
    if check:
        check_rollout(model, base)
        check_rollout(model, pert)
    return RunResult(pert, base, run_metrics(setup, pert, base))


def run_metrics(setup: Setup, pert: Rollout, base: Rollout) -> dict:
    """Recovery metrics of d(t) by ``setup.config.metric`` (geodesic joint angles by default;
    :mod:`neuromotor.studies.metrics`) and the unperturbed run's error against the mocap."""
    start = onset(setup.config.perturbations, setup.config.ball, default=float(np.asarray(setup.ref.time)[0]))
    metric = setup.config.metric
    dev, tracking, residual, violation = _metric_arrays(metric, setup.model, pert, base, setup.ref)
    out = mx.recovery_metrics(pert.time, dev, start)
    out["unperturbed_rms_error_deg"] = float(tracking)
    out["max_kkt_residual"] = float(residual)
    out["max_constraint_violation"] = float(violation)
    out["diverged"] = bool(int(pert.diverged_step) >= 0 or int(base.diverged_step) >= 0)
    return out


@functools.partial(compiler.jit, static_argnames=("metric",))
def _metric_arrays(metric: str, model: Model, pert: Rollout, base: Rollout, ref: Reference):
    """The array reductions of :func:`run_metrics` as one program (not a dozen eager ops): d(t),
    the unperturbed run's RMS error against the mocap (over samples and joints, or DOFs for
    ``euler``), the largest KKT residual and constraint violation."""
    dev = mx.run_deviation(metric, model, pert, base)
    if metric == "euler":
        track = mx.wrap_angle(base.theta - ref.theta[: base.theta.shape[0]])
    else:  # the simulated joints' local rotations against the mocap's on the grid
        local = mx.joint_quats(model, base.states.quat)
        track = mx.geodesic_angle(local, ref.rel_quat[: local.shape[0]])
    return (
        dev,
        jnp.rad2deg(jnp.sqrt(jnp.mean(track**2))),
        jnp.maximum(jnp.max(pert.residual), jnp.max(base.residual)),
        jnp.maximum(jnp.max(pert.violation), jnp.max(base.violation)),
    )


def deviation_curve(setup: Setup, pert: Rollout, base: Rollout, joints=None) -> np.ndarray:
    """d(t) (deg) of ``pert`` against ``base`` by ``setup.config.metric``, over ``joints`` (body
    indices; None: every simulated joint)."""
    return np.asarray(_deviation(setup.config.metric, setup.model, pert, base, joints))


def tracking_curve(setup: Setup, run_: Rollout) -> np.ndarray:
    """Per sample, the RMS error (deg) of a run against the mocap by ``setup.config.metric``:
    geodesic on the joints' local rotations against ``ref.rel_quat``, or over the Euler DOFs."""
    return np.asarray(_tracking(setup.config.metric, setup.model, run_, setup.ref))


@functools.partial(compiler.jit, static_argnames=("metric", "joints"))
def _deviation(metric, model, pert, base, joints):
    return mx.run_deviation(metric, model, pert, base, joints)


@functools.partial(compiler.jit, static_argnames=("metric",))
def _tracking(metric, model, run_, ref):
    if metric == "euler":
        return mx.deviation(run_.theta, ref.theta[: run_.theta.shape[0]])
    local = mx.joint_quats(model, run_.states.quat)
    return mx.rms_joint_angle_deg(local, ref.rel_quat[: local.shape[0]])
