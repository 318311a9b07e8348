"""One compiled evaluation ``x -> (y, dy/dx, curves, diverged)`` shared by every solver, with a
cache of recent evaluations."""

from __future__ import annotations

import collections
import dataclasses
import time as _time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from neuromotor import compiler
from neuromotor.studies.fit.problem import FitProblem


@dataclasses.dataclass
class Evaluation:
    x: np.ndarray
    y: np.ndarray  # (m,)
    jac: np.ndarray  # (m, p)
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
        self._fn = compiled_response(jacobian)
        self._cache: collections.OrderedDict[bytes, Evaluation] = collections.OrderedDict()
        self._size = cache_size
        self.n_evals = 0
        self.seconds = 0.0
        self.diverged_evals: list[tuple[np.ndarray, int, int]] = []  # (x, run, step)

    def __call__(self, x) -> Evaluation:
        x = np.asarray(x, np.float64).reshape(self.problem.n_params)
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

    def with_problem(self, problem: FitProblem) -> ResponseEvaluator:
        """A fresh cache over another problem of the same shapes (same compiled code)."""
        return ResponseEvaluator(problem, self.jacobian, self._size)


_COMPILED: dict[str, Callable] = {}


REVERSE_BATCH = 8  # backward passes run together in reverse mode


def compiled_response(jacobian: str):
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
