"""The residual of a compiled evaluation as a JAX function the solvers can differentiate."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from neuromotor.studies.fit.evaluate import ResponseEvaluator


def residual_function(evaluator: ResponseEvaluator, target, weights) -> Callable:
    """r(x) = w * (y(x) - target) as a JAX function for the solvers.

    Its value comes from the shared compiled evaluation through ``jax.pure_callback``; its
    derivative is the custom JVP ``J @ t`` with J from the same evaluation, linear in t, so
    forward mode, ``linearize`` and reverse mode (transposition) all work.
    """
    target = np.asarray(target, np.float64)
    weights = np.asarray(weights, np.float64)
    m = target.size
    p = evaluator.problem.n_params
    shapes = (jax.ShapeDtypeStruct((m,), jnp.float64), jax.ShapeDtypeStruct((m, p), jnp.float64))

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
