"""Gain calibration: the single (ks, kd) whose simulated reaction to a hit matches a target.

Parameters. ``x = (log ks, log kd)``: the gains stay positive and both are fitted on the scale
on which they matter (a factor, not an increment).

Residuals. Given C perturbation cases (magnitudes, directions, bodies, start times), simulated
jointly by one ``vmap`` over the case axis of a :class:`~neuromotor.physics.perturbation.ForcePulses`,
the model output y(x) stacks over cases either

* the simulated trajectory inside the fit window (joint angles of all or named DOFs, or body
  COM positions), or
* smooth response features of the deviation from the unperturbed twin (peak deviation, time to
  peak, recovery time, overshoot, peak angular acceleration), the unperturbed run being one
  extra member of the batch;

and the residual is ``r(x) = w * (y(x) - y_target)`` with per-entry weights w (a per-DOF
weight, or 1/sd for a feature). **What is minimized**: ``L(x) = 1/2 ||r(x)||^2``, the residual
being taken through the whole rollout (every step of the ``lax.scan``).

Derivatives. ``J = dr/dx`` by ``jax.jacfwd`` (two parameters: two tangents through the scan),
or in reverse mode (``jacobian="reverse"``: one recorded forward pass, then one backward pass
per residual, a few at a time), which pays off when residuals are few (feature targets) or
parameters many.

Solvers, by name (:data:`SOLVERS`): optimistix Levenberg-Marquardt, Gauss-Newton (with an Armijo
backtracking line search, :class:`GaussNewtonLineSearch`) and BFGS (on L), jaxopt
Levenberg-Marquardt and L-BFGS (on L). All of them see the same residual function:
:class:`ResponseEvaluator` compiles ``x -> (y, dy/dx)`` once, and :func:`residual_function`
exposes it to the solvers as a JAX function with a custom JVP (``J @ t``) through
``jax.pure_callback``. Without this each solver would trace and compile its own copy of the
rollout and its derivative, which costs a minute or more per solver; with it, switching solver
costs nothing and every solver can be stepped one iteration at a time from Python (progress
bar, divergence checks). The pure-JAX path (:meth:`FitProblem.residuals`, :func:`loss`) stays
available for ``jit``/``grad``/``vmap`` by users.

After the fit (:class:`FitResult`): the Gauss-Newton covariance of (log ks, log kd),
``s^2 (J^T J)^-1`` with ``s^2 = ||r||^2 / (m - 2)``, standard errors (also of ks and kd by the
delta method), the final residual, iteration and evaluation counts, wall time, and a status:
``converged``, ``converged (loss flat)`` (the step limit was reached with the loss flat: relative
change below ``LOSS_FLAT_RTOL`` in each of the last ``LOSS_FLAT_ITERATIONS`` iterations; counts as
converged), ``max_steps``, ``diverged`` (the rollout at the returned gains blew up) or
``nonfinite`` (the solver produced NaN; the last finite iterate is returned instead). A fit
never returns NaN gains; with ``strict=True`` anything but the two converged statuses raises
:class:`FitError`.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import math
import pathlib
import time as _time
from typing import Callable

import equinox as eqx
import jax
import optimistix as optx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor.io.atomic import atomic_path
from neuromotor import compiler
from neuromotor.studies import metrics as mx
from neuromotor.physics.control import Gains
from neuromotor.physics.dynamics import Reference, Rollout, SimConfig, rollout
from neuromotor.physics.perturbation import ForcePulses
from neuromotor.model.skeleton import Model

SOLVERS = ("optimistix_lm", "optimistix_gn", "optimistix_bfgs", "jaxopt_lm", "jaxopt_lbfgs")
KINDS = ("joint_angles", "body_positions", "features")
FEATURE_NAMES = ("peak_deviation_deg", "time_to_peak_s", "recovery_time_s", "overshoot_deg",
                 "peak_acceleration_deg_s2")


class FitError(RuntimeError):
    """The fit failed (no convergence, diverged rollout, non-finite iterate); carries the result."""

    def __init__(self, message: str, result: "FitResult | None" = None):
        super().__init__(message)
        self.result = result


# ----------------------------------------------------------------------------------------------
# The problem: x -> model output y(x)


@dataclasses.dataclass(frozen=True)
class ResponseSpec:
    """What the model output y(x) is (static: it fixes shapes).

    kind: joint_angles | body_positions | features. columns: DOF indices (joint angles, and the
    DOFs of the deviation signal for features; empty = all) or body indices. Samples
    ``i0 <= k < i1`` of the simulation grid form the window. Feature surrogates: ``beta``
    (1/deg) sharpens the soft peak, ``width`` is the sigmoid width as a fraction of the
    threshold, and the recovery threshold is ``max(fraction * peak, floor_deg)``.
    ``accel_beta`` (s^2/deg) sharpens the softmax-weighted peak of the angular acceleration.
    """

    kind: str
    columns: tuple[int, ...]
    i0: int
    i1: int
    features: tuple[str, ...] = ()
    beta: float = 20.0
    width: float = 0.1
    fraction: float = mx.RECOVERY_FRACTION
    floor_deg: float = mx.RECOVERY_FLOOR_DEG
    accel_beta: float = 0.1


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
    sim: SimConfig = eqx.field(static=True)
    spec: ResponseSpec = eqx.field(static=True)

    @property
    def n_cases(self) -> int:
        n = self.pulses.magnitude.shape[0]
        return n - 1 if self.spec.kind == "features" else n

    def gains_at(self, x: Float[Array, " 2"]) -> Gains:
        return dataclasses.replace(self.gains, ks=jnp.exp(x[0]), kd=jnp.exp(x[1]))

    def rollouts(self, x: Float[Array, " 2"]) -> Rollout:
        """Every case's rollout at gains exp(x), one vmap over the case axis."""
        gains = self.gains_at(x)
        return jax.vmap(lambda p: rollout(self.model, gains, p, self.ref, self.sim))(self.pulses)

    def outputs(self, x: Float[Array, " 2"]) -> tuple[Float[Array, " m"], Float[Array, "C T c"], Int[Array, " R"]]:
        """Model output y (flat), the curves to plot per case, and each run's diverged step.

        For feature targets the curves are, per case, the deviation d(t) (deg) and the
        acceleration a(t) (deg/s^2) of :func:`acceleration_deg`.
        """
        runs = self.rollouts(x)
        s = self.spec
        if s.kind == "joint_angles":
            cur = runs.theta[:, s.i0:s.i1][:, :, jnp.asarray(s.columns)]
            return cur.reshape(-1), cur, runs.diverged_step
        if s.kind == "body_positions":
            cur = runs.states.pos[:, s.i0:s.i1][:, :, jnp.asarray(s.columns)]
            return cur.reshape(-1), cur.reshape(cur.shape[0], cur.shape[1], -1), runs.diverged_step
        time = runs.time[0, s.i0:s.i1]
        base = runs.theta[-1, s.i0:s.i1]
        dofs = jnp.asarray(s.columns) if s.columns else None
        base_rate = runs.theta_dot[-1, s.i0:s.i1]
        h = self.sim.h
        feats, devs = [], []
        for c in range(self.n_cases):
            dev = deviation_deg(runs.theta[c, s.i0:s.i1], base, dofs)
            acc = acceleration_deg(runs.theta_dot[c, s.i0:s.i1], base_rate, h, dofs)
            f = response_features(time, dev, self.start[c], s, acc)
            feats.append(jnp.stack([f[name] for name in s.features]))
            devs.append(jnp.stack([dev, acc], axis=-1))
        return jnp.concatenate(feats), jnp.stack(devs), runs.diverged_step

    def residuals(self, x, target, weights) -> Float[Array, " m"]:
        """Pure-JAX residual r(x) = w * (y(x) - target)."""
        return weights * (self.outputs(x)[0] - target)


