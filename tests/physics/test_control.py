"""The controller of Section 5.2 (physics/control.py), tested on its own: the feedback multipliers,
their signal dependence and floor, the PD-tracking variant, the joint torque in both of its forms
(rotation matrices and quaternions) against a closed-form case, and its damping block."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.physics.control import (DAMPING, ControllerInputs, Gains, feedback_multipliers, joint_torque,
                                        joint_torque_q, pd_tracking_gains, rate_feedback_gains)
from neuromotor.rotations import axis_rotation, euler_to_matrix, matrix_to_quat

jax.config.update("jax_enable_x64", True)


def _gains(n=3, **kw):
    base = dict(ks=jnp.asarray(400.0), kd=jnp.asarray(20.0), scale=jnp.array([0.5, 2.0, 1.0][:n]),
                floor=jnp.array([1.0, 3.0, 0.5][:n]), reference_torque=jnp.array([2.0, 6.0, 1.0][:n]))
    base.update(kw)
    return Gains(**base)


def test_feedback_multipliers_hand_computed():
    g = _gains()
    tau, act = jnp.array([1.5, -2.0, 0.25]), jnp.array([4.0, 1.0, 0.1])
    e, edot = jnp.array([0.1, -0.2, 0.3]), jnp.array([1.0, 0.5, -2.0])
    # DOF 0: magnitude max(4, 1) = 4: 1.5 + 4 (400*0.5*0.1 + 20*0.5*1.0) = 1.5 + 4 * 30 = 121.5
    # DOF 1: magnitude max(1, 3) = 3 (the floor): -2 + 3 (400*2*(-0.2) + 20*2*0.5) = -2 + 3 * (-140) = -422
    # DOF 2: magnitude max(0.1, 0.5) = 0.5: 0.25 + 0.5 (400*0.3 + 20*(-2)) = 0.25 + 0.5 * 80 = 40.25
    np.testing.assert_allclose(feedback_multipliers(g, tau, act, e, edot), [121.5, -422.0, 40.25], rtol=1e-15)
    active = jnp.array([1.0, 0.0, 1.0])
    np.testing.assert_allclose(feedback_multipliers(g, tau, act, e, edot, active), [121.5, 0.0, 40.25], rtol=1e-15)


def test_signal_dependence_and_floor():
    g = _gains(1, scale=jnp.array([1.0]), floor=jnp.array([2.0]), reference_torque=jnp.array([4.0]))
    e = jnp.array([0.01])
    fb = lambda gains, a: float(feedback_multipliers(gains, jnp.zeros(1), jnp.array([a]), e, jnp.zeros(1))[0])
    # Above the floor the stiffness grows in proportion to the activation ...
    assert fb(g, 10.0) == pytest.approx(2.0 * fb(g, 5.0), rel=1e-14)
    # ... below it the floor holds it constant.
    assert fb(g, 0.5) == pytest.approx(fb(g, 1.5), rel=1e-14) == pytest.approx(2.0 * 400.0 * 0.01, rel=1e-14)
    # signal_dependence = 0: constant stiffness at the floor, whatever the activation.
    flat = dataclasses.replace(g, signal_dependence=jnp.asarray(0.0))
    assert fb(flat, 10.0) == pytest.approx(fb(flat, 0.0), rel=1e-14)


def test_pd_tracking_gains_is_a_plain_pd_servo():
    g = pd_tracking_gains(_gains())
    tau, act = jnp.array([5.0, -7.0, 3.0]), jnp.array([100.0, 0.0, 8.0])
    e, edot = jnp.array([0.1, -0.2, 0.3]), jnp.array([1.0, 0.5, -2.0])
    # No feedforward, and ks I_j, kd I_j with I_j = scale * reference_torque, independent of |T_j|.
    inertia = np.array([0.5 * 2.0, 2.0 * 6.0, 1.0 * 1.0])
    want = 400.0 * inertia * np.asarray(e) + 20.0 * inertia * np.asarray(edot)
    np.testing.assert_allclose(feedback_multipliers(g, tau, act, e, edot), want, rtol=1e-14)


def test_multipliers_are_linear_in_the_rate_error_with_rate_feedback_gains():
    g = _gains()
    tau, act, e = jnp.array([1.5, -2.0, 0.25]), jnp.array([4.0, 1.0, 0.1]), jnp.array([0.1, -0.2, 0.3])
    active = jnp.array([1.0, 0.0, 1.0])
    f = lambda edot: feedback_multipliers(g, tau, act, e, edot, active)
    jac = jax.jacfwd(f)(jnp.array([0.3, -1.0, 2.0]))
    np.testing.assert_allclose(jac, np.diag(rate_feedback_gains(g, act, active)), rtol=1e-15, atol=0)
    x, y = jnp.array([0.3, -1.0, 2.0]), jnp.array([-4.0, 0.2, 1.0])
    np.testing.assert_allclose(f(x + y) - f(x), jac @ y, rtol=1e-12)


def _one_joint(theta_d, rel_rot, rel_omega, gains, tau, act, order="XYZ"):
    """ControllerInputs of a single joint (C = 1)."""
    a0, a1, a2 = ("XYZ".index(c) for c in order)
    r1 = axis_rotation(a0, theta_d[0])
    r2 = r1 @ axis_rotation(a1, theta_d[1])
    local = jnp.stack([jnp.eye(3)[a0], r1[:, a1], r2[:, a2]], -1)
    row = lambda x: jnp.asarray(x)[None]
    return ControllerInputs(row(tau), row(act), row(theta_d), row(rel_rot), row(rel_omega), row(local),
                            row(matrix_to_quat(rel_rot)), row(gains.scale), row(gains.floor),
                            row(gains.reference_torque), row(jnp.ones(3)))


def test_joint_torque_closed_form():
    """Parent at identity, desired pose identity, the child turned by phi about x and spinning at w
    about x: the errors are -phi and -w along h_1 = x (shrunk by the damping 1 / (1 + mu^2))."""
    g = _gains()
    phi, w = 0.05, 0.7
    tau, act = jnp.array([0.2, -0.1, 0.3]), jnp.array([2.0, 2.0, 2.0])
    inp = _one_joint(jnp.zeros(3), jnp.eye(3), jnp.zeros(3), g, tau, act)
    rot_p, rot_c = jnp.eye(3)[None], axis_rotation(0, jnp.asarray(phi))[None]
    w_p, w_c = jnp.zeros((1, 3)), jnp.array([[w, 0.0, 0.0]])
    shrink = 1.0 / (1.0 + DAMPING**2)
    mag = np.maximum(np.asarray(act), np.asarray(g.floor))
    err = np.array([-phi, 0.0, 0.0]) * shrink
    rate = np.array([-w, 0.0, 0.0]) * shrink
    want = np.asarray(tau) + mag * np.asarray(g.scale) * (400.0 * err + 20.0 * rate)
    got = joint_torque(g, rot_p, rot_c, w_p, w_c, inp)[0]
    np.testing.assert_allclose(got, want, rtol=1e-13)
    got_q, _ = joint_torque_q(g, matrix_to_quat(rot_p[0]), matrix_to_quat(rot_c[0]), w_p[0], w_c[0],
                              jax.tree_util.tree_map(lambda x: x[0], inp))
    np.testing.assert_allclose(got_q, want, rtol=1e-13)


@pytest.mark.parametrize("order", ["ZXY", "XZY"])
def test_matrix_and_quaternion_forms_agree_with_damping_block_by_jacfwd(order):
    rng = np.random.default_rng(3)
    g = _gains()
    theta_d = jnp.asarray(rng.uniform(-1.2, 1.2, 3))
    rel_d = euler_to_matrix(theta_d, order)
    inp = _one_joint(theta_d, rel_d, jnp.asarray(rng.normal(size=3)), g, jnp.asarray(rng.normal(size=3)),
                     jnp.asarray(rng.uniform(0.1, 5.0, 3)), order)
    rot_p = euler_to_matrix(jnp.asarray(rng.normal(size=3)), "XYZ")
    rot_c = rot_p @ euler_to_matrix(theta_d + 0.1 * jnp.asarray(rng.normal(size=3)), order)
    w_p, w_c = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=3))
    one = jax.tree_util.tree_map(lambda x: x[0], inp)
    by_matrix = joint_torque(g, rot_p[None], rot_c[None], w_p[None], w_c[None], inp)[0]
    q_p, q_c = matrix_to_quat(rot_p), matrix_to_quat(rot_c)
    by_quat, damping = joint_torque_q(g, q_p, q_c, w_p, w_c, one)
    np.testing.assert_allclose(by_quat, by_matrix, rtol=1e-12, atol=1e-12 * float(jnp.abs(by_matrix).max()))
    d_child = jax.jacfwd(lambda w: joint_torque_q(g, q_p, q_c, w_p, w, one)[0])(w_c)
    d_parent = jax.jacfwd(lambda w: joint_torque_q(g, q_p, q_c, w, w_c, one)[0])(w_p)
    np.testing.assert_allclose(damping, d_child, rtol=1e-12, atol=1e-12 * float(jnp.abs(d_child).max()))
    np.testing.assert_allclose(d_parent, -d_child, rtol=1e-12, atol=1e-12 * float(jnp.abs(d_child).max()))


def test_joint_torque_rotation_derivative_by_finite_differences():
    """d torque / d (world rotation of the child), jacfwd against central differences."""
    rng = np.random.default_rng(5)
    g = _gains()
    theta_d = jnp.asarray(rng.uniform(-0.8, 0.8, 3))
    inp = _one_joint(theta_d, euler_to_matrix(theta_d, "XYZ"), jnp.zeros(3), g, jnp.asarray(rng.normal(size=3)),
                     jnp.full(3, 2.0))
    rot_p = euler_to_matrix(jnp.asarray(rng.normal(size=3)), "XYZ")
    rot_c = rot_p @ euler_to_matrix(theta_d + 0.05, "XYZ")
    w = jnp.zeros(3)

    def torque(d):
        turned = jnp.asarray(jax.scipy.linalg.expm(jnp.asarray([[0, -d[2], d[1]], [d[2], 0, -d[0]],
                                                                 [-d[1], d[0], 0]]))) @ rot_c
        return joint_torque(g, rot_p[None], turned[None], w[None], w[None], inp)[0]

    jac = jax.jacfwd(torque)(jnp.zeros(3))
    eps = 1e-6
    fd = np.stack([(torque(eps * e) - torque(-eps * e)) / (2 * eps) for e in jnp.eye(3)], -1)
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-6 * float(np.abs(fd).max()))
    assert float(jnp.abs(jac).max()) > 0
