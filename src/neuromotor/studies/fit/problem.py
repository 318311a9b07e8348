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

from neuromotor.config.specs import FEATURE_NAMES, TARGET_KINDS as KINDS, Surrogate, check_fit_parameters, onset
from neuromotor.errors import ConfigError
from neuromotor.model.skeleton import Model
from neuromotor.physics.control import Gains
from neuromotor.physics.dynamics import Params, Reference, Rollout, SimModel, StepOptions, simulate
from neuromotor.physics.perturbation import ForcePulses, build_pulses, stack_runs, unperturbed
from neuromotor.studies import metrics as mx
from neuromotor.studies.fit import parameters as fp
from neuromotor.studies.fit.surrogate import acceleration_deg, deviation_deg, joint_acceleration_deg, response_features
from neuromotor.studies.gains import gains_for


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
        return jax.vmap(lambda p: simulate(sim, Params(gains, p)))(self.pulses)

    def outputs(self, x: Float[Array, " p"]) -> tuple[Float[Array, " m"], Float[Array, "C T c"], Int[Array, " R"]]:
        """Model output y (flat), the curves to plot per case, and each run's diverged step.

        For feature targets the curves are, per case, the deviation d(t) (deg) and the
        acceleration a(t) (deg/s^2) of :func:`acceleration_deg`.
        """
        runs = self.rollouts(x)
        s = self.spec
        if s.kind == "joint_angles":
            cur = runs.theta[:, s.i0 : s.i1][:, :, jnp.asarray(s.columns)]
            return cur.reshape(-1), cur, runs.diverged_step
        if s.kind == "body_positions":
            cur = runs.states.pos[:, s.i0 : s.i1][:, :, jnp.asarray(s.columns)]
            return cur.reshape(-1), cur.reshape(cur.shape[0], cur.shape[1], -1), runs.diverged_step
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

    def residuals(self, x, target, weights) -> Float[Array, " m"]:
        """Pure-JAX residual r(x) = w * (y(x) - target)."""
        return weights * (self.outputs(x)[0] - target)


def loss(problem: FitProblem, x, target, weights) -> Float[Array, ""]:
    """The minimized objective L(x) = 1/2 ||w * (y(x) - target)||^2 (pure JAX)."""
    r = problem.residuals(x, target, weights)
    return 0.5 * jnp.sum(r**2)


def make_problem(
    setup, kind: str, columns=(), window=None, features=FEATURE_NAMES, names=fp.DEFAULT, **surrogate
) -> FitProblem:
    """A :class:`FitProblem` over the perturbation cases of ``setup.config.perturbations``.

    Each ``[[perturbation]]`` entry is one case (one rollout), of any kind and shape (the
    shape is an array leaf). ``window`` = (t0, t1) in clip
    seconds (default: the whole simulation).
    """
    from neuromotor.studies.simulate import body_lookup, direction_lookup
    from neuromotor.studies.targets import window_indices

    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    cfg = setup.config
    specs = cfg.perturbations
    if not specs:
        raise ConfigError(f"{cfg.source}: a fit needs at least one [[perturbation]] (one per case)")
    index = body_lookup(setup.model, cfg.source, setup.character)
    direction_of = direction_lookup(setup.character, cfg.source, cfg.still)
    times = np.asarray(setup.ref.time)
    per_case = [build_pulses([s], setup.model, setup.options.h, index, direction_of, times) for s in specs]
    if kind == "features":
        per_case = per_case + [unperturbed(per_case[0])]
    batch = jax.tree_util.tree_map(jnp.asarray, stack_runs(per_case))  # cases of any kinds: one program
    sim_time = np.asarray(setup.ref.time[: setup.options.n_steps + 1])
    if window is None:
        window = (float(sim_time[0]), float(sim_time[-1]))
    i0, i1 = window_indices(sim_time, window, cfg.source, "fit.window")
    surrogate.setdefault("metric", cfg.metric)
    spec = ResponseSpec(
        kind, tuple(int(c) for c in columns), i0, i1, tuple(features) if kind == "features" else (), **surrogate
    )
    start = jnp.asarray([onset([s]) for s in specs])  # each case measured from its own onset
    names = check_fit_parameters(names, setup.gains.reflex is not None, cfg.source)
    return FitProblem(setup.model, setup.gains, batch, setup.ref, start, setup.options, spec, names)