def deviation_deg(theta, theta_ref, dofs=None) -> Float[Array, " T"]:
    """:func:`neuromotor.studies.metrics.deviation` (wrapped differences) with a derivative at zero deviation.

    Before the hit the perturbed and unperturbed runs are identical; d sqrt(u) = du / 2 sqrt(u)
    is then 0/0 and would put NaN in the Jacobian. Where u = 0 the derivative is taken as 0
    (the double-``where`` keeps the NaN out of the unselected branch too).
    """
    return _rms_deg(mx.wrap_angle(theta - theta_ref), dofs)


def _rms_deg(diff, dofs=None) -> Float[Array, " T"]:
    """Zero-safe RMS over DOFs of ``diff`` (radians, or rad/s^2), scaled by 180/pi."""
    if dofs is not None:
        diff = diff[:, dofs]
    u = jnp.mean(diff**2, axis=-1)
    pos = u > 0
    return jnp.rad2deg(jnp.where(pos, jnp.sqrt(jnp.where(pos, u, 1.0)), 0.0))


def acceleration_deg(theta_dot, theta_dot_ref, h: float, dofs=None) -> Float[Array, " T"]:
    """Angular acceleration of the deviation, ``a(t) = rms_i d^2/dt^2 (theta_i - theta_ref_i)``
    in deg/s^2 over ``dofs`` (default all), per sample of the step grid.

    The second derivative is the central difference of the simulated joint rates,
    ``(w[k+1] - w[k-1]) / 2h`` with ``w = theta_dot - theta_dot_ref`` (the rates come from the
    body angular velocities, so this is one difference, not the two of a second difference of
    the angles); the first and last samples, which lack a neighbour, are 0. The RMS over DOFs
    matches :func:`deviation_deg` (same zero-safe square root).
    """
    w = theta_dot - theta_dot_ref
    acc = (w[2:] - w[:-2]) / (2.0 * h)
    inner = _rms_deg(acc, dofs)  # a rate, not an angle: no wrapping
    return jnp.pad(inner, (1, 1))


def soft_max_weighted(signal, beta: float):
    """Smooth peak of a signal: the softmax(beta * signal)-weighted mean of the signal.

    Below the exact maximum by about ``1 / (2 beta)`` near a rounded peak, whatever the
    signal's length (the log-sum-exp :func:`neuromotor.studies.metrics.soft_peak` is low by up to
    ``log(T) / beta``, too much at the smoothing scale an acceleration in deg/s^2 needs).
    """
    w = jax.nn.softmax(beta * signal)
    return jnp.sum(w * signal)


def exact_peak_acceleration(acc) -> float:
    """The non-smooth counterpart of the ``peak_acceleration_deg_s2`` surrogate: max a(t)."""
    return float(np.max(np.asarray(acc)))


def loss(problem: FitProblem, x, target, weights) -> Float[Array, ""]:
    """The minimized objective L(x) = 1/2 ||w * (y(x) - target)||^2 (pure JAX)."""
    r = problem.residuals(x, target, weights)
    return 0.5 * jnp.sum(r**2)


def soft_recovery(time, dev, start, threshold, width: float):
    """Smooth time from ``start`` until d(t) falls below ``threshold`` for good.

    A sample counts while d is still above threshold at that sample *or any later one*:
    ``1 - prod_{s >= t} (1 - above(s))`` with a sigmoid ``above`` (a reverse cumulative
    product, summed in log space). Summed over the samples after ``start`` this is the time
    to the last crossing. The surrogate of :mod:`neuromotor.studies.metrics` integrates the time spent
    above threshold instead, which leaves out the rise before the first crossing and any dip
    below threshold before the last one.
    """
    dt = time[1] - time[0]
    gate = jax.nn.sigmoid((time - start) / dt)
    z = (dev - threshold) / (width * threshold)
    log_below = jax.nn.log_sigmoid(-z)  # log(1 - above)
    never_again = jnp.exp(jnp.cumsum(log_below[::-1])[::-1])
    return jnp.sum(gate * (1.0 - never_again)) * dt


def response_features(time, dev, start, spec: ResponseSpec, acc=None) -> dict:
    """Smooth peak deviation, time to peak, recovery time and overshoot of a deviation signal,
    and (given the acceleration signal ``acc`` of :func:`acceleration_deg`) its peak angular
    acceleration.

    Exact counterparts: :func:`neuromotor.studies.metrics.recovery_metrics` (time to peak there is
    absolute; here it is measured from ``start``) and :func:`exact_peak_acceleration`.
    """
    peak = mx.soft_peak(dev, spec.beta)
    t_peak = mx.soft_time_of_peak(time, dev, spec.beta)
    thr = jnp.maximum(spec.fraction * peak, spec.floor_deg)
    rec = soft_recovery(time, dev, start, thr, spec.width)
    # First return below threshold after the peak: the running product of "still above"
    # indicators is ~1 until the first drop and ~0 after, so its integral is the time to it.
    dt = time[1] - time[0]
    after_peak = jax.nn.sigmoid((time - t_peak) / dt)
    still = jnp.cumprod(1.0 - after_peak * (1.0 - jax.nn.sigmoid((dev - thr) / (spec.width * thr))))
    t_return = t_peak + jnp.sum(still * after_peak) * dt
    overshoot = mx.soft_overshoot(time, dev, t_return, spec.beta)
    out = {"peak_deviation_deg": peak, "time_to_peak_s": t_peak - start,
           "recovery_time_s": rec, "overshoot_deg": overshoot}
    if acc is not None:
        out["peak_acceleration_deg_s2"] = soft_max_weighted(acc, spec.accel_beta)
    return out


# ----------------------------------------------------------------------------------------------
# One compiled evaluation shared by every solver


