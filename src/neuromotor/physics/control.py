"""The neuromotor controller of Section 5.2: feedforward plus low-gain, signal-dependent feedback.

For every simulated DOF i (Eq. 4 and Section 5.2):

    psi_i   = h_i tau_i(t)                                              (feedforward)
    gamma_i = h_i |tau_i| (ks_i (theta_di - theta_i) + kd_i (thetadot_di - thetadot_i))
    xi      = sum_i (gamma_i + psi_i)

Gains. One pair (ks, kd) sets every DOF: ``ks_i = ks * s_j`` and ``kd_i = kd * s_j`` for the DOFs
of joint j, with ``s_j = I_j / rms_t(|T_j|)``. I_j is the moment of inertia of the chain of bodies
distal to the joint, about the joint (mean over its three DOF axes, clip's first frame); T_j is
the joint's feedforward muscle torque ``sum_i h_i tau_i`` over its DOFs. The feedback torque of
a DOF is then

    a_j ks_i (theta_d - theta) = (a_j / rms(|T_j|)) * ks * I_j * (theta_d - theta),

so **ks is in 1/s^2 and kd in 1/s**: at typical load, sqrt(ks) is the natural frequency (rad/s)
of a joint's distal chain and kd / (2 sqrt(ks)) its damping ratio. Gains are proportional to
the distal inertia (the paper, after Zordan & Hodgins) and to the muscle torque (stiffness grows
with activation).

Signal dependence per joint, not per DOF. The paper writes |tau_i| per DOF. We use the joint's
torque magnitude a_j = |T_j| for all three DOFs of a joint, and share s_j among them. With
per-DOF weights W the joint's feedback stiffness is A W A^-1 (A = [h_1 h_2 h_3]), which is not
symmetric whenever the Euler axes are not orthogonal; near gimbal lock its symmetric part turns
indefinite and the joint gains energy. On the MocapBank clip this destabilized the hip at 78
degrees of flexion for every gain we tried. With one weight per joint the feedback torque is
``w_j A A^-1 e = w_j e``: isotropic, conservative, and bounded at lock.

Floor. Where the feedforward torque passes through zero the feedback would vanish; a_j is
replaced by ``max(a_j, floor_j)`` with ``floor_j = tau_floor * rms_t(|T_j|)`` (default
``tau_floor = 0.5``: the feedback never drops below half its value at typical load).

High-gain tracking for contrast (Zordan & Hodgins 2002, the controller the paper argues
against). ``Gains.feedforward`` (1: the paper's model, 0: none) weights the feedforward term
and ``Gains.signal_dependence`` (1: stiffness grows with |T_j|, 0: constant) its effect on the
feedback. With both 0 and ``tau_floor = 1`` the controller is a plain PD servo whose gains are
``ks I_j`` and ``kd I_j``: :func:`pd_tracking_gains`.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor import compiler
from neuromotor.model.kinematics import body_kinematics
from neuromotor.model.skeleton import Model
from neuromotor.physics.balance import Balance
from neuromotor.physics.reflex import Reflex, reflex_multipliers
from neuromotor.physics.system import dofs_to_per_joint, per_joint_to_dofs, world_inertia
from neuromotor.rotations import (
    AXIS,
    axis_rotation,
    inv3,
    matrix_to_quat,
    mm,
    mmt,
    mtv,
    mv,
    quat_conj,
    quat_log,
    quat_mul,
    quat_to_matrix,
)

DEFAULT_KS = 400.0  # 1/s^2: natural frequency 20 rad/s (3.2 Hz) at typical load
DEFAULT_KD = 20.0  # 1/s: damping ratio 0.5
DEFAULT_TAU_FLOOR = 0.5


class Gains(eqx.Module):
    """The fitted pair and the fixed per-DOF scaling (all array leaves)."""

    ks: Float[Array, ""]
    kd: Float[Array, ""]
    scale: Float[Array, " n"]  # s_j = I_j / rms|T_j| per DOF of joint j (kg m^2 / N m)
    floor: Float[Array, " n"]  # torque floor per DOF (N m)
    reference_torque: Float[Array, " n"]  # rms_t |T_j| of each DOF's joint (N m)
    feedforward: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.asarray(1.0))
    signal_dependence: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.asarray(1.0))
    reflex: Reflex | None = None  # the delayed stretch reflex (neuromotor.physics.reflex); None: the paper's
    balance: Balance | None = None  # the postural loop (neuromotor.physics.balance); None: none

    def per_dof(self) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        return self.ks * self.scale, self.kd * self.scale


def distal_inertia(model: Model, q0: Float[Array, " Q"], local_axes: Float[Array, "C 3 3"]) -> Float[Array, " n"]:
    """I_i: inertia of the chain distal to DOF i's joint, about the DOF's axis through the joint
    (``local_axes``: each joint's axes in its parent's frame, columns, as ``Reference.local_axes``)."""
    zeros = jnp.zeros_like(q0)
    pos, rot, *_ = body_kinematics(model, q0, zeros, zeros)
    axes = per_joint_to_dofs(model, jnp.swapaxes(mm(rot[model.topology.parent], local_axes), -1, -2))
    iw = world_inertia(model, rot)
    # in_sub[b, c] = 1 if body c is in the subtree of body b (static mask: one contraction
    # instead of a Python double loop over bodies).
    in_sub = np.zeros((model.n_bodies, model.n_bodies))
    for b, members in enumerate(_subtrees(model)):
        in_sub[b, members] = 1.0
    origin = pos - jnp.einsum("bij,bj->bi", rot, model.com)  # joint origin of each body
    r = pos[None, :, :] - origin[:, None, :]  # (b, c, 3): body c's COM from joint b
    eye = jnp.eye(3, dtype=q0.dtype)
    steiner = model.mass[None, :, None, None] * (
        jnp.sum(r * r, -1)[..., None, None] * eye - r[..., :, None] * r[..., None, :]
    )
    total = jnp.einsum("bc,bcij->bij", in_sub, iw[None] + steiner)
    per_body = total[np.array(model.dof_body)]
    return jnp.einsum("ni,nij,nj->n", axes, per_body, axes)


def _subtrees(model: Model) -> list[list[int]]:
    sub = [[b] for b in range(model.n_bodies)]
    for b in reversed(range(1, model.n_bodies)):
        sub[model.body_parent[b]].extend(sub[b])
    return sub


@compiler.jit
def make_gains(
    model: Model,
    q0: Float[Array, " Q"],
    local_axes: Float[Array, "C 3 3"],
    activation: Float[Array, "T n"],
    ks: float = DEFAULT_KS,
    kd: float = DEFAULT_KD,
    tau_floor: float = DEFAULT_TAU_FLOOR,
) -> Gains:
    per_dof = distal_inertia(model, q0, local_axes)
    # One value per joint: the mean over its three axes (a third of the trace for the rotation
    # law's orthonormal axes: the same for every Euler order).
    inertia = per_joint_to_dofs(
        model, jnp.repeat(jnp.mean(dofs_to_per_joint(model, per_dof), -1, keepdims=True), 3, -1)
    )
    rms = jnp.sqrt(jnp.mean(activation**2, axis=0))
    # A DOF that carries no load at all still gets feedback at a tiny reference torque.
    rms = jnp.maximum(rms, 1e-6 * jnp.max(rms))
    scale = inertia / rms
    dtype = scale.dtype
    return Gains(jnp.asarray(ks, dtype), jnp.asarray(kd, dtype), scale, tau_floor * rms, rms)


def pd_tracking_gains(gains: Gains) -> Gains:
    """The same per-DOF scaling as a high-gain PD tracker: no feedforward, constant stiffness.

    The floor becomes the joint's RMS torque, so ``floor * scale = I_j`` and the feedback
    torque of DOF i is ``ks I_j (theta_d - theta) + kd I_j (thetadot_d - thetadot)``.
    """
    zero = jnp.zeros_like(gains.ks)
    return dataclasses.replace(gains, floor=gains.reference_torque, feedforward=zero, signal_dependence=zero)


def joint_torque_magnitude(model: Model, axes: Float[Array, "T n 3"], tau: Float[Array, "T n"]) -> Float[Array, "T n"]:
    """|T_j| of each DOF's joint, where T_j = sum over the joint's DOFs of h_i tau_i.

    Unlike the individual tau_i, which grow large with opposite signs near gimbal lock, the
    joint torque stays bounded.
    """
    contrib = dofs_to_per_joint(model, jnp.moveaxis(axes * tau[..., None], -2, 0))  # (C, 3, T, 3)
    total = jnp.linalg.norm(jnp.sum(contrib, axis=1), axis=-1)  # (C, T)
    out = per_joint_to_dofs(model, jnp.repeat(total[:, None, :], 3, 1))  # (n, T)
    return jnp.moveaxis(out, 0, -1)


def feedback_multipliers(
    gains: Gains,
    tau: Float[Array, " n"],
    activation: Float[Array, " n"],
    angle_error: Float[Array, " n"],
    rate_error: Float[Array, " n"],
    active: Float[Array, " n"] | None = None,
) -> Float[Array, " n"]:
    """Feedforward plus feedback multiplier per DOF, so that xi = sum_i h_i * result_i.

    ``angle_error`` is theta_d - theta and ``rate_error`` thetadot_d - thetadot per DOF;
    ``activation`` is the signal-dependent magnitude that scales the feedback (|tau_i|, see
    :func:`neuromotor.physics.control.make_gains`).
    """
    ks, kd = gains.per_dof()
    magnitude = _feedback_magnitude(gains, activation)
    out = gains.feedforward * tau + magnitude * (ks * angle_error + kd * rate_error)
    return out if active is None else out * active


def rate_feedback_gains(
    gains: Gains, activation: Float[Array, " n"], active: Float[Array, " n"] | None = None
) -> Float[Array, " n"]:
    """d(multiplier_i) / d(rate error_i): the multipliers of :func:`feedback_multipliers` are
    linear in the rate error, with this slope per DOF. The damping block D of Eq. 2 is built
    from it in closed form instead of by a tangent through the controller."""
    out = _feedback_magnitude(gains, activation) * gains.per_dof()[1]
    return out if active is None else out * active


def _feedback_magnitude(gains: Gains, activation):
    return jnp.maximum(gains.signal_dependence * activation, gains.floor)


def reflex_torque(gains: Gains, history, h: float, axes, inp: ControllerInputs):
    """The delayed reflex (:mod:`neuromotor.physics.reflex`), signal-dependent and scaled like
    the muscle feedback: ``(rho, r)``, the world torque ``rho_j = sum_i h_i r_i`` on each
    joint's child (``axes``: the world Euler axes h_i as columns) and the multipliers r_i per
    joint and DOF (N m along h_i)."""
    g = inp.gains(gains)
    assert gains.reflex is not None  # called for gains with a reflex
    r = reflex_multipliers(
        gains.reflex,
        history,
        h,
        _feedback_magnitude(g, inp.activation),
        inp.scale,
        inp.tau,
        inp.reference_torque,
        inp.active,
    )
    return mv(axes, r), r


# ---------------------------------------------------------------- the joint torque (Section 5.2)

DAMPING = 0.02  # damped least squares at gimbal lock (singular value scale of the Euler axes)


class ControllerInputs(eqx.Module):
    """What the Section 5.2 torque of every joint reads at one grid step, per joint (leading
    axis C, joint c attaching body c + 1): the mocap's targets, the per-DOF gain scaling and the
    mask of the DOFs that are not driven. Everything here is independent of the state."""

    tau: Float[Array, "C 3"]  # feedforward multipliers tau_i (Eq. 3)
    activation: Float[Array, "C 3"]  # |T_j|, the signal that scales the feedback
    theta_d: Float[Array, "C 3"]  # desired Euler angles
    rel_rot: Float[Array, "C 3 3"]  # desired rotation of the child in the parent's frame
    rel_omega: Float[Array, "C 3"]  # desired relative angular velocity, parent frame
    local_axes: Float[Array, "C 3 3"]  # Euler axes h_i at theta_d in the parent's frame (columns)
    rel_quat: Float[Array, "C 4"]  # rel_rot as a quaternion
    scale: Float[Array, "C 3"]  # Gains.scale, per joint
    floor: Float[Array, "C 3"]  # Gains.floor, per joint
    reference_torque: Float[Array, "C 3"]  # Gains.reference_torque, per joint
    active: Float[Array, "C 3"]  # 0 on the DOFs of driven joints (their torque is not applied)
    # P_L: resolves a parent-frame error along the axes (None: the damped pseudo-inverse of
    # local_axes, the Euler law; the identity for the rotation law). See joint_affine.
    local_pinv: Float[Array, "C 3 3"] | None = None
    # The reference's motion over the step, for the feedback's implicit terms (None: the target
    # holds still over the step, the paper's step): [h w_parent(k+1), h w_child(k+1),
    # (w_c - w_p)(k+1) - (w_c - w_p)(k)], world frame. See stiffness.reference_drift.
    drift: Float[Array, "C 9"] | None = None

    def pinv(self) -> Float[Array, "C 3 3"]:
        return damped_pinv(self.local_axes) if self.local_pinv is None else self.local_pinv

    def gains(self, gains: Gains) -> Gains:
        """``gains`` with this joint's per-DOF leaves (the scalars ks, kd stay shared)."""
        return dataclasses.replace(gains, scale=self.scale, floor=self.floor, reference_torque=self.reference_torque)


