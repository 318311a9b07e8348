"""The fit: minimize 1/2 ||w * (y(x) - target)||^2 over x = the logarithms of the fitted
parameters (default (ks, kd)), then report."""

from __future__ import annotations

import math
import time as _time
from collections.abc import Callable

import numpy as np

from neuromotor.config.specs import FIT_SOLVERS, SolverOptions
from neuromotor.studies.fit.bridge import residual_function
from neuromotor.studies.fit.covariance import gauss_newton_covariance
from neuromotor.studies.fit.evaluate import Evaluation, ResponseEvaluator
from neuromotor.studies.fit.parameters import beyond_history, describe
from neuromotor.studies.fit.result import (
    LOSS_FLAT_ITERATIONS,
    LOSS_FLAT_RTOL,
    FitError,
    FitResult,
    identifiability,
    loss_is_flat,
)
from neuromotor.studies.fit.solvers import run_solver
from neuromotor.studies.gains import DELAYS, gain_value


def fit(
    evaluator: ResponseEvaluator,
    target,
    weights,
    x0,
    solver: str = "optimistix_lm",
    options: SolverOptions | None = None,
    progress: bool = True,
    strict: bool = False,
    residual: Callable | None = None,
) -> FitResult:
    """Minimize ``1/2 ||w * (y(x) - target)||^2`` over x (the logarithms of the problem's
    fitted parameters, ``evaluator.problem.names``) from ``x0``.

    Pass ``residual`` (from :func:`residual_function`) to reuse one across calls. Raises
    :class:`FitError` when the rollout diverges at the starting gains, and (``strict``) when
    the fit does not end ``converged``.
    """
    from tqdm.auto import tqdm

    if solver not in FIT_SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose one of {', '.join(FIT_SOLVERS)}")
    opts = options or SolverOptions()
    target, weights, x0 = (np.asarray(a, np.float64) for a in (target, weights, x0))
    t_start, evals0, div0 = _time.perf_counter(), evaluator.n_evals, len(evaluator.diverged_evals)
    ev0 = evaluator(x0)
    if np.any(ev0.diverged >= 0):
        raise FitError(
            f"the rollout diverges at the starting values {_at(evaluator, x0)} "
            f"({_divergence_text(evaluator, ev0)}); start from values that simulate"
        )
    r = residual or residual_function(evaluator, target, weights)
    bar = tqdm(total=opts.max_steps, desc=f"fit {solver}", unit="it", disable=not progress, leave=False)
    track = _Progress(evaluator, target, weights, x0, bar)
    try:
        x, iters, converged, message = run_solver(solver, r, x0, target.size, opts, track)
    finally:
        bar.close()
    status, x, ev, message = _final_status(evaluator, solver, opts, track, x, iters, converged, message)
    out = _report(evaluator, ev, target, weights, x, x0, solver, status, message, track.history)
    out.iterations, out.evaluations = int(iters), evaluator.n_evals - evals0
    out.wall_time_s = _time.perf_counter() - t_start
    out.diverged_evaluations = len(evaluator.diverged_evals) - div0
    if strict and not out.converged:
        raise FitError(f"fit with {solver} failed ({status}): {out.message}", out)
    return out


class _Progress:
    """The solvers' per-iteration callback: history of the loss, progress bar, and the last
    finite iterate. Reads the loss from the evaluations the solver already made (no extra rollout)."""

    def __init__(self, evaluator: ResponseEvaluator, target, weights, x0, bar):
        self.evaluator, self.target, self.weights, self.bar = evaluator, target, weights, bar
        self.history: list[dict] = []
        self.last_good = x0.copy()

    def loss_of(self, ev) -> float:
        return 0.5 * float(np.sum((self.weights * (ev.y - self.target)) ** 2))

    def __call__(self, k, x) -> bool:
        finite = bool(np.all(np.isfinite(x)))
        if finite:
            self.last_good = x.copy()
        cache = self.evaluator._cache
        lval = self.loss_of(next(reversed(cache.values())))  # the evaluation the solver just used
        at_x = cache.get(np.asarray(x, np.float64).reshape(-1).tobytes()) if finite else None
        loss_x = self.loss_of(at_x) if at_x is not None else lval
        names = self.evaluator.problem.names
        values = {n: float(np.exp(v)) for n, v in zip(names, x)}
        self.history.append({"iteration": k, **values, "last_loss": lval, "loss": loss_x})
        self.bar.update(1)
        self.bar.set_postfix(loss=f"{lval:.4g}", **{n: f"{v:.4g}" for n, v in values.items()})
        return finite