@dataclasses.dataclass
class Evaluation:
    x: np.ndarray
    y: np.ndarray  # (m,)
    jac: np.ndarray  # (m, 2)
    curves: np.ndarray  # (C, T, c)
    diverged: np.ndarray  # (R,) first bad step per run, -1 if fine


class ResponseEvaluator:
    """Compiles ``x -> (y, dy/dx, curves, diverged)`` once and caches recent evaluations.

    The problem is an argument of the compiled function, so a new target, weights or even
    new perturbation magnitudes reuse the compiled code (only shapes and static settings
    matter).
    """

    def __init__(self, problem: FitProblem, jacobian: str = "forward", cache_size: int = 16):
        if jacobian not in ("forward", "reverse"):
            raise ValueError(f"jacobian must be 'forward' or 'reverse', got {jacobian!r}")
        self.problem = problem
        self.jacobian = jacobian
        self._fn = _compiled_response(jacobian)
        self._cache: collections.OrderedDict[bytes, Evaluation] = collections.OrderedDict()
        self._size = cache_size
        self.n_evals = 0
        self.seconds = 0.0
        self.diverged_evals: list[tuple[np.ndarray, int, int]] = []  # (x, run, step)

    def __call__(self, x) -> Evaluation:
        x = np.asarray(x, np.float64).reshape(2)
        key = x.tobytes()
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        t0 = _time.perf_counter()
        y, jac, curves, div = jax.device_get(self._fn(self.problem, jnp.asarray(x)))
        self.seconds += _time.perf_counter() - t0
        self.n_evals += 1
        ev = Evaluation(x.copy(), np.asarray(y), np.asarray(jac), np.asarray(curves), np.asarray(div))
        bad = np.nonzero(ev.diverged >= 0)[0]
        if bad.size:
            self.diverged_evals.append((x.copy(), int(bad[0]), int(ev.diverged[bad[0]])))
        self._cache[key] = ev
        if len(self._cache) > self._size:
            self._cache.popitem(last=False)
        return ev

    def with_problem(self, problem: FitProblem) -> "ResponseEvaluator":
        """A fresh cache over another problem of the same shapes (same compiled code)."""
        return ResponseEvaluator(problem, self.jacobian, self._size)


_COMPILED: dict[str, Callable] = {}
REVERSE_BATCH = 8  # backward passes run together in reverse mode


def _compiled_response(jacobian: str):
    # Module-level so every evaluator (and every test) shares one jit cache entry per mode.
    if jacobian not in _COMPILED:

        def fn(problem: FitProblem, x):
            if jacobian == "forward":
                def y_aux(x):
                    y, curves, div = problem.outputs(x)
                    return y, (y, curves, div)

                jac, (y, curves, div) = jax.jacfwd(y_aux, has_aux=True)(x)
                return y, jac, curves, div
            # Reverse: one forward pass records the tape, then one backward pass per residual,
            # REVERSE_BATCH at a time (jax.jacrev would run all m of them at once, holding m
            # copies of the backward state). Worth it when residuals are few (feature targets)
            # or parameters many; for 2 gains and a trajectory, forward mode is far cheaper.
            (y, curves, div), vjp = jax.vjp(problem.outputs, x, has_aux=False)
            eye = jnp.eye(y.shape[0], dtype=y.dtype)
            zc, zd = jnp.zeros_like(curves), jnp.zeros(div.shape, jax.dtypes.float0)
            rows = jax.lax.map(lambda e: vjp((e, zc, zd))[0], eye, batch_size=REVERSE_BATCH)
            return y, rows, curves, div

        _COMPILED[jacobian] = compiler.jit(fn)
    return _COMPILED[jacobian]


def residual_function(evaluator: ResponseEvaluator, target, weights) -> Callable:
    """r(x) = w * (y(x) - target) as a JAX function for the solvers.

    Its value comes from the shared compiled evaluation through ``jax.pure_callback``; its
    derivative is the custom JVP ``J @ t`` with J from the same evaluation, linear in t, so
    forward mode, ``linearize`` and reverse mode (transposition) all work.
    """
    target = np.asarray(target, np.float64)
    weights = np.asarray(weights, np.float64)
    m = target.size
    shapes = (jax.ShapeDtypeStruct((m,), jnp.float64), jax.ShapeDtypeStruct((m, 2), jnp.float64))

    def host(x):
        ev = evaluator(x)
        return weights * (ev.y - target), weights[:, None] * ev.jac

    def call(x):
        return jax.pure_callback(host, shapes, x, vmap_method="sequential")

    @jax.custom_jvp
    def r(x):
        return call(x)[0]

    @r.defjvp
    def r_jvp(primals, tangents):
        (x,), (t,) = primals, tangents
        val, jac = call(x)
        return val, jac @ t

    return r


# ----------------------------------------------------------------------------------------------
# Solvers


@dataclasses.dataclass
class SolverOptions:
    """Stopping rules. optimistix: relative/absolute change of y and of the objective
    (``rtol``, ``atol``). jaxopt: gradient norm below ``gtol`` times its value at the start."""

    max_steps: int = 100
    rtol: float = 1e-9
    atol: float = 1e-10
    gtol: float = 1e-9


class GaussNewtonLineSearch(optx.AbstractGaussNewton):
    """Gauss-Newton steps (normal equations, no damping) with a backtracking Armijo line
    search. optimistix's plain ``GaussNewton`` takes every full step; from 3x-off gains the
    first full step in log space can overshoot to gains where the rollout diverges (seen:
    ks = 2e42), so the step length is backtracked until the loss decreases."""

    rtol: float
    atol: float
    norm: Callable
    descent: optx.NewtonDescent
    search: optx.BacktrackingArmijo
    verbose: Callable

    def __init__(self, rtol: float, atol: float):
        plain = optx.GaussNewton(rtol=rtol, atol=atol)
        self.rtol, self.atol, self.norm, self.verbose = rtol, atol, plain.norm, plain.verbose
        self.descent = optx.NewtonDescent()
        self.search = optx.BacktrackingArmijo()


def _optimistix_loop(solver, fn, y0, f_struct, opts: SolverOptions, on_iter):
    args, options, tags = None, {}, frozenset()
    state = solver.init(fn, y0, args, options, f_struct, None, tags)
    dyn0, static = eqx.partition(state, eqx.is_array)

    @jax.jit
    def terminate(y, dyn):
        return solver.terminate(fn, y, args, options, eqx.combine(static, dyn), tags)

    @jax.jit
    def step(y, dyn):
        new_y, new_state, _ = solver.step(fn, y, args, options, eqx.combine(static, dyn), tags)
        # As optimistix's own loop: terminate() looks at the previous y and the new state.
        done, res = solver.terminate(fn, y, args, options, new_state, tags)
        return new_y, eqx.partition(new_state, eqx.is_array)[0], done, res

    y, dyn = y0, dyn0
    done, res = terminate(y, dyn)
    k = 0
    ok = optx.RESULTS.successful
    while not bool(done) and bool(res == ok) and k < opts.max_steps:
        y, dyn, done, res = step(y, dyn)
        k += 1
        if not on_iter(k, np.asarray(y)):
            break
    converged = bool(done) and bool(res == ok)
    if converged:
        message = ""
    elif bool(res == ok):
        message = "maximum number of steps reached"
    else:
        try:
            message = str(optx.RESULTS[res])
        except Exception:  # the message lookup is an optimistix internal
            message = "optimistix reported a failure"
    return np.asarray(y), k, converged, message