def controller_inputs(
    model: Model,
    gains: Gains,
    active: Float[Array, " n"],
    tau,
    activation,
    theta_d,
    rel_rot: Float[Array, "B 3 3"],
    rel_omega: Float[Array, "B 3"],
    local_axes,
    rel_quat,
    local_pinv=None,
    drift=None,
) -> ControllerInputs:
    """Per-DOF (n) and per-body (B) values of one grid step regrouped per joint."""
    per = lambda x: dofs_to_per_joint(model, x)
    c = model.topology.child
    return ControllerInputs(
        per(tau),
        per(activation),
        per(theta_d),
        rel_rot[c],
        rel_omega[c],
        local_axes,
        rel_quat,
        per(gains.scale),
        per(gains.floor),
        per(gains.reference_torque),
        per(active),
        local_pinv,
        drift,
    )


def damped_pinv(la: Float[Array, "... 3 3"], mu: float = DAMPING) -> Float[Array, "... 3 3"]:
    """``L^T (L L^T + mu^2 1)^-1``: the damped pseudo-inverse of axes L (columns)."""
    gram = mmt(la, la) + mu**2 * jnp.eye(3, dtype=la.dtype)
    return mm(jnp.swapaxes(la, -1, -2), inv3(gram))


def joint_errors(rot_p, rot_c, w_p, w_c, pinv, rel_d, rel_w_d):
    """Angle and rate errors of joints (any leading shape) resolved along their axes by ``pinv``
    (P_L of :class:`JointAffine`, parent frame); see :func:`dof_errors`. With axes ``a = R_p L``
    this is the damped solve ``a^T (a a^T + mu^2)^-1 e = P_L R_p^T e``."""
    rel = mm(jnp.swapaxes(rot_p, -1, -2), rot_c)
    e_local = quat_log(matrix_to_quat(mmt(rel_d, rel)))  # R_p^T of the world error
    w_err = rel_w_d - mtv(rot_p, w_c - w_p)
    return mv(pinv, e_local), mv(pinv, w_err)