def _final_status(evaluator, solver, opts, track: _Progress, x, iters, converged, message):
    """(status, x, its evaluation, message) of a finished solver run; see the package docstring for the statuses."""
    status = "converged" if converged else "max_steps"
    history = track.history
    # Converged in the loss: flat at the iterates, and the solver's latest evaluations finite (a
    # solver stuck because every trial point is NaN also has a flat loss, and has not converged).
    recent_ok = all(math.isfinite(h["last_loss"]) for h in history[-(LOSS_FLAT_ITERATIONS + 1) :])
    if status == "max_steps" and iters >= opts.max_steps and recent_ok and loss_is_flat([h["loss"] for h in history]):
        status = "converged (loss flat)"
        message = (
            f"converged (loss flat): the loss changed by less than {LOSS_FLAT_RTOL:g} (relative) in "
            f"each of the last {LOSS_FLAT_ITERATIONS} iterations; {solver}'s own step tolerance "
            f"was not met in {opts.max_steps} steps"
        )
    if not np.all(np.isfinite(x)):
        status, x = "nonfinite", track.last_good
        message = f"the solver produced non-finite parameters; returning the last finite iterate {_at(evaluator, x)}"
    ev = evaluator(x)
    if status != "nonfinite" and not np.all(np.isfinite(ev.y)):
        status = "nonfinite"
        message = f"the response is non-finite at {_at(evaluator, x)} ({message or 'solver stopped'})"
    beyond = _beyond_history(evaluator, x)
    if np.any(ev.diverged >= 0):
        status = "diverged"
        message = f"the rollout diverges at the final values {_at(evaluator, x)}: {_divergence_text(evaluator, ev)}"
    elif beyond:
        status, message = "out_of_range", beyond
    elif status == "max_steps":
        message = f"{solver} did not converge in {opts.max_steps} steps ({message})"
    return status, x, ev, message


def _beyond_history(evaluator: ResponseEvaluator, x) -> str | None:
    """Why the fitted delays are not the model's, or None (:func:`.parameters.beyond_history`)."""
    p = evaluator.problem
    if not any(n in DELAYS for n in p.names):
        return None
    why = beyond_history(p.gains, p.options.h, dict(zip(p.names, np.exp(np.asarray(x, np.float64)))))
    return None if why is None else f"{why} and fit again"


def _report(evaluator, ev, target, weights, x, x0, solver, status, message, history) -> FitResult:
    """The :class:`FitResult` at ``x``: residual, covariance and standard errors (counts and
    wall time are filled in by :func:`fit`)."""
    names = evaluator.problem.names
    res = weights * (ev.y - target)
    cov, s2 = gauss_newton_covariance(weights[:, None] * ev.jac, res)
    se = np.sqrt(np.diag(cov))
    values = {n: float(np.exp(v)) for n, v in zip(names, x)}
    starts = {n: float(np.exp(v)) for n, v in zip(names, x0)}
    gains = evaluator.problem.gains
    fixed = lambda n, d: d[n] if n in d else float(gain_value(gains, n))
    se_abs = {n: values[n] * float(s) for n, s in zip(names, se)}
    corr = (
        float(cov[0, 1] / (se[0] * se[1]))
        if (len(se) > 1 and np.all(np.isfinite(se[:2])) and np.all(se[:2] > 0))
        else float("nan")
    )
    ok, note = identifiability(names, se, cov)
    return FitResult(
        solver=solver,
        status=status,
        message=message or "converged",
        ks=fixed("ks", values),
        kd=fixed("kd", values),
        ks0=fixed("ks", starts),
        kd0=fixed("kd", starts),
        log_params=[float(v) for v in x],
        covariance_log=cov.tolist(),
        se_log=se.tolist(),
        se_ks=se_abs.get("ks", 0.0),
        se_kd=se_abs.get("kd", 0.0),
        correlation=corr,
        s2=s2,
        residual_norm=float(np.linalg.norm(res)),
        residual_rms=float(np.sqrt(np.mean(res**2))),
        loss=0.5 * float(res @ res),
        n_residuals=int(res.size),
        iterations=0,
        evaluations=0,
        wall_time_s=0.0,
        jacobian=evaluator.jacobian,
        diverged_evaluations=0,
        history=history,
        parameters=list(names),
        values=values,
        start_values=starts,
        standard_errors=se_abs,
        identifiable=ok,
        identifiability=note,
    )


def _at(evaluator: ResponseEvaluator, x) -> str:
    return describe(evaluator.problem.names, x)


def _divergence_text(evaluator: ResponseEvaluator, ev: Evaluation) -> str:
    p = evaluator.problem
    run = int(np.nonzero(ev.diverged >= 0)[0][0])
    step = int(ev.diverged[run])
    time = np.asarray(p.ref.time)
    t = float(time[min(step + 1, time.size - 1)])
    which = "the unperturbed run" if (p.spec.kind == "features" and run == p.n_cases) else f"case {run}"
    return f"{which} diverged at step {step} (t = {t:.4f} s)"
