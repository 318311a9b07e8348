"""K and D in closed form (physics/stiffness.joint_blocks, gyro_blocks) against jax.jacfwd, the
SO(3) log-map derivative they use, and the post-stabilization metric reused across Newton steps."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.config import DEFAULT_HIT, SimulationConfig
from neuromotor.model.topology import of_tree
from neuromotor.physics.dynamics import SimModel, reference_inputs, rollout
from neuromotor.physics.solvers import nullspace
from neuromotor.physics.stiffness import Jacobians, stiff_blocks
from neuromotor.rotations import quat_exp, quat_log, quat_mul, right_jacobian_inv
from neuromotor.studies.simulate import load_character, prepare

from test_nullspace import PARENT, _random_tree


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
    run = jax.jit(rollout, static_argnames="cfg")(setup.model, setup.gains, setup.pulses, setup.ref, setup.sim)
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
    sim = SimModel(m, setup.ref, setup.sim)
    inputs = reference_inputs(sim, setup.gains, k)
    blocks = {j: jax.jit(lambda j=j: stiff_blocks(m, setup.gains, inputs, state, j))() for j in Jacobians}
    closed, ref = blocks[Jacobians.CLOSED_FORM], blocks[Jacobians.JACFWD]
    for name in ("k", "k_diag", "k_up", "k_down", "d_diag", "d_up", "d_down"):
        a, b = np.asarray(getattr(closed, name)), np.asarray(getattr(ref, name))
        assert np.abs(b).max() > 0, name
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max(), err_msg=name)


def test_rollout_with_closed_form_blocks_equals_jacfwd_rollout(hit):
    setup, run = hit
    other = jax.jit(rollout, static_argnames="cfg")(setup.model, setup.gains, setup.pulses, setup.ref,
                                                     dataclasses.replace(setup.sim, jacobians="jacfwd"))
    assert float(jnp.abs(run.theta - other.theta).max()) < 1e-11
    assert float(jnp.abs(run.states.omega - other.states.omega).max()) < 1e-9


@pytest.mark.parametrize("tree", [False, True])
def test_reused_metric_keeps_the_constraint_step_exact(tree):
    """Post-stabilization factors S^T M S once: at a later iterate the step with the first
    iterate's metric still satisfies J dx = -C exactly, and differs from the step with a fresh
    metric in proportion to how far the configuration moved (first order)."""
    rng, n, mass, inertia, r_parent, r_child, r0 = _random_tree(4)
    st = nullspace.structure(of_tree(PARENT), unrolled=tree)
    geo = lambda rp, rc: nullspace.geometry(st, jnp.asarray(rp), jnp.asarray(rc), jnp.asarray(r0))
    first = nullspace.projection_metric(st, geo(r_parent, r_child), jnp.asarray(mass), jnp.asarray(inertia), tree)
    nc = 6 + 3 * (n - 1)
    c = 1e-6 * rng.normal(size=nc)
    direction = rng.normal(size=r_parent.shape)
    gaps = []
    for scale in (1e-4, 1e-5):  # the later iterate: levers turned by about this many radians
        turn = scale * direction
        rp2, rc2 = r_parent + np.cross(turn, r_parent), r_child + np.cross(turn, r_child)
        g2 = geo(rp2, rc2)
        step = lambda metric: np.asarray(jax.jit(lambda g: nullspace.projection_step(
            st, g, jnp.asarray(mass), jnp.asarray(inertia), jnp.asarray(c), tree, metric))(g2))
        fresh, reused = step(None), step(first)
        for dx in (fresh, reused):  # J dx = -C at the later iterate, whichever metric
            _, rows = nullspace.kkt_residual(st, g2, jnp.asarray(rp2), jnp.asarray(rc2), jnp.zeros((n, 6)),
                                             jnp.asarray(dx), jnp.zeros(nc), jnp.asarray(-c), of_tree(PARENT).parent)
            np.testing.assert_allclose(rows, 0.0, atol=1e-15 * np.abs(c).max())
        gaps.append(np.abs(reused - fresh).max() / np.abs(fresh).max())
    assert 0 < gaps[0] < 0.05
    assert 5 < gaps[0] / gaps[1] < 20  # first order in the configuration change
