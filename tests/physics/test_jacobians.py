"""K and D in closed form (physics/stiffness.joint_blocks, gyro_blocks) against jax.jacfwd, the
SO(3) log-map derivative they use, and post-stabilization's closing Newton step."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.config import DEFAULT_HIT, SimulationConfig
from neuromotor.physics import solvers
from neuromotor.physics.constraints import closing_step, full_constraint_error
from neuromotor.physics.dynamics import SimModel, reference_inputs, rollout
from neuromotor.physics.system import retract
from neuromotor.physics.stiffness import Jacobians, stiff_blocks
from neuromotor.rotations import quat_exp, quat_log, quat_mul, quat_to_matrix, right_jacobian_inv
from neuromotor.studies.simulate import load_character, prepare


@pytest.mark.parametrize("angle", [0.0, 1e-7, 3e-3, 0.02, 0.7, 2.0, 3.1])
def test_right_jacobian_inverse_is_the_derivative_of_the_log_map(angle):
    """d/dd log(exp(e) exp(d)) at d = 0, on both sides of the series switch (|e| = 1e-2)."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    e = jnp.asarray(angle * axis)
    want = jax.jacfwd(lambda d: quat_log(quat_mul(quat_exp(e), quat_exp(d))))(jnp.zeros(3))
    np.testing.assert_allclose(right_jacobian_inv(e), want, rtol=0, atol=1e-13)


@pytest.fixture(scope="module")
def hit():
    character, traj = load_character(CLIPS["mocapbank"])
    setup = prepare(SimulationConfig(duration=0.2, perturbations=[dict(DEFAULT_HIT, magnitude=400.0, start=0.02)]),
                    character, traj)
    run = jax.jit(rollout, static_argnames="options")(setup.model, setup.gains, setup.pulses, setup.ref, setup.options)
    return setup, run


@pytest.mark.parametrize("when", ["start", "hit"])
def test_closed_form_blocks_equal_jacfwd_blocks(hit, when):
    """Every block of K and D and the stiff torques, at the mocap's first state (joint errors
    near zero: the series side of Jr^-1) and during the hit with spinning bodies."""
    setup, run = hit
    m = setup.model
    k = 0 if when == "start" else 20
    state = jax.tree_util.tree_map(lambda x: x[k], run.states)
    if when == "hit":
        state = dataclasses.replace(state, omega=state.omega + 0.7)
    sim = SimModel(m, setup.ref, setup.options)
    inputs = reference_inputs(sim, setup.gains, k)
    blocks = {j: jax.jit(lambda j=j: stiff_blocks(m, setup.gains, inputs, state, j))() for j in Jacobians}
    closed, ref = blocks[Jacobians.CLOSED_FORM], blocks[Jacobians.JACFWD]
    for name in ("k", "k_diag", "k_up", "k_down", "d_diag", "d_up", "d_down"):
        a, b = np.asarray(getattr(closed, name)), np.asarray(getattr(ref, name))
        assert np.abs(b).max() > 0, name
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max(), err_msg=name)


def test_rollout_with_closed_form_blocks_equals_jacfwd_rollout(hit):
    setup, run = hit
    other = jax.jit(rollout, static_argnames="options")(setup.model, setup.gains, setup.pulses, setup.ref,
                                                     dataclasses.replace(setup.options, jacobians="jacfwd"))
    assert float(jnp.abs(run.theta - other.theta).max()) < 1e-11
    assert float(jnp.abs(run.states.omega - other.states.omega).max()) < 1e-9


@pytest.mark.parametrize("unrolled, rows", [(False, "root"), (True, "root"), (False, "driven"), (False, "free_root")])
def test_closing_step_closes_what_the_projection_leaves(hit, unrolled, rows):
    """Post-stabilization's later Newton steps (constraints.closing_step) close the 1e-8-scale
    error that the linearized projection leaves, to round-off and without a solve, and land within
    that error's size of where a second projection would: with the driven root's rows, with
    driven joints' rows too, and with the root floating free."""
    setup, _ = hit
    model, targets = setup.model, setup.ref.pose_targets(0)
    cfg = dataclasses.replace(setup.options, driven=(2, 5) if rows == "driven" else (), free_root=rows == "free_root")
    rng = np.random.default_rng(7)
    quat = quat_mul(quat_exp(jnp.asarray(1e-4 * rng.normal(size=(model.n_bodies, 3)))), setup.ref.init.quat)
    pos = setup.ref.init.pos + 1e-4 * rng.normal(size=(model.n_bodies, 3))
    solver = solvers.get(cfg.solver)
    err = lambda p, q: np.asarray(full_constraint_error(model, cfg.driven, p, quat_to_matrix(q), targets, cfg.free_root))

    @jax.jit
    def stages(pos, quat, c0):
        pos1, quat1 = retract(pos, quat, solver.projection_step(model, cfg, quat_to_matrix(quat), c0))
        c1 = full_constraint_error(model, cfg.driven, pos1, quat_to_matrix(quat1), targets, cfg.free_root)
        rot1 = quat_to_matrix(quat1)
        closed = retract(pos1, quat1, closing_step(model, cfg, rot1, c1, unrolled))
        projected = retract(pos1, quat1, solver.projection_step(model, cfg, rot1, c1))
        return (pos1, quat1), closed, projected

    err0 = err(pos, quat)
    first, closed, projected = stages(pos, quat, jnp.asarray(err0))
    left = np.abs(err(*first)).max()
    assert np.abs(err0).max() > 1e-4 and 1e-12 < left < 1e-6  # the projection leaves a second-order error
    assert np.abs(err(*closed)).max() < 1e-14 and np.abs(err(*projected)).max() < 1e-12
    assert 1e-3 * left < np.abs(np.asarray(closed[0]) - np.asarray(first[0])).max() < 10 * left  # it moved
    assert np.abs(np.asarray(closed[0]) - np.asarray(projected[0])).max() < 10 * left
    assert np.abs(np.asarray(closed[1]) - np.asarray(projected[1])).max() < 10 * left
