"""The rollout's observation: joint angles and rates of many states at once
(:func:`neuromotor.physics.system.joint_angles_and_rates`, :func:`neuromotor.rotations.euler_angles_and_rates`).

Held to the definitions joint by joint (the Euler decomposition of each relative rotation and
the solve ``sum_i h_i theta_dot_i = w_child - w_parent`` over the Euler axes), to central
differences of the angles along the motion, and at gimbal lock in every Euler order, on every
shipped clip and on generated skeletons with mixed rotation orders.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import ALL_CLIPS
from neuromotor.physics import system
from neuromotor.rotations import (euler_angles_and_rates, euler_axes, euler_to_matrix, matrix_to_euler, quat_entries,
                                  quat_exp, quat_mul, quat_normalize, quat_to_matrix)
from neuromotor.studies.simulate import load_character
from tests.synthetic_rigs import ORDERS, make_rig


def _random_states(n_bodies: int, count: int, seed: int = 0):
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    quat = quat_normalize(jax.random.normal(k1, (count, n_bodies, 4), jnp.float64))
    return quat, jax.random.normal(k2, (count, n_bodies, 3), jnp.float64)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """The embedded clip, every shipped clip, and two generated rigs (random Euler orders per joint,
    fingers, six channels on every joint in one)."""
    out = [load_character(None)[0].model] + [load_character(c)[0].model for c in ALL_CLIPS.values()]
    for seed in (2, 5):
        path = tmp_path_factory.mktemp("rigs") / f"rig{seed}.bvh"
        path.write_text(make_rig(seed, frames=40, fingers=True, six_channels=seed == 5).text)
        out.append(load_character(path)[0].model)
    return out


def _observe(model, with_reference: bool):
    """The observation of a batch of states, compiled (one program instead of op-by-op dispatch)."""
    if with_reference:
        return jax.jit(jax.vmap(lambda q, w, f: system.joint_angles_and_rates(model, q, w, f)))
    return jax.jit(jax.vmap(lambda q, w: system.joint_angles_and_rates(model, q, w)))


def test_clips_are_found():
    assert len(ALL_CLIPS) >= 4, "../shared/mocap must be beside the repository"


def _per_joint(model, quat, omega, reference):
    """The definitions joint by joint: theta from each body's rotation in its parent's frame, and
    theta_dot from ``sum_i h_i theta_dot_i = w_child - w_parent`` over the Euler axes h_i."""
    rot = np.asarray(quat_to_matrix(quat))
    omega = np.asarray(omega)
    theta, rates = np.zeros((len(rot), model.n_dofs)), np.zeros((len(rot), model.n_dofs))
    for b in range(1, model.n_bodies):
        p = model.body_parent[b]
        order = model.joint_order[model.body_joint[b]]
        dofs = np.array(model.dofs_of_body(b))
        ref = None if reference is None else np.asarray(reference)[:, dofs]
        ang = np.asarray(matrix_to_euler(np.swapaxes(rot[:, p], -1, -2) @ rot[:, b], order, ref))
        axes = np.asarray(euler_axes(rot[:, p], ang, order))  # rows h_i
        theta[:, dofs] = ang
        rates[:, dofs] = np.linalg.solve(np.swapaxes(axes, -1, -2), (omega[:, b] - omega[:, p])[..., None])[..., 0]
    return theta, rates


def test_angles_and_rates_equal_the_per_joint_definitions(models):
    """With a reference branch (as rollouts observe) on every clip and on rigs whose joints mix
    rotation orders (several groups in one skeleton); without one on the first skeleton."""
    mixed = False
    for n, model in enumerate(models):
        mixed |= len(model.topology.groups) > 1
        quat, omega = _random_states(model.n_bodies, 64)
        plain, _ = _per_joint(model, quat, omega, None)
        reference = plain + 0.6 * np.asarray(jax.random.normal(jax.random.PRNGKey(1), plain.shape))
        for ref in ((None, reference) if n == 0 else (reference,)):
            want, want_rates = _per_joint(model, quat, omega, ref)
            args = (quat, omega) if ref is None else (quat, omega, ref)
            theta, rates = _observe(model, ref is not None)(*args)
            assert theta.shape == rates.shape == (64, model.n_dofs)
            np.testing.assert_allclose(theta, want, rtol=0, atol=1e-12)
            # Random rotations come near gimbal lock, where both forms lose digits alike.
            cond = 1.0 / np.abs(np.cos(want[:, 1::3])).min()
            np.testing.assert_allclose(rates, want_rates, rtol=0, atol=1e-13 * cond * np.abs(want_rates).max())
    assert mixed, "no generated skeleton mixed rotation orders"


def test_rates_are_the_derivative_of_the_angles():
    """theta_dot against central differences of theta along the motion exp(t w) q."""
    model = load_character(None)[0].model
    quat, omega = _random_states(model.n_bodies, 16, seed=3)
    quat = quat_normalize(quat * jnp.array([4.0, 1.0, 1.0, 1.0]))  # away from gimbal lock
    ref, _ = _per_joint(model, quat, omega, None)
    at = lambda t: jax.vmap(lambda q, w, f: system.joint_angles_and_rates(
        model, quat_mul(quat_exp(t * w), q), w, f)[0])(quat, omega, ref)
    eps = 1e-5
    numeric = (at(eps) - at(-eps)) / (2 * eps)
    _, rates = jax.vmap(lambda q, w, f: system.joint_angles_and_rates(model, q, w, f))(quat, omega, ref)
    np.testing.assert_allclose(rates, numeric, rtol=0, atol=1e-7 * float(jnp.abs(rates).max()))


@pytest.mark.parametrize("order", ORDERS)
def test_every_order_round_trips_and_keeps_the_reference_at_lock(order):
    angles = jnp.array([[0.4, 0.3, -0.7], [2.9, -1.2, 3.0], [-0.4, jnp.pi / 2 - 1e-9, 0.25],
                        [1.1, -jnp.pi / 2 + 1e-10, -2.0]])
    r = euler_to_matrix(angles, order)
    ref = angles + jnp.array([0.05, -0.02, 0.03])
    for reference in (None, ref):
        ang, rates = euler_angles_and_rates(lambda a, b: r[..., a, b], jnp.zeros((4, 3)), order, reference)
        # Near lock only t1 + s t3 is resolved: the same 5e-11 as the matrix form before it.
        np.testing.assert_allclose(euler_to_matrix(ang, order), r, rtol=0, atol=1e-10)
        np.testing.assert_allclose(ang, matrix_to_euler(r, order, reference), rtol=0, atol=0)
        np.testing.assert_allclose(rates, 0.0, atol=0)
    ang = matrix_to_euler(r, order, ref)
    np.testing.assert_allclose(ang[:2], angles[:2], rtol=0, atol=1e-12)  # the branch nearest the reference
    np.testing.assert_allclose(ang[2:, 0], ref[2:, 0], rtol=0, atol=1e-12)  # at lock t1 stays at the reference
    exact = euler_to_matrix(jnp.array([1.1, jnp.pi / 2, -2.0]), order)
    ang = matrix_to_euler(exact, order, jnp.array([1.0, 1.5, -2.1]))
    np.testing.assert_allclose(euler_to_matrix(ang, order), exact, rtol=0, atol=1e-14)
    assert float(ang[0]) == 1.0
    # quat_entries gives the matrix's entries
    q = jnp.array([0.3, -0.5, 0.1, 0.8]) / jnp.linalg.norm(jnp.array([0.3, -0.5, 0.1, 0.8]))
    entry = quat_entries(q)
    np.testing.assert_allclose([[entry(a, b) for b in range(3)] for a in range(3)], quat_to_matrix(q), atol=1e-15)


def test_compiled_tangents_equal_central_differences():
    """The forward-mode tangent of the observation, compiled (as inside a fit's ``jacfwd``),
    against central differences. A tangent through ``jnp.hypot`` of quaternion entries once came
    out wrong from XLA:CPU under the suite's compile flags while the eager one was right."""
    model = load_character(None)[0].model
    quat, omega = _random_states(model.n_bodies, 32, seed=4)
    quat = quat_normalize(quat * jnp.array([3.0, 1.0, 1.0, 1.0]))
    k1, k2 = jax.random.split(jax.random.PRNGKey(5))
    dq, dw = jax.random.normal(k1, quat.shape, jnp.float64), jax.random.normal(k2, omega.shape, jnp.float64)
    ref, _ = _per_joint(model, quat, omega, None)
    ref = ref + 0.2
    f = lambda q, w: jax.vmap(lambda a, b, c: system.joint_angles_and_rates(model, quat_normalize(a), b, c))(q, w, ref)
    (theta, rates), (d_theta, d_rates) = jax.jit(lambda q, w, a, b: jax.jvp(f, (q, w), (a, b)))(quat, omega, dq, dw)
    eps = 1e-6
    (tp, rp), (tm, rm) = f(quat + eps * dq, omega + eps * dw), f(quat - eps * dq, omega - eps * dw)
    np.testing.assert_allclose(d_theta, (tp - tm) / (2 * eps), rtol=0, atol=1e-7 * float(jnp.abs(d_theta).max()))
    np.testing.assert_allclose(d_rates, (rp - rm) / (2 * eps), rtol=0, atol=1e-7 * float(jnp.abs(d_rates).max()))