def _jaxopt_loop(solver, x0, opts: SolverOptions, on_iter, tol):
    state = solver.init_state(x0)
    update = jax.jit(solver.update)
    x, k = x0, 0
    while float(state.error) > tol and k < opts.max_steps:
        x, state = update(x, state)
        k += 1
        if not on_iter(k, np.asarray(x)):
            break
    err = float(state.error)
    converged = err <= tol
    message = "" if converged else ("maximum number of steps reached" if math.isfinite(err)
                                    else "the gradient became non-finite")
    return np.asarray(x), k, converged, message


def run_solver(name: str, residual: Callable, x0, m: int, opts: SolverOptions, on_iter) -> tuple:
    """Minimize 1/2 ||residual(x)||^2 from x0 with the named solver.

    Returns (x, iterations, converged, message). ``on_iter(k, x)`` is called after every
    iteration; returning False stops the loop.
    """
    x0 = jnp.asarray(x0, jnp.float64)
    objective = lambda x: 0.5 * jnp.sum(residual(x) ** 2)
    if name in ("optimistix_lm", "optimistix_gn", "optimistix_bfgs"):
        if name == "optimistix_bfgs":
            solver = optx.BFGS(rtol=opts.rtol, atol=opts.atol)
            fn = lambda y, args: (objective(y), None)
            f_struct = jax.ShapeDtypeStruct((), jnp.float64)
        else:
            cls = optx.LevenbergMarquardt if name == "optimistix_lm" else GaussNewtonLineSearch
            solver = cls(rtol=opts.rtol, atol=opts.atol)
            fn = lambda y, args: (residual(y), None)
            f_struct = jax.ShapeDtypeStruct((m,), jnp.float64)
        return _optimistix_loop(solver, fn, x0, f_struct, opts, on_iter)
    if name in ("jaxopt_lm", "jaxopt_lbfgs"):
        import warnings

        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=DeprecationWarning)
            import jaxopt
        if name == "jaxopt_lm":
            solver = jaxopt.LevenbergMarquardt(residual, maxiter=opts.max_steps, tol=opts.gtol,
                                               materialize_jac=True, solver="cholesky", jit=True)
        else:
            solver = jaxopt.LBFGS(objective, maxiter=opts.max_steps, tol=opts.gtol, jit=True)
        # Relative gradient tolerance: the residual's units (rad, m, feature sds) vary by target.
        g0 = float(jnp.linalg.norm(jax.grad(objective)(x0)))
        return _jaxopt_loop(solver, x0, opts, on_iter, opts.gtol * max(g0, 1e-300))
    raise ValueError(f"unknown solver {name!r}; choose one of {', '.join(SOLVERS)}")


# ----------------------------------------------------------------------------------------------
# The fit and its report


LOSS_FLAT_RTOL = 1e-8  # relative change of the loss per iteration that counts as none
LOSS_FLAT_ITERATIONS = 3  # ... over this many consecutive iterations
CONVERGED_STATUSES = ("converged", "converged (loss flat)")


def loss_is_flat(losses, rtol: float = LOSS_FLAT_RTOL, n: int = LOSS_FLAT_ITERATIONS) -> bool:
    """True when each of the last ``n`` changes of the loss (a sequence over iterations) is
    below ``rtol`` relative to the loss before it: the fit has converged in its objective even
    if the solver's step-size test has not fired (the gains then move by round-off only)."""
    vals = [float(v) for v in losses if v is not None]
    if len(vals) < n + 1:
        return False
    tail = np.asarray(vals[-(n + 1):])
    if not np.all(np.isfinite(tail)):
        return False
    return bool(np.all(np.abs(np.diff(tail)) <= rtol * np.maximum(np.abs(tail[:-1]), 1e-300)))


@dataclasses.dataclass
class FitResult:
    """Everything the calibration reports (``to_json`` gives the JSON contract)."""

    solver: str
    status: str  # converged | max_steps | diverged | nonfinite
    message: str
    ks: float
    kd: float
    ks0: float
    kd0: float
    log_params: list[float]
    covariance_log: list[list[float]]  # Gauss-Newton s^2 (J^T J)^-1 of (log ks, log kd)
    se_log: list[float]
    se_ks: float
    se_kd: float
    correlation: float
    s2: float
    residual_norm: float
    residual_rms: float
    loss: float
    n_residuals: int
    iterations: int
    evaluations: int
    wall_time_s: float
    jacobian: str
    diverged_evaluations: int
    history: list[dict]

    @property
    def converged(self) -> bool:
        return self.status in CONVERGED_STATUSES

    @property
    def x(self) -> np.ndarray:
        return np.asarray(self.log_params)

    def to_json(self) -> dict:
        return _json_safe(dataclasses.asdict(self))


def _json_safe(obj):
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def gauss_newton_covariance(jac: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, float]:
    """``s^2 (J^T J)^-1`` with ``s^2 = ||r||^2 / (m - p)`` (p = 2 parameters).

    With m = p there are no degrees of freedom left to estimate s^2; the weights are then
    taken as exact inverse standard deviations (s^2 = 1). A singular J^T J (a parameter the
    target does not see) gives infinite variances.
    """
    m, p = jac.shape
    s2 = float(r @ r / (m - p)) if m > p else 1.0
    jtj = jac.T @ jac
    if not np.all(np.isfinite(jtj)) or np.linalg.cond(jtj) > 1e14:
        return np.full((p, p), np.inf), s2
    return s2 * np.linalg.inv(jtj), s2


