"""Issue 38: the stepping state machine of neuromotor.physics.balance (off by default; see
docs/balance.md, "Stepping"). These tests check the machinery on the standing pose without a
rollout: the [balance] keys, idle in the quiet pose, the trigger and the step's target, vmap
over parameters and gradients with respect to the stepping parameters."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.config import ConfigError, simulation_config
from neuromotor.physics.balance import balance_torques, empty_posture
from neuromotor.studies.standing import standing_setup


@pytest.fixture(scope="module")
def setups():
    on = standing_setup(0.05, balance={"stepping": True})
    off = standing_setup(0.05, balance={"stepping": False})
    return on, off


def machine(setup, bal, n, state=None):
    """``n`` calls of the balance loop on a fixed state: (torques of the last call, posture)."""
    state = setup.ref.init if state is None else state
    posture = empty_posture(bal, jnp.float64)
    for _ in range(n):
        torque, posture = balance_torques(setup.model, bal, state, posture, setup.options.h)
    return torque, posture


def test_stepping_config():
    assert simulation_config({"sim": {"root": "free"}}, "x").balance.stepping is False  # off by default
    spec = simulation_config({"balance": {"stepping": True, "swing_time": 0.3, "max_step": 0.4}}, "x").balance
    assert spec.stepping and spec.swing_time == 0.3 and spec.values()["stepping"]["max_step"] == 0.4
    assert spec.values()["stepping"]["margin"] == spec.step_margin
    assert simulation_config({}, "x").balance.values()["stepping"] is None
    bad = [
        ({"balance": {"stepping": "yes"}}, "balance.stepping"),
        ({"balance": {"swing_time": 0.0}}, "balance.swing_time"),
        ({"balance": {"step_margin": -0.1}}, "balance.step_margin"),
        ({"balance": {"foot_kp": "stiff"}}, "balance.foot_kp"),
    ]
    for data, field in bad:
        with pytest.raises(ConfigError, match=f"field '{field}'"):
            simulation_config(data, "x.toml")


def test_idle_in_the_quiet_pose(setups):
    """The standing pose's capture point is within the margin: the machine stays idle and the
    torques are those of the loop without stepping."""
    on, off = setups
    t_on, p_on = machine(on, on.gains.balance, 30)
    t_off, _ = machine(off, off.gains.balance, 30)
    assert float(p_on.step.t) == -1.0 and float(p_on.step.count) == 0.0
    np.testing.assert_allclose(t_on, t_off, atol=1e-12)


def test_trigger_and_target(setups):
    """With a zero margin the machine steps at once, the swing foot's anchor moves by at most
    max_step, and the clock runs; the stepping foot's leg gets torques."""
    on, _ = setups
    bal = on.gains.balance
    bal = dataclasses.replace(bal, stepping=dataclasses.replace(bal.stepping, margin=jnp.asarray(0.0)))
    _, p = machine(on, bal, 5)
    step = p.step
    assert float(step.count) == 1.0 and 0.0 < float(step.t) < float(bal.stepping.swing_time)
    f = int(step.swing)
    moved = float(jnp.linalg.norm(step.anchor[f] - step.start))
    assert 0.0 < moved <= float(bal.stepping.max_step) + 1e-12
    assert float(step.held[f]) == 1.0 and float(step.held[1 - f]) == 0.0
    torque, _ = machine(on, bal, 5)
    hip = bal.stepping.legs[f][0]
    assert float(jnp.linalg.norm(torque[hip])) > 1.0


def test_vmap_over_stepping_parameters(setups):
    """A batch of two parameter sets equals the two single runs."""
    on, _ = setups
    bal = on.gains.balance
    margins, lifts = jnp.asarray([0.0, 0.5]), jnp.asarray([0.05, 0.08])

    def run(margin, lift):
        b = dataclasses.replace(bal, stepping=dataclasses.replace(bal.stepping, margin=margin, lift=lift))
        torque, posture = machine(on, b, 8)
        return torque, posture.step.t

    batch = jax.vmap(run)(margins, lifts)
    for i in range(2):
        single = run(margins[i], lifts[i])
        np.testing.assert_allclose(batch[0][i], single[0], rtol=1e-12, atol=1e-12)
        assert float(batch[1][i]) == float(single[1])
    assert float(batch[1][0]) >= 0.0 and float(batch[1][1]) == -1.0  # the first steps, the second does not


def test_gradient_of_stepping_parameters(setups):
    """The torques during a swing are differentiable in the swing time, the lift and the
    offset (the trigger's decision is discrete and has no gradient): jacfwd against central
    differences."""
    on, _ = setups
    bal = on.gains.balance

    def f(x):
        sp = dataclasses.replace(
            bal.stepping, margin=jnp.asarray(0.0), swing_time=x[0], lift=x[1], offset=x[2], foot_kp=x[3]
        )
        torque, _ = machine(on, dataclasses.replace(bal, stepping=sp), 10)
        return jnp.sum(torque**2)

    x0 = jnp.asarray([0.35, 0.05, 0.05, 3000.0])
    grad = jax.jacfwd(f)(x0)
    for i, eps in enumerate((1e-6, 1e-6, 1e-6, 1e-3)):
        e = jnp.zeros(4).at[i].set(eps)
        fd = (f(x0 + e) - f(x0 - e)) / (2 * eps)
        np.testing.assert_allclose(grad[i], fd, rtol=1e-5)
        assert float(jnp.abs(grad[i])) > 0
