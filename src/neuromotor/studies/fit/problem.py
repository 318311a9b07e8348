"""The fit problem: parameters x = log of the fitted values (default (ks, kd); any subset of
:data:`~neuromotor.studies.fit.parameters.PARAMETERS`) -> model output y(x) over C perturbation cases,
simulated jointly by one ``vmap`` over the case axis of a
:class:`~neuromotor.physics.perturbation.ForcePulses`."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor.config.specs import (
    BODY_TARGET_KINDS,
    FEATURE_NAMES,
    TARGET_KINDS as KINDS,
    Surrogate,
    check_fit_parameters,
    onset,
)
from neuromotor.errors import ConfigError
from neuromotor.model.skeleton import Model
from neuromotor.physics.contact import ContactScene, simulate_contact
from neuromotor.physics.control import Gains
from neuromotor.physics.dynamics import Params, Reference, Rollout, SimModel, StepOptions, simulate
from neuromotor.physics.perturbation import ForcePulses, build_pulses, stack_runs, unperturbed
from neuromotor.studies import metrics as mx
from neuromotor.studies.fit import observables as ob, parameters as fp
from neuromotor.studies.fit.surrogate import acceleration_deg, deviation_deg, joint_acceleration_deg, response_features
from neuromotor.studies.gains import gains_for

MULTIPLE = "multiple"  # ResponseSpec.kind of several targets fitted together


@dataclasses.dataclass(frozen=True)
class Part:
    """One trajectory target's share of the model output (static).

    ``joint_angles``: the DOFs ``columns`` (rad); ``body_positions``: the COMs of the bodies
    ``columns`` (m, x y z each); ``body_angle`` / ``body_position``: one curve, the observable of
    :mod:`.observables` of body ``body`` relative to body ``other`` (-1: the world), about/along
    the problem's ``axes[:, slot]``; ``lever`` is the point from the body's COM (body frame, m).
    """

    kind: str
    columns: tuple[int, ...] = ()
    body: int = -1
    other: int = -1
    lever: tuple[float, float, float] = (0.0, 0.0, 0.0)
    slot: int = 0

    @property
    def width(self) -> int:
        """Curve columns it adds."""
        if self.kind in BODY_TARGET_KINDS:
            return 1
        return len(self.columns) * (3 if self.kind == "body_positions" else 1)


@dataclasses.dataclass(frozen=True)
class ResponseSpec:
    """What the model output y(x) is (static: it fixes shapes).

    kind: joint_angles | body_positions | features. columns: DOF indices (joint angles, and the
    DOFs of the deviation signal for features; empty = all) or body indices. Samples
    ``i0 <= k < i1`` of the simulation grid form the window. Feature surrogates: ``beta``
    (1/deg) sharpens the soft peak, ``width`` is the sigmoid width as a fraction of the
    threshold, and the recovery threshold is ``max(fraction * peak, floor_deg)``.
    ``accel_beta`` (s^2/deg) sharpens the softmax-weighted peak of the angular acceleration.
    ``metric``: features from the geodesic joint deviation (the joints of ``columns``' DOFs) or
    from the Euler-DOF one. Joint-angle targets stay per Euler DOF (the target files give angles).
    """

    kind: str
    columns: tuple[int, ...]
    i0: int
    i1: int
    features: tuple[str, ...] = ()
    beta: float = Surrogate.beta
    width: float = Surrogate.width
    fraction: float = Surrogate.fraction
    floor_deg: float = Surrogate.floor_deg
    accel_beta: float = Surrogate.accel_beta
    metric: str = "geodesic"  # the deviation of feature targets ([sim] metric; studies.metrics)
    # Trajectory targets: the curves, side by side (y = curves (C, T, sum of widths) flattened);
    # () = one part of ``kind`` over ``columns``.
    parts: tuple[Part, ...] = ()

    @property
    def trajectory_parts(self) -> tuple[Part, ...]:
        if self.parts or self.kind == "features":
            return self.parts
        return (Part(self.kind, self.columns),)


class FitProblem(eqx.Module):
    """Model, reference, fixed gain scaling and a batch of C perturbation cases.

    ``pulses`` has a leading case axis on every leaf; for feature targets its last member is
    the unperturbed twin (magnitudes zero), so the batch holds C + 1 runs.
    """

    model: Model
    gains: Gains
    pulses: ForcePulses
    ref: Reference
    start: Float[Array, " C"]  # start of each case's (first) pulse, clip seconds
    options: StepOptions = eqx.field(static=True)
    spec: ResponseSpec = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True, default=fp.DEFAULT)  # the fitted parameters, in x's order
    # Body targets (Part.slot): each case's axis as a world unit vector at its onset, and the
    # onset sample (the last simulation sample at or before the case's onset).
    axes: Float[Array, "C K 3"] | None = None
    onset_step: Int[Array, " C"] | None = None
    # The ground under a free root (None: no contact): every case is then the contact rollout
    # that ``neuromotor simulate`` runs, with the postural loop of ``gains.balance``.
    scene: ContactScene | None = None

    @property
    def n_cases(self) -> int:
        n = self.pulses.magnitude.shape[0]
        return n - 1 if self.spec.kind == "features" else n

    @property
    def n_params(self) -> int:
        return len(self.names)

    def gains_at(self, x: Float[Array, " p"]) -> Gains:
        """The controller with the fitted parameters at exp(x), the others as in ``gains``."""
        return gains_for(self.gains, **dict(zip(self.names, jnp.exp(x))))

    def rollouts(self, x: Float[Array, " p"]) -> Rollout:
        """Every case's rollout at parameters exp(x), one vmap over the case axis."""
        gains = self.gains_at(x)
        sim = SimModel(self.model, self.ref, self.options)
        if self.scene is not None:
            scene = self.scene
            return jax.vmap(lambda p: simulate_contact(sim, Params(gains, p), scene).run)(self.pulses)
        return jax.vmap(lambda p: simulate(sim, Params(gains, p)))(self.pulses)

    def outputs(self, x: Float[Array, " p"]) -> tuple[Float[Array, " m"], Float[Array, "C T c"], Int[Array, " R"]]:
        """Model output y (flat), the curves to plot per case, and each run's diverged step.

        For feature targets the curves are, per case, the deviation d(t) (deg) and the
        acceleration a(t) (deg/s^2) of :func:`acceleration_deg`.
        """
        runs = self.rollouts(x)
        s = self.spec
        if s.kind != "features":
            cur = jnp.concatenate([self.part_curves(runs, p) for p in s.trajectory_parts], -1)
            return cur.reshape(-1), cur, runs.diverged_step
        time = runs.time[0, s.i0 : s.i1]
        h = self.options.h
        if s.metric == "geodesic":
            rows, mask = mx.dof_selection(self.model, s.columns) if s.columns else (mx.joint_rows(self.model), None)
            quat, omega = runs.states.quat[:, s.i0 : s.i1], runs.states.omega[:, s.i0 : s.i1]
            local = lambda c: mx.joint_quats(self.model, quat[c])
            curve = lambda c: (
                mx.selected_deviation_deg(local(c), local(-1), rows, np.ones((len(rows), 3)) if mask is None else mask),
                joint_acceleration_deg(self.model, quat[c], omega[c], quat[-1], omega[-1], h, rows, mask),
            )
        else:
            base = runs.theta[-1, s.i0 : s.i1]
            dofs = jnp.asarray(s.columns) if s.columns else None
            base_rate = runs.theta_dot[-1, s.i0 : s.i1]
            curve = lambda c: (
                deviation_deg(runs.theta[c, s.i0 : s.i1], base, dofs),
                acceleration_deg(runs.theta_dot[c, s.i0 : s.i1], base_rate, h, dofs),
            )
        feats, devs = [], []
        for c in range(self.n_cases):
            dev, acc = curve(c)
            f = response_features(time, dev, self.start[c], s, acc)
            feats.append(jnp.stack([f[name] for name in s.features]))
            devs.append(jnp.stack([dev, acc], axis=-1))
        return jnp.concatenate(feats), jnp.stack(devs), runs.diverged_step

    def part_curves(self, runs: Rollout, part: Part) -> Float[Array, "C T w"]:
        """One trajectory part's curves inside the window, every case (SI units: rad, m)."""
        s = self.spec
        if part.kind == "joint_angles":
            return runs.theta[:, s.i0 : s.i1][:, :, jnp.asarray(part.columns)]
        if part.kind == "body_positions":
            cur = runs.states.pos[:, s.i0 : s.i1][:, :, jnp.asarray(part.columns)]
            return cur.reshape(cur.shape[0], cur.shape[1], -1)
        if self.axes is None or self.onset_step is None:
            raise ValueError("a body target needs the problem's axes and onset steps (make_problem(..., axes=...))")
        quat, pos = runs.states.quat, runs.states.pos  # (C, S1, B, 4), (C, S1, B, 3)
        qb, pb = quat[:, :, part.body], pos[:, :, part.body]
        if part.other >= 0:
            qo, po = quat[:, :, part.other], pos[:, :, part.other]
        else:
            qo = jnp.broadcast_to(ob.identity_quats(1, quat.dtype), qb.shape)
            po = jnp.zeros_like(pb)
        axis = self.axes[:, part.slot]
        if part.kind == "body_angle":
            cur = jax.vmap(ob.body_angle)(qb, qo, self.onset_step, axis)
        else:
            lever = jnp.asarray(part.lever, pos.dtype)
            cur = jax.vmap(lambda a, b, c, d, k, e: ob.body_displacement(a, b, lever, c, d, k, e))(
                pb, qb, po, qo, self.onset_step, axis
            )
        return cur[:, s.i0 : s.i1, None]

    def residuals(self, x, target, weights) -> Float[Array, " m"]:
        """Pure-JAX residual r(x) = w * (y(x) - target)."""
        return weights * (self.outputs(x)[0] - target)


def loss(problem: FitProblem, x, target, weights) -> Float[Array, ""]:
    """The minimized objective L(x) = 1/2 ||w * (y(x) - target)||^2 (pure JAX)."""
    r = problem.residuals(x, target, weights)
    return 0.5 * jnp.sum(r**2)


def make_problem(
    setup,
    kind: str,
    columns=(),
    window=None,
    features=FEATURE_NAMES,
    names=fp.DEFAULT,
    parts: tuple[Part, ...] = (),
    axes=None,
    **surrogate,
) -> FitProblem:
    """A :class:`FitProblem` over the perturbation cases of ``setup.config.perturbations``.

    Each ``[[perturbation]]`` entry is one case (one rollout), of any kind and shape (the
    shape is an array leaf). ``window`` = (t0, t1) in clip
    seconds (default: the whole simulation). ``parts``: several trajectory targets side by side
    (``kind`` is then the one part's kind or ``"multiple"``); ``axes`` (C, K, 3): the world axis
    of each case's body target ``slot`` k at the case's onset.
    """
    from neuromotor.studies.ground import ground_scene
    from neuromotor.studies.simulate import body_lookup
    from neuromotor.studies.targets import window_indices

    if kind not in KINDS and kind != MULTIPLE:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    cfg = setup.config
    specs = cfg.perturbations
    if not specs:
        raise ConfigError(f"{cfg.source}: a fit needs at least one [[perturbation]] (one per case)")
    index = body_lookup(setup.model, cfg.source, setup.character)
    direction_of = setup.direction_of
    times = np.asarray(setup.ref.time)
    pivot = setup.tilt_pivot  # a tilt turns the ground where every command turns it
    per_case = [build_pulses([s], setup.model, setup.options.h, index, direction_of, times, pivot) for s in specs]
    if kind == "features":
        per_case = per_case + [unperturbed(per_case[0])]
    batch = jax.tree_util.tree_map(jnp.asarray, stack_runs(per_case))  # cases of any kinds: one program
    sim_time = np.asarray(setup.ref.time[: setup.options.n_steps + 1])
    if window is None:
        window = (float(sim_time[0]), float(sim_time[-1]))
    i0, i1 = window_indices(sim_time, window, cfg.source, "fit.window")
    surrogate.setdefault("metric", cfg.metric)
    spec = ResponseSpec(
        kind,
        tuple(int(c) for c in columns),
        i0,
        i1,
        tuple(features) if kind == "features" else (),
        parts=tuple(parts),
        **surrogate,
    )
    onsets = [onset([s]) for s in specs]  # each case measured from its own onset
    start = jnp.asarray(onsets)
    names = check_fit_parameters(
        names, setup.gains.reflex is not None, cfg.source, has_balance=setup.gains.balance is not None
    )
    steps = np.array([onset_step(sim_time, t) for t in onsets])
    return FitProblem(
        setup.model,
        setup.gains,
        batch,
        setup.ref,
        start,
        setup.options,
        spec,
        names,
        None if axes is None else jnp.asarray(np.asarray(axes, np.float64)),
        jnp.asarray(steps),
        None if setup.ground is None else ground_scene(setup.ground),
    )


def onset_step(sim_time, t: float) -> int:
    """The last simulation sample at or before clip time ``t`` (the first sample if ``t`` is before it)."""
    k = int(np.searchsorted(np.asarray(sim_time), float(t) + 1e-9, side="right")) - 1
    return int(np.clip(k, 0, len(sim_time) - 1))