def fit(evaluator: ResponseEvaluator, target, weights, x0, solver: str = "optimistix_lm",
        options: SolverOptions | None = None, progress: bool = True, strict: bool = False,
        residual: Callable | None = None) -> FitResult:
    """Minimize ``1/2 ||w * (y(x) - target)||^2`` over x = (log ks, log kd) from ``x0``.

    Pass ``residual`` (from :func:`residual_function`) to reuse one across calls. Raises
    :class:`FitError` when the rollout diverges at the starting gains, and (``strict``) when
    the fit does not end ``converged``.
    """
    from tqdm.auto import tqdm

    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose one of {', '.join(SOLVERS)}")
    opts = options or SolverOptions()
    target = np.asarray(target, np.float64)
    weights = np.asarray(weights, np.float64)
    x0 = np.asarray(x0, np.float64)
    t_start = _time.perf_counter()
    evals0 = evaluator.n_evals
    div0 = len(evaluator.diverged_evals)
    ev0 = evaluator(x0)
    if np.any(ev0.diverged >= 0):
        raise FitError(f"the rollout diverges at the starting gains ks={math.exp(x0[0]):.6g}, "
                       f"kd={math.exp(x0[1]):.6g} ({_divergence_text(evaluator, ev0)}); "
                       f"start from gains that simulate")
    r = residual or residual_function(evaluator, target, weights)
    history: list[dict] = []
    last_good = [x0.copy()]
    bar = tqdm(total=opts.max_steps, desc=f"fit {solver}", unit="it", disable=not progress, leave=False)

    def on_iter(k, x):
        finite = bool(np.all(np.isfinite(x)))
        if finite:
            last_good[0] = x.copy()
        # The most recent evaluation is the one the solver just used (no extra rollout).
        recent = next(reversed(evaluator._cache.values()))
        lval = 0.5 * float(np.sum((weights * (recent.y - target)) ** 2))
        # The loss at the iterate itself when the solver evaluated it (no extra rollout).
        at_x = evaluator._cache.get(np.asarray(x, np.float64).reshape(-1).tobytes()) if finite else None
        loss_x = 0.5 * float(np.sum((weights * (at_x.y - target)) ** 2)) if at_x is not None else lval
        history.append({"iteration": k, "ks": float(np.exp(x[0])), "kd": float(np.exp(x[1])),
                        "last_loss": lval, "loss": loss_x})
        bar.update(1)
        bar.set_postfix(loss=f"{lval:.4g}", ks=f"{math.exp(x[0]):.4g}" if finite else "nan",
                        kd=f"{math.exp(x[1]):.4g}" if finite else "nan")
        return finite

    try:
        x, iters, converged, message = run_solver(solver, r, x0, target.size, opts, on_iter)
    finally:
        bar.close()
    status = "converged" if converged else "max_steps"
    # Converged in the loss: flat at the iterates, and the solver's latest evaluations finite (a
    # solver stuck because every trial point is NaN also has a flat loss, and has not converged).
    recent_ok = all(math.isfinite(h["last_loss"]) for h in history[-(LOSS_FLAT_ITERATIONS + 1):])
    if (status == "max_steps" and iters >= opts.max_steps and recent_ok
            and loss_is_flat([h["loss"] for h in history])):
        status = "converged (loss flat)"
        message = (f"converged (loss flat): the loss changed by less than {LOSS_FLAT_RTOL:g} (relative) in "
                   f"each of the last {LOSS_FLAT_ITERATIONS} iterations; {solver}'s own step tolerance "
                   f"was not met in {opts.max_steps} steps")
    if not np.all(np.isfinite(x)):
        status, x = "nonfinite", last_good[0]
        message = (f"the solver produced non-finite parameters; returning the last finite iterate "
                   f"ks={math.exp(x[0]):.6g}, kd={math.exp(x[1]):.6g}")
    ev = evaluator(x)
    if status != "nonfinite" and not np.all(np.isfinite(ev.y)):
        status = "nonfinite"
        message = (f"the response is non-finite at ks={math.exp(x[0]):.6g}, kd={math.exp(x[1]):.6g} "
                   f"({message or 'solver stopped'})")
    if np.any(ev.diverged >= 0):
        status = "diverged"
        message = (f"the rollout diverges at the final gains ks={math.exp(x[0]):.6g}, "
                   f"kd={math.exp(x[1]):.6g}: {_divergence_text(evaluator, ev)}")
    elif status == "max_steps":
        message = f"{solver} did not converge in {opts.max_steps} steps ({message})"
    res = weights * (ev.y - target)
    jac = weights[:, None] * ev.jac
    cov, s2 = gauss_newton_covariance(jac, res)
    se = np.sqrt(np.diag(cov))
    ks, kd = float(np.exp(x[0])), float(np.exp(x[1]))
    corr = float(cov[0, 1] / (se[0] * se[1])) if np.all(np.isfinite(se)) and np.all(se > 0) else float("nan")
    out = FitResult(
        solver=solver, status=status, message=message or "converged", ks=ks, kd=kd,
        ks0=float(np.exp(x0[0])), kd0=float(np.exp(x0[1])), log_params=[float(v) for v in x],
        covariance_log=cov.tolist(), se_log=se.tolist(), se_ks=ks * float(se[0]), se_kd=kd * float(se[1]),
        correlation=corr, s2=s2, residual_norm=float(np.linalg.norm(res)),
        residual_rms=float(np.sqrt(np.mean(res**2))), loss=0.5 * float(res @ res), n_residuals=int(res.size),
        iterations=int(iters), evaluations=evaluator.n_evals - evals0,
        wall_time_s=_time.perf_counter() - t_start, jacobian=evaluator.jacobian,
        diverged_evaluations=len(evaluator.diverged_evals) - div0, history=history,
    )
    if strict and not out.converged:
        raise FitError(f"fit with {solver} failed ({status}): {out.message}", out)
    return out


def _divergence_text(evaluator: ResponseEvaluator, ev: Evaluation) -> str:
    p = evaluator.problem
    run = int(np.nonzero(ev.diverged >= 0)[0][0])
    step = int(ev.diverged[run])
    time = np.asarray(p.ref.time)
    t = float(time[min(step + 1, time.size - 1)])
    which = "the unperturbed run" if (p.spec.kind == "features" and run == p.n_cases) else f"case {run}"
    return f"{which} diverged at step {step} (t = {t:.4f} s)"


def save_json_atomic(path, data: dict) -> pathlib.Path:
    path = pathlib.Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2, allow_nan=False)
        fh.write("\n")
    return path


# ----------------------------------------------------------------------------------------------
# Building a calibration from a Setup or a config file


def make_problem(setup, kind: str, columns=(), window=None, features=FEATURE_NAMES, **surrogate) -> FitProblem:
    """A :class:`FitProblem` over the perturbation cases of ``setup.config.perturbations``.

    Each ``[[perturbation]]`` entry is one case (one rollout); all cases must share a pulse
    shape (a static field: one shape per vmapped batch). ``window`` = (t0, t1) in clip
    seconds (default: the whole simulation).
    """
    from neuromotor.physics.perturbation import pulses as make_pulses
    from neuromotor.studies.simulate import body_lookup
    from neuromotor.studies.targets import window_indices
    from neuromotor.config import ConfigError

    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    cfg = setup.config
    specs = cfg.perturbations
    if not specs:
        raise ConfigError(f"{cfg.source}: a fit needs at least one [[perturbation]] (one per case)")
    index = body_lookup(setup.model, cfg.source)
    per_case = [make_pulses([s], index) for s in specs]
    shapes = {p.shape for p in per_case}
    if len(shapes) > 1:
        raise ConfigError(f"{cfg.source}: field 'perturbation[*].shape': the cases of one fit must share a "
                          f"pulse shape (and kind), got {sorted(s[0] for s in shapes)}")
    if kind == "features":
        base = dataclasses.replace(per_case[0], magnitude=jnp.zeros_like(per_case[0].magnitude))
        per_case = per_case + [base]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *per_case)
    sim_time = np.asarray(setup.ref.time[: setup.sim.n_steps + 1])
    if window is None:
        window = (float(sim_time[0]), float(sim_time[-1]))
    i0, i1 = window_indices(sim_time, window, cfg.source, "fit.window")
    spec = ResponseSpec(kind, tuple(int(c) for c in columns), i0, i1,
                        tuple(features) if kind == "features" else (), **surrogate)
    start = jnp.asarray([float(s["start"]) for s in specs])
    return FitProblem(setup.model, setup.gains, batch, setup.ref, start, setup.sim, spec)


