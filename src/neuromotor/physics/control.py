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
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor.model.kinematics import body_kinematics
from neuromotor.model.skeleton import Model
from neuromotor.physics.system import dof_axes, dofs_to_per_joint, per_joint_to_dofs

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

    def per_dof(self) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        return self.ks * self.scale, self.kd * self.scale


def distal_inertia(model: Model, q0: Float[Array, " Q"], theta0: Float[Array, " n"]) -> Float[Array, " n"]:
    """I_i: inertia of the chain distal to DOF i's joint, about the DOF axis through the joint."""
    zeros = jnp.zeros_like(q0)
    pos, rot, *_ = body_kinematics(model, q0, zeros, zeros)
    axes = dof_axes(model, rot, theta0)
    iw = rot @ model.inertia @ jnp.swapaxes(rot, -1, -2)
    # in_sub[b, c] = 1 if body c is in the subtree of body b (static mask: one contraction
    # instead of a Python double loop over bodies).
    in_sub = np.zeros((model.n_bodies, model.n_bodies))
    for b, members in enumerate(_subtrees(model)):
        in_sub[b, members] = 1.0
    origin = pos - jnp.einsum("bij,bj->bi", rot, model.com)  # joint origin of each body
    r = pos[None, :, :] - origin[:, None, :]  # (b, c, 3): body c's COM from joint b
    eye = jnp.eye(3, dtype=q0.dtype)
    steiner = model.mass[None, :, None, None] * (
        jnp.sum(r * r, -1)[..., None, None] * eye - r[..., :, None] * r[..., None, :])
    total = jnp.einsum("bc,bcij->bij", in_sub, iw[None] + steiner)
    per_body = total[np.array(model.dof_body)]
    return jnp.einsum("ni,nij,nj->n", axes, per_body, axes)


def _subtrees(model: Model) -> list[list[int]]:
    sub = [[b] for b in range(model.n_bodies)]
    for b in reversed(range(1, model.n_bodies)):
        sub[model.body_parent[b]].extend(sub[b])
    return sub


@jax.jit
def make_gains(
    model: Model,
    q0: Float[Array, " Q"],
    theta0: Float[Array, " n"],
    activation: Float[Array, "T n"],
    ks: float = DEFAULT_KS,
    kd: float = DEFAULT_KD,
    tau_floor: float = DEFAULT_TAU_FLOOR,
) -> Gains:
    per_dof = distal_inertia(model, q0, theta0)
    # One value per joint: the mean over its three DOF axes.
    inertia = per_joint_to_dofs(model, jnp.repeat(jnp.mean(dofs_to_per_joint(model, per_dof), -1, keepdims=True), 3, -1))
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
    return dataclasses.replace(gains, floor=gains.reference_torque, feedforward=zero,
                               signal_dependence=zero)


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
    :func:`joint_torque_projection`).
    """
    ks, kd = gains.per_dof()
    magnitude = _feedback_magnitude(gains, activation)
    out = gains.feedforward * tau + magnitude * (ks * angle_error + kd * rate_error)
    return out if active is None else out * active


def rate_feedback_gains(gains: Gains, activation: Float[Array, " n"],
                        active: Float[Array, " n"] | None = None) -> Float[Array, " n"]:
    """d(multiplier_i) / d(rate error_i): the multipliers of :func:`feedback_multipliers` are
    linear in the rate error, with this slope per DOF. The damping block D of Eq. 2 is built
    from it in closed form instead of by a tangent through the controller."""
    out = _feedback_magnitude(gains, activation) * gains.per_dof()[1]
    return out if active is None else out * active


def _feedback_magnitude(gains: Gains, activation):
    return jnp.maximum(gains.signal_dependence * activation, gains.floor)