def dof_errors(model: Model, rot, omega, axes, rel_d, rel_w_d):
    """Per-DOF angle and rate errors (desired minus simulated) from rotation errors.

    The joint's rotation error (rotation vector taking the simulated relative orientation to
    the desired one, world frame) and relative angular-velocity error are resolved along the
    Euler axes h_i. To first order this is exactly theta_d - theta and thetadot_d - thetadot of
    the BVH decomposition, it is always the shortest rotation (no wrapping issue), and it stays
    bounded at gimbal lock, where Euler differences are ill-defined.
    """
    topo = model.topology
    c, p = topo.child, topo.parent
    a = jnp.swapaxes(dofs_to_per_joint(model, axes), -1, -2)
    pinv = damped_pinv(mm(jnp.swapaxes(rot[p], -1, -2), a))
    d_theta, d_rate = joint_errors(rot[p], rot[c], omega[p], omega[c], pinv, rel_d[c], rel_w_d[c])
    return per_joint_to_dofs(model, d_theta), per_joint_to_dofs(model, d_rate)


def joint_torque(gains: Gains, rot_p, rot_c, w_p, w_c, inp: ControllerInputs):
    """World muscle torque ``T_j = sum_i h_i (psi_i + gamma_i)`` of joints on their children
    (Eq. 4 and Section 5.2; each parent gets -T_j), from rotation matrices. The Euler axes h_i
    come from the desired angles placed in the simulated parent's frame: exactly Eq. 4 on the
    mocap, and the feedforward sum h_i tau_i stays well-conditioned near gimbal lock where the
    individual tau_i are large and of opposite signs. A joint's torque depends on its two
    bodies only."""
    a = mm(rot_p, inp.local_axes)  # columns h_i (the Euler axes at theta_d, or R_p for the rotation law)
    d_theta, d_rate = joint_errors(rot_p, rot_c, w_p, w_c, inp.pinv(), inp.rel_rot, inp.rel_omega)
    mult = feedback_multipliers(inp.gains(gains), inp.tau, inp.activation, d_theta, d_rate, inp.active)
    return mv(a, mult)