@dataclasses.dataclass
class Calibration:
    """A calibration ready to run: problem, target, weights, start and solver settings."""

    setup: object  # neuromotor.studies.simulate.Setup
    problem: FitProblem
    target: np.ndarray  # (m,) flat, as y(x)
    weights: np.ndarray  # (m,)
    x0: np.ndarray
    solver: str = "optimistix_lm"
    options: SolverOptions = dataclasses.field(default_factory=SolverOptions)
    jacobian: str = "forward"
    labels: tuple[str, ...] = ()  # one per plotted curve column
    target_file: str | None = None
    feature_table: list[dict] = dataclasses.field(default_factory=list)  # per case: name -> value/sd/source
    source: str = "<calibration>"

    @property
    def time(self) -> np.ndarray:
        s = self.problem.spec
        return np.asarray(self.problem.ref.time[s.i0:s.i1])

    def target_curves(self) -> np.ndarray:
        """Trajectory targets shaped like the evaluator's curves (C, T, c)."""
        c, t = self.problem.n_cases, self.time.size
        return self.target.reshape(c, t, -1)


def trajectory_calibration(setup, table, quantity: str, names=None, weights=None, window=None,
                           angle_unit: str = "rad", source: str | None = None) -> tuple:
    """Target and weights for a trajectory table (see :mod:`neuromotor.studies.targets`).

    Returns (problem, target, weights, labels). ``names``: the DOFs or bodies to fit (default:
    every column of the file); ``weights``: name -> weight (default 1).
    """
    from neuromotor.config import ConfigError
    from neuromotor.studies.targets import resample

    model = setup.model
    src = source or setup.config.source
    known = model.dof_names if quantity == "joint_angles" else model.body_names
    what = "DOF" if quantity == "joint_angles" else "body"
    unknown = [n for n in table.names if n not in known]
    if unknown:
        raise ConfigError(f"{table.source}: field 'names' has unknown {what} name(s) {unknown[:5]}; "
                          f"the model's are e.g. {list(known[:4])}")
    names = list(table.names) if names is None else list(names)
    for i, n in enumerate(names):
        if n not in known:
            raise ConfigError(f"{src}: field 'fit.target.{'dofs' if what == 'DOF' else 'bodies'}[{i}]' is an "
                              f"unknown {what} name {n!r}")
        if n not in table.names:
            raise ConfigError(f"{table.source}: column {n!r} is missing (named by {src} fit.target)")
    weights = dict(weights or {})
    for n, w in weights.items():
        if n not in names:
            raise ConfigError(f"{src}: field 'fit.target.weights.{n}' names a {what} that is not fitted")
        if not (isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) and w >= 0):
            raise ConfigError(f"{src}: field 'fit.target.weights.{n}' must be a number >= 0, got {w!r}")
    if table.values.shape[0] != len(setup.config.perturbations):
        raise ConfigError(f"{table.source}: holds {table.values.shape[0]} case(s) but {src} has "
                          f"{len(setup.config.perturbations)} [[perturbation]] entries (one per case)")
    columns = [known.index(n) for n in names]
    problem = make_problem(setup, quantity, columns, window)
    s = problem.spec
    times = np.asarray(setup.ref.time[s.i0:s.i1])
    vals = resample(table, times, "fit.window")  # (C, T, k[, 3])
    pick = [table.names.index(n) for n in names]
    vals = vals[:, :, pick]
    if quantity == "joint_angles" and angle_unit == "deg":
        vals = np.deg2rad(vals)
    w = np.array([float(weights.get(n, 1.0)) for n in names])
    if quantity == "body_positions":
        w = np.repeat(w, 3)
        labels = tuple(f"{n}.{a}" for n in names for a in "xyz")
    else:
        labels = tuple(names)
    wfull = np.broadcast_to(w, vals.reshape(vals.shape[0], vals.shape[1], -1).shape).reshape(-1)
    return problem, vals.reshape(-1), np.array(wfull), labels


def load_calibration(path, solver: str | None = None, character=None, traj=None) -> Calibration:
    """Read a fit config (TOML; layout in docs/fitting.md) into a :class:`Calibration`."""
    from neuromotor.config import read_toml

    path = pathlib.Path(path)
    return calibration_from_dict(read_toml(path), str(path), path.parent, solver, character, traj)


