"""Solver adapters: optimistix (Levenberg-Marquardt, Gauss-Newton with a line search, BFGS) and
jaxopt (Levenberg-Marquardt, L-BFGS), each stepped one iteration at a time from Python."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from neuromotor import compiler
from neuromotor.config.specs import FIT_SOLVERS, SolverOptions


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
        plain: optx.GaussNewton = optx.GaussNewton(rtol=rtol, atol=atol)
        self.rtol, self.atol, self.norm, self.verbose = rtol, atol, plain.norm, plain.verbose
        self.descent = optx.NewtonDescent()
        self.search = optx.BacktrackingArmijo()


def _optimistix_loop(solver, fn, y0, f_struct, opts: SolverOptions, on_iter):
    args = None
    options: dict[str, Any] = {}
    tags: frozenset[object] = frozenset()
    state = solver.init(fn, y0, args, options, f_struct, None, tags)
    dyn0, static = eqx.partition(state, eqx.is_array)

    @compiler.jit
    def terminate(y, dyn):
        return solver.terminate(fn, y, args, options, eqx.combine(static, dyn), tags)

    @compiler.jit
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
            message = str(optx.RESULTS[res])  # type: ignore[misc]  # an equinox Enumeration
        except Exception:  # the message lookup is an optimistix internal
            message = "optimistix reported a failure"
    return np.asarray(y), k, converged, message


def _jaxopt_loop(solver, x0, opts: SolverOptions, on_iter, tol):
    state = solver.init_state(x0)
    update = compiler.jit(solver.update)
    x, k = x0, 0
    while float(state.error) > tol and k < opts.max_steps:
        x, state = update(x, state)
        k += 1
        if not on_iter(k, np.asarray(x)):
            break
    err = float(state.error)
    converged = err <= tol
    message = (
        ""
        if converged
        else ("maximum number of steps reached" if math.isfinite(err) else "the gradient became non-finite")
    )
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
            solver: optx.AbstractMinimiser | optx.AbstractLeastSquaresSolver = optx.BFGS(rtol=opts.rtol, atol=opts.atol)
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
            solver = jaxopt.LevenbergMarquardt(
                residual, maxiter=opts.max_steps, tol=opts.gtol, materialize_jac=True, solver="cholesky", jit=True
            )
        else:
            solver = jaxopt.LBFGS(objective, maxiter=opts.max_steps, tol=opts.gtol, jit=True)
        # Relative gradient tolerance: the residual's units (rad, m, feature sds) vary by target.
        g0 = float(jnp.linalg.norm(jax.grad(objective)(x0)))
        return _jaxopt_loop(solver, x0, opts, on_iter, opts.gtol * max(g0, 1e-300))
    raise ValueError(f"unknown solver {name!r}; choose one of {', '.join(FIT_SOLVERS)}")