class JointAffine(eqx.Module):
    """A joint's Section 5.2 torque as an affine function of its errors in the parent's frame:

        T = R_p (t0 + Ks e + Kd w),    e = R_p^T log(R_p R_d R_c^T),  w = w_d - R_p^T (w_c - w_p).

    The Euler axes are ``a = R_p L`` (L: the axes at theta_d in the parent's frame), so the damped
    pseudo-inverse that resolves the errors along them is ``P = a^T (a a^T + mu^2 1)^-1 =
    P_L R_p^T`` with ``P_L = L^T (L L^T + mu^2 1)^-1``: the whole torque law apart from R_p is
    state-independent, ``t0 = L (ff tau)``, ``Ks = L diag(|T| ks_i) P_L``, ``Kd = L diag(|T| kd_i)
    P_L`` (signal dependence, gains and the active mask folded in). K and D of Eq. 2 then come
    in closed form (:func:`neuromotor.physics.stiffness.joint_blocks`)."""

    t0: Float[Array, "... 3"]
    ks: Float[Array, "... 3 3"]
    kd: Float[Array, "... 3 3"]


def joint_affine(gains: Gains, inp: ControllerInputs) -> JointAffine:
    """:class:`JointAffine` of joints (any leading shape) from their controller inputs."""
    g = inp.gains(gains)
    la, p_local = inp.local_axes, inp.pinv()
    stiff = _feedback_magnitude(g, inp.activation) * g.per_dof()[0] * inp.active  # d multiplier / d angle error
    weighted = lambda s: mm(la * s[..., None, :], p_local)
    return JointAffine(
        mv(la, g.feedforward * inp.tau * inp.active),
        weighted(stiff),
        weighted(rate_feedback_gains(g, inp.activation, inp.active)),
    )