def calibration_from_dict(data: dict, source: str = "<dict>", base_dir=None, solver: str | None = None,
                          character=None, traj=None) -> Calibration:
    from neuromotor.config import ConfigError, _Fields, simulation_config
    from neuromotor.studies.simulate import prepare
    from neuromotor.studies.targets import read_target

    cfg = simulation_config(data, source, base_dir)
    if "fit" not in data:
        raise ConfigError(f"{source}: a fit config needs a [fit] table")
    f = _Fields(data["fit"], "fit", source)
    name = f.choice("solver", "optimistix_lm", SOLVERS)
    opts = SolverOptions(
        max_steps=int(f.number("max_steps", 100, positive=True)),
        rtol=f.number("rtol", SolverOptions.rtol, positive=True),
        atol=f.number("atol", SolverOptions.atol, positive=True),
        gtol=f.number("gtol", SolverOptions.gtol, positive=True),
    )
    jacobian = f.choice("jacobian", "forward", ("forward", "reverse"))
    window = f.get("window")
    if window is not None and (not isinstance(window, list) or len(window) != 2 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in window)):
        f.fail("window", f"must be [t0, t1] in clip seconds, got {window!r}")
    t = _Fields(f.get("target", None) or f.fail("target", "is required ([fit.target] table)"), "fit.target", source)
    f.done()
    kind = t.choice("kind", None, KINDS)
    if not (cfg.ks > 0 and cfg.kd > 0):
        raise ConfigError(f"{source}: field 'gains.ks'/'gains.kd' (the starting gains) must be > 0")
    if solver is not None and solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose one of {', '.join(SOLVERS)}")
    x0 = np.log([cfg.ks, cfg.kd])
    common = dict(x0=x0, solver=solver or name, options=opts, jacobian=jacobian, source=source)
    if kind in ("joint_angles", "body_positions"):
        file = t.get("file")
        if not isinstance(file, str):
            t.fail("file", f"must be the path of an NPZ or CSV target, got {file!r}")
        p = pathlib.Path(file)
        if base_dir is not None and not p.is_absolute():
            p = pathlib.Path(base_dir) / p
        key = "dofs" if kind == "joint_angles" else "bodies"
        names = t.string_list(key, []) or None
        unit = t.choice("angle_unit", "rad", ("rad", "deg"))
        weights = t.get("weights", {})
        if not isinstance(weights, dict):
            t.fail("weights", f"must be a table of name = weight, got {weights!r}")
        t.done()
        table = read_target(p, kind)  # before the (slow) inverse dynamics: bad files fail fast
        setup = prepare(cfg, character, traj)
        common["setup"] = setup
        problem, target, w, labels = trajectory_calibration(setup, table, kind, names, weights, window, unit, source)
        return Calibration(problem=problem, target=target, weights=w, labels=labels, target_file=str(p), **common)
    dofs = t.string_list("dofs", [])
    setup = prepare(cfg, character, traj)
    common["setup"] = setup
    model = setup.model
    for i, n in enumerate(dofs):
        if n not in model.dof_names:
            t.fail(f"dofs[{i}]", f"is an unknown DOF name {n!r} (e.g. {list(model.dof_names[:3])})")
    surrogate = dict(beta=t.number("beta", 20.0, positive=True),
                     width=t.number("width", 0.1, positive=True),
                     fraction=t.number("recovery_fraction", mx.RECOVERY_FRACTION, positive=True),
                     floor_deg=t.number("recovery_floor_deg", mx.RECOVERY_FLOOR_DEG, nonneg=True),
                     accel_beta=t.number("accel_beta", ResponseSpec.accel_beta, positive=True))
    cases = t.get("case", [])
    if not isinstance(cases, list) or not cases:
        t.fail("case", "must be one or more [[fit.target.case]] tables (one per [[perturbation]])")
    t.done()
    if len(cases) != len(cfg.perturbations):
        t.fail("case", f"has {len(cases)} entries but there are {len(cfg.perturbations)} [[perturbation]] entries")
    table, used = [], []
    for i, case in enumerate(cases):
        c = _Fields(case, f"fit.target.case[{i}]", source)
        row = {}
        for feat in FEATURE_NAMES:
            spec = c.get(feat)
            if spec is None:
                continue
            g = _Fields(spec, f"fit.target.case[{i}].{feat}", source)
            row[feat] = {"value": g.number("value", None), "sd": g.number("sd", None, positive=True),
                         "source": g.get("source", "")}
            if row[feat]["value"] is None:
                g.fail("value", "is required")
            if row[feat]["sd"] is None:
                g.fail("sd", "is required (the residual is (simulated - value) / sd)")
            if not isinstance(row[feat]["source"], str) or not row[feat]["source"].strip():
                g.fail("source", "is required: cite where the number comes from, or say it is illustrative")
            g.done()
        c.done()
        if not row:
            c.fail(FEATURE_NAMES[0], f"one of {list(FEATURE_NAMES)} is required")
        table.append(row)
        used.append(set(row))
    feats = tuple(n for n in FEATURE_NAMES if any(n in u for u in used))
    problem = make_problem(setup, "features", [model.dof_names.index(n) for n in dofs], window, feats, **surrogate)
    target = np.array([row.get(n, {}).get("value", 0.0) for row in table for n in feats])
    # A feature a case does not list gets weight 0: it is computed but does not count.
    w = np.array([1.0 / row[n]["sd"] if n in row else 0.0 for row in table for n in feats])
    return Calibration(problem=problem, target=target, weights=w, labels=("deviation (deg)",),
                       feature_table=table, **common)


# ----------------------------------------------------------------------------------------------
# Running a calibration end to end: JSON + PNG


def calibrate(cal: Calibration, outdir=None, progress: bool = True, evaluator: ResponseEvaluator | None = None,
              strict: bool = False) -> tuple[FitResult, dict]:
    """Fit, then write ``fit.json`` and ``fit.png`` to ``outdir`` (if given).

    Returns the result and the JSON document (which adds the problem description and, for
    feature targets, the surrogate and exact features at the fitted gains).
    """
    ev = evaluator or ResponseEvaluator(cal.problem, cal.jacobian)
    res = fit(ev, cal.target, cal.weights, cal.x0, cal.solver, cal.options, progress=progress, strict=False)
    doc = {"config": cal.source, "target_file": cal.target_file, "target_kind": cal.problem.spec.kind,
           "window_s": [float(cal.time[0]), float(cal.time[-1])], "h": cal.setup.sim.h,
           "cases": cal.setup.config.perturbations, **res.to_json()}
    if cal.problem.spec.kind == "features":
        doc["features"] = _feature_report(cal, ev, res)
    doc = _json_safe(doc)  # NaN/inf (e.g. an exact recovery time that never came) -> null
    if outdir is not None:
        outdir = pathlib.Path(outdir)
        save_json_atomic(outdir / "fit.json", doc)
        plot_fit(cal, ev(cal.x0), ev(res.x), outdir / "fit.png", res)
    if strict and not res.converged:
        raise FitError(f"fit with {res.solver} failed ({res.status}): {res.message}", res)
    return res, doc


def _feature_report(cal: Calibration, ev: ResponseEvaluator, res: FitResult) -> list[dict]:
    s = cal.problem.spec
    fitted = ev(res.x)
    y = fitted.y.reshape(cal.problem.n_cases, len(s.features))
    out = []
    for c, row in enumerate(cal.feature_table):
        dev = fitted.curves[c, :, 0]
        start = float(cal.problem.start[c])
        exact = mx.recovery_metrics(cal.time, dev, start, s.fraction, s.floor_deg)
        exact_named = {"peak_deviation_deg": exact["peak_deviation_deg"],
                       "time_to_peak_s": exact["time_of_peak_s"] - start,
                       "recovery_time_s": exact["recovery_time_s"], "overshoot_deg": exact["overshoot_deg"],
                       "peak_acceleration_deg_s2": exact_peak_acceleration(fitted.curves[c, :, 1])}
        out.append({n: {"target": row.get(n, {}).get("value"), "sd": row.get(n, {}).get("sd"),
                        "source": row.get(n, {}).get("source"), "fitted_surrogate": float(y[c, j]),
                        "fitted_exact": exact_named[n]} for j, n in enumerate(s.features)})
    return out


