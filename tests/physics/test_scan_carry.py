"""The rollout's scan starts its carry as depending on the parameters (``dynamics.depending_on``):
same values, and ``jvp`` and ``vmap`` of a rollout trace the step once instead of twice."""

import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from neuromotor.physics import dynamics


class Toy(eqx.Module):
    """The least a scanned step needs: a grid index, a state, ``badness`` and ``held``."""

    k: jax.Array
    state: jax.Array

    def badness(self, max_speed):
        return jnp.abs(self.state) / max_speed

    def held(self, last, bad):
        return self


def _counting_step():
    """A step with a primitive whose JVP and batching rules count how often a transformation
    processes it: once per round of scan's fixed point (its input depends on the parameters,
    so every round reaches it)."""
    rounds = {"jvp": 0, "vmap": 0}
    mark = Primitive("counted_identity")
    mark.def_impl(lambda x: x)
    mark.def_abstract_eval(lambda x: x)
    mlir.register_lowering(mark, mlir.lower_fun(lambda x: x, multiple_results=False))

    def jvp_rule(primals, tangents):
        rounds["jvp"] += 1
        return mark.bind(primals[0]), tangents[0]

    def batch_rule(args, dims):
        rounds["vmap"] += 1
        return mark.bind(args[0]), dims[0]

    ad.primitive_jvps[mark] = jvp_rule
    batching.primitive_batchers[mark] = batch_rule

    def step(sim, params, data):
        return Toy(data.k + 1, mark.bind(0.891 * (data.state + params["push"])))

    return step, rounds


SIM = types.SimpleNamespace(options=types.SimpleNamespace(n_steps=5, max_speed=1e3), ref=types.SimpleNamespace(time=jnp.zeros(6)))


def _final(step, params):
    out, bad_step, _ = dynamics.scan_steps(SIM, params, Toy(jnp.asarray(0), jnp.ones(3)), step)
    return out.state[-1]


@pytest.mark.parametrize("tied", [True, False])
def test_jvp_and_vmap_of_the_scan_trace_the_step_once(monkeypatch, tied):
    if not tied:  # the check can fail: without the tie, scan's fixed point takes a second round
        monkeypatch.setattr(dynamics, "depending_on", lambda params, carry, skip=None: carry)
    step, rounds = _counting_step()
    params = {"push": jnp.asarray(0.5)}
    _, tangent = jax.jvp(lambda p: _final(step, p), (params,), ({"push": jnp.asarray(1.0)},))
    batched = jax.vmap(lambda p: _final(step, {"push": p}))(jnp.array([0.5, 1.0]))
    assert rounds == ({"jvp": 1, "vmap": 1} if tied else {"jvp": 2, "vmap": 2})
    # Same values either way: x_{k+1} = 0.891 (x_k + push).
    x, dx = np.ones(3), np.zeros(3)
    for _ in range(5):
        x, dx = 0.891 * (x + 0.5), 0.891 * (dx + 1.0)
    np.testing.assert_allclose(tangent, dx, rtol=1e-14)
    np.testing.assert_allclose(batched[0], x, rtol=1e-14)


def test_depending_on_keeps_values_and_the_skipped_leaf():
    k, state = jnp.asarray(3), jnp.array([1.0, jnp.nan, -2.0])
    params = {"gain": jnp.asarray(jnp.inf)}  # a non-finite parameter cannot reach the carry
    flag = jnp.array([True, False])
    out = dynamics.depending_on(params, (k, state, jnp.asarray(-1), flag), skip=k)
    assert out[0] is k and out[3] is flag
    np.testing.assert_array_equal(out[1], state)
    assert out[1].dtype == state.dtype and int(out[2]) == -1
    # Under vmap over a parameter, every leaf but the skipped one carries the batch axis.
    tie = lambda g: dynamics.depending_on({"gain": g}, (k, state), skip=k)
    assert int(jax.vmap(lambda g: tie(g)[0], out_axes=None)(jnp.ones(2))) == 3
    with pytest.raises(ValueError):
        jax.vmap(lambda g: tie(g)[1], out_axes=None)(jnp.ones(2))