def affine_torque(aff: JointAffine, q_p, q_c, w_p, w_c, inp: ControllerInputs):
    """``(T, R_p, e)``: the torque of :class:`JointAffine` from quaternions, with the parent's
    rotation and the world rotation error ``e = log(q_p q_d q_c^-1)`` that its derivatives use."""
    r_p = quat_to_matrix(q_p)
    e_world = quat_log(quat_mul(quat_mul(q_p, inp.rel_quat), quat_conj(q_c)))
    y = aff.t0 + mv(aff.ks, mtv(r_p, e_world)) + mv(aff.kd, inp.rel_omega - mtv(r_p, w_c - w_p))
    return mv(r_p, y), r_p, e_world


def joint_torque_q(gains: Gains, q_p, q_c, w_p, w_c, inp: ControllerInputs):
    """:func:`joint_torque` of one joint (or any leading shape) from quaternions, with its
    damping block, through :class:`JointAffine`.

    The rotation error is ``log(q_p q_d q_c^-1)``, the world-frame rotation vector of
    ``R_p R_d R_c^T``, the same vector as ``R_p log(R_d R_rel^T)`` of :func:`joint_errors`.
    Returns the torque and ``d torque / d w_c`` (= -d torque / d w_p) ``= -R_p Kd R_p^T``.
    """
    aff = joint_affine(gains, inp)
    torque, r_p, _ = affine_torque(aff, q_p, q_c, w_p, w_c, inp)
    return torque, -mm(r_p, mmt(aff.kd, r_p))


def joint_torques(model: Model, gains: Gains, inputs: ControllerInputs, rot, omega) -> Float[Array, "C 3"]:
    """:func:`joint_torque` of every joint (one batched call: the axes come with the inputs)."""
    c, p = model.topology.child, model.topology.parent
    return joint_torque(gains, rot[p], rot[c], omega[p], omega[c], inputs)


def body_torques(model: Model, joint_torque: Float[Array, "C 3"]) -> Float[Array, "B 3"]:
    """+T_j on each joint's child, -T_j on its parent (static one-hot selectors, no scatter)."""
    topo = model.topology
    return jnp.einsum("cb,ci->bi", jnp.asarray(topo.sel_child - topo.sel_parent, joint_torque.dtype), joint_torque)


def _local_axes(theta: Float[Array, "C 3"], order: str) -> Float[Array, "C 3 3"]:
    """Euler axes of joints in their parent's frame, as columns: ``h_i = R_p L[:, i]`` (Eq. 4).
    They depend on the desired angles only, so they stay outside the state Jacobians."""
    a0, a1, a2 = (AXIS[ax] for ax in order)
    eye = jnp.eye(3, dtype=theta.dtype)
    r1 = axis_rotation(a0, theta[..., 0])
    r2 = mm(r1, axis_rotation(a1, theta[..., 1]))
    return jnp.stack([jnp.broadcast_to(eye[a0], theta.shape), r1[..., :, a1], r2[..., :, a2]], -1)


def joint_local_axes(model: Model, theta_d: Float[Array, " n"]) -> Float[Array, "C 3 3"]:
    """:func:`_local_axes` of every joint, each group of joints with its own rotation order."""
    per = dofs_to_per_joint(model, theta_d)
    out = jnp.zeros((model.n_bodies - 1, 3, 3), theta_d.dtype)
    for order, _, rows in model.topology.groups:
        if len(rows) == model.n_bodies - 1:
            return _local_axes(per, order)
        out = out.at[rows].set(_local_axes(per[rows], order))
    return out