def plot_fit(cal: Calibration, ev_start: Evaluation, ev_fit: Evaluation, path, res: FitResult | None = None,
             max_columns: int = 4):
    """PNG: the target, the fitted response and the response at the starting gains."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = cal.time
    n_cases = cal.problem.n_cases
    feats = cal.problem.spec.kind == "features"
    if feats:  # deviation, and the acceleration when it is fitted
        cols = [0, 1] if "peak_acceleration_deg_s2" in cal.problem.spec.features else [0]
    else:
        tgt = cal.target_curves()
        # Show the columns the gains move most (start vs fitted), not those the mocap moves most.
        spread = np.abs(ev_start.curves - ev_fit.curves).max(axis=(0, 1))
        cols = list(np.argsort(-spread)[:max_columns])
    fig, axes = plt.subplots(n_cases, len(cols), figsize=(max(3.6 * len(cols), 7.0), 2.7 * n_cases + 0.6), squeeze=False)
    scale = 1.0 if feats or cal.problem.spec.kind == "body_positions" else 180.0 / np.pi
    unit = "deg" if feats or cal.problem.spec.kind == "joint_angles" else "m"
    for c in range(n_cases):
        for j, col in enumerate(cols):
            ax = axes[c, j]
            if not feats:
                ax.plot(t, scale * tgt[c, :, col], "k.", ms=3, label="target")
            ax.plot(t, scale * ev_fit.curves[c, :, col], "C0-", lw=1.6, label="fitted")
            ax.plot(t, scale * ev_start.curves[c, :, col], "C3--", lw=1.2, label="start")
            if feats and col == 1:
                row = cal.feature_table[c]
                if "peak_acceleration_deg_s2" in row:
                    v, sd = row["peak_acceleration_deg_s2"]["value"], row["peak_acceleration_deg_s2"]["sd"]
                    ax.axhspan(v - sd, v + sd, color="k", alpha=0.12, label="target peak ± sd")
                ax.set_ylabel("acceleration (deg/s²)")
                ax.set_title(f"case {c}: angular acceleration of the deviation", fontsize=9)
            elif feats:
                start = float(cal.problem.start[c])
                row = cal.feature_table[c]
                if "peak_deviation_deg" in row:
                    v, sd = row["peak_deviation_deg"]["value"], row["peak_deviation_deg"]["sd"]
                    ax.axhspan(v - sd, v + sd, color="k", alpha=0.12, label="target peak ± sd")
                if "time_to_peak_s" in row:
                    ax.axvline(start + row["time_to_peak_s"]["value"], color="k", ls=":", label="target time to peak")
                if "recovery_time_s" in row:
                    ax.axvline(start + row["recovery_time_s"]["value"], color="k", ls="-.", lw=0.8,
                               label="target recovery")
                ax.set_ylabel(f"deviation ({unit})")
                ax.set_title(f"case {c}", fontsize=9)
            else:
                ax.set_title(f"case {c}: {cal.labels[col]}", fontsize=9)
                ax.set_ylabel(unit)
            ax.set_xlabel("clip time (s)")
            if c == 0 and (j == 0 or feats):
                ax.legend(fontsize=7)
    if res is not None:
        fig.suptitle(f"{res.solver}: ks = {res.ks:.4g} ± {res.se_ks:.2g} 1/s², kd = {res.kd:.4g} ± {res.se_kd:.2g} 1/s\n"
                     f"(start ks = {res.ks0:.4g}, kd = {res.kd0:.4g}; {res.status}, {res.iterations} iterations)",
                     fontsize=9)
    fig.tight_layout()
    path = pathlib.Path(path)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    finally:
        plt.close(fig)
    return path


def synthetic_target(cal: Calibration, ks: float, kd: float, noise: float = 0.0, seed: int = 0,
                     evaluator: ResponseEvaluator | None = None) -> np.ndarray:
    """The model output at known gains plus seeded Gaussian noise (sd ``noise``, output units)."""
    ev = (evaluator or ResponseEvaluator(cal.problem, cal.jacobian))(np.log([ks, kd]))
    if np.any(ev.diverged >= 0):
        raise FitError(f"the rollout diverges at ks={ks}, kd={kd}; cannot make a synthetic target")
    rng = np.random.default_rng(seed)
    return ev.y + noise * rng.standard_normal(ev.y.shape)


def write_synthetic_target(config_path, ks: float, kd: float, noise_deg: float = 0.0, seed: int = 0,
                           progress: bool = True) -> pathlib.Path:
    """Simulate a joint-angle target at known gains and write it to the config's target file.

    The config's ``[fit.target]`` must be ``kind = "joint_angles"`` with ``file`` and ``dofs``;
    the CSV covers the fit window on the simulation grid, in the config's ``angle_unit``, with
    seeded Gaussian noise of ``noise_deg`` degrees added.
    """
    from neuromotor.config import ConfigError, _Fields, read_toml, simulation_config
    from neuromotor.studies.simulate import prepare
    from neuromotor.studies.targets import write_target_csv

    config_path = pathlib.Path(config_path)
    data = read_toml(config_path)
    source = str(config_path)
    cfg = simulation_config(data, source, config_path.parent)
    fit_t = data.get("fit", {}).get("target", {})
    t = _Fields(fit_t, "fit.target", source)
    if t.get("kind") != "joint_angles":
        t.fail("kind", "must be 'joint_angles' to write a synthetic trajectory target")
    file = t.get("file")
    dofs = t.string_list("dofs", [])
    unit = t.choice("angle_unit", "rad", ("rad", "deg"))
    if not isinstance(file, str) or not dofs:
        t.fail("file" if not isinstance(file, str) else "dofs", "is required to write a synthetic target")
    setup = prepare(cfg)
    model = setup.model
    for i, n in enumerate(dofs):
        if n not in model.dof_names:
            raise ConfigError(f"{source}: field 'fit.target.dofs[{i}]' is an unknown DOF name {n!r}")
    window = data.get("fit", {}).get("window")
    problem = make_problem(setup, "joint_angles", [model.dof_names.index(n) for n in dofs], window)
    ev = ResponseEvaluator(problem)
    cal = Calibration(setup=setup, problem=problem, target=np.zeros(1), weights=np.zeros(1), x0=np.zeros(2))
    y = synthetic_target(cal, ks, kd, np.deg2rad(noise_deg), seed, evaluator=ev)
    vals = y.reshape(problem.n_cases, -1, len(dofs))
    if unit == "deg":
        vals = np.rad2deg(vals)
    path = pathlib.Path(file)
    if not path.is_absolute():
        path = config_path.parent / path
    note = (f"synthetic target: neuromotor rollout at ks = {ks} 1/s^2, kd = {kd} 1/s, h = {setup.sim.h}\n"
            f"plus Gaussian noise of sd {noise_deg} deg (seed {seed}); angles in {unit}; config {config_path.name}")
    return write_target_csv(path, cal.time, dofs, vals, "joint_angles", note)
