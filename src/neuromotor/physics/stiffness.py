"""The stiff forces of Eq. 2 and their derivatives K = dk/dx and D = dk/dv.

Only the stiff forces -- the muscle torques of Section 5.2 (:mod:`neuromotor.physics.control`)
and the gyroscopic term -- depend on the state, and both are pure torques that depend on
orientations and angular velocities only, so K and D live in the angular-angular blocks; K is
taken over the position tangent space (3 translations and 3 world-frame rotations per body,
rotations perturbed as ``exp(d) R``). Two representations, both by ``jax.jacfwd``:

* :class:`StiffBlocks` (tree and null-space solvers): a joint's torque depends on its two bodies
  only, so K and D are 3x3 blocks on the body tree -- the diagonal and the body/parent couplings.
  The sparsity is exact, not an approximation. Two ways to the blocks (:class:`Jacobians`):
  ``CLOSED_FORM`` (default) differentiates the affine torque law of
  :class:`~neuromotor.physics.control.JointAffine` by hand (:func:`joint_blocks`,
  :func:`gyro_blocks`); ``JACFWD`` takes ``jax.jacfwd`` of the per-joint quaternion form along
  its 6 rotation tangents, vmapped over joints. Tests hold the two equal to round-off.
* :class:`DenseStiffness` (dense solver, the reference path): one ``jacfwd`` of the whole force
  vector (rotation-matrix form of the torque) over all bodies.
"""

from __future__ import annotations

import enum

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from neuromotor.model.skeleton import Model
from neuromotor.model.topology import Topology
from neuromotor.physics import static
from neuromotor.physics.control import (
    ControllerInputs,
    Gains,
    affine_torque,
    body_torques,
    joint_affine,
    joint_torque_q,
    joint_torques,
)
from neuromotor.physics.system import State, embed_angular, gyroscopic_forces, world_inertia
from neuromotor.rotations import (
    cross,
    matrix_to_quat,
    mm,
    mmt,
    mtv,
    mv,
    quat_exp,
    quat_mul,
    quat_to_matrix,
    right_jacobian_inv,
    skew,
)


class Jacobians(str, enum.Enum):
    """How the tree blocks of K and D are computed (``StepOptions.jacobians``)."""

    CLOSED_FORM = "closed_form"  # by hand from the affine torque law (fastest)
    JACFWD = "jacfwd"  # jax.jacfwd along each joint's 6 rotation tangents (the check)

    def __str__(self) -> str:
        return self.value


def muscle_and_gyro(model: Model, gains: Gains, inputs: ControllerInputs, rot, omega) -> Float[Array, " 6B"]:
    """Stiff generalized forces: muscle torques (feedforward + feedback, Eq. 4 and Section 5.2)
    and the gyroscopic term, in the rotation-matrix form."""
    torque = body_torques(model, joint_torques(model, gains, inputs, rot, omega))
    muscle = jnp.concatenate([jnp.zeros_like(torque), torque], -1).reshape(-1)
    return gyroscopic_forces(model, rot, omega) + muscle


def _as_forces(torque: Float[Array, "B 3"]) -> Float[Array, "B 6"]:
    return jnp.concatenate([jnp.zeros_like(torque), torque], -1)


class StiffBlocks(eqx.Module):
    """K = dk/dx and D = dk/dv of the stiff torques, angular 3x3 blocks on the body tree."""

    k: Float[Array, "B 3"]  # stiff torques per body (muscles and gyroscopic term)
    k_diag: Float[Array, "B 3 3"]
    k_up: Float[Array, "C 3 3"]  # d torque(child) / d rotation(parent)
    k_down: Float[Array, "C 3 3"]  # d torque(parent) / d rotation(child)
    d_diag: Float[Array, "B 3 3"]
    d_up: Float[Array, "C 3 3"]
    d_down: Float[Array, "C 3 3"]

    def forces(self) -> Float[Array, "B 6"]:
        return _as_forces(self.k)

    def g_blocks(self, h: float):
        """The blocks of ``G = h D + h^2 K`` (A = M - G in Eq. 2): diagonal, up, down."""
        return (
            h * self.d_diag + h * h * self.k_diag,
            h * self.d_up + h * h * self.k_up,
            h * self.d_down + h * h * self.k_down,
        )

    def damping_times(self, model: Model, v: Float[Array, "B 6"]) -> Float[Array, "B 6"]:
        """D v."""
        return _as_forces(tree_matvec(model.topology, self.d_diag, self.d_up, self.d_down, v[:, 3:]))


class DenseStiffness(eqx.Module):
    """The stiff forces, K and D as dense (6B,), (6B, 6B), (6B, 6B)."""

    k: Float[Array, " 6B"]
    kmat: Float[Array, "6B 6B"]
    dmat: Float[Array, "6B 6B"]

    def forces(self) -> Float[Array, "B 6"]:
        return self.k.reshape(-1, 6)

    def damping_times(self, model: Model, v: Float[Array, "B 6"]) -> Float[Array, "B 6"]:
        return (self.dmat @ v.reshape(-1)).reshape(-1, 6)


def tree_matvec(
    topo: Topology,
    diag: Float[Array, "B 3 3"],
    up: Float[Array, "C 3 3"],
    down: Float[Array, "C 3 3"],
    w: Float[Array, "B 3"],
) -> Float[Array, "B 3"]:
    """An angular block-tree matrix times w: diagonal, body <- parent and parent <- child blocks
    (both one-hot sums in one dot: no scatter under vmap, and a kernel fewer for one trajectory)."""
    c, p = topo.child, topo.parent
    # the one-hot matrices take w's dtype (keeps float32 runs in float32)
    return mv(diag, w) + static.dot_sum(
        (topo.sel_child.T, topo.sel_parent.T), (mv(up, w[p]), mv(down, w[c])), unrolled=False
    )


def stiff_jacobians(model: Model, gains: Gains, inputs: ControllerInputs, rot, omega) -> DenseStiffness:
    """k_stiff, K and D over all bodies by one dense ``jacfwd`` each (angular columns embedded
    in the 6B layout)."""
    n = model.n_bodies

    def f(delta, w):
        return muscle_and_gyro(model, gains, inputs, quat_to_matrix(quat_exp(delta)) @ rot, w)

    zero = jnp.zeros((n, 3), rot.dtype)
    embed = lambda m: embed_angular(m.reshape(6 * n, n, 3), (-1,)).reshape(6 * n, 6 * n)
    kmat = jax.jacfwd(f, argnums=0)(zero, omega).reshape(6 * n, 3 * n)
    dmat = jax.jacfwd(f, argnums=1)(zero, omega).reshape(6 * n, 3 * n)
    k = f(zero, omega)
    if inputs.drift is not None:  # an applied torque, as in stiff_blocks
        drift = body_torques(model, reference_drift(model, gains, inputs, matrix_to_quat(rot), omega))
        k = k + _as_forces(drift).reshape(-1)
    return DenseStiffness(k, embed(kmat), embed(dmat))


def _joint_jacobians(model: Model, gains: Gains, inputs: ControllerInputs, quat, omega):
    """Per joint: its torque on the child and ``[dT/d rot_p, dT/d rot_c, dT/d w_c]`` (C, 3, 9)."""
    topo = model.topology
    c, p = topo.child, topo.parent
    zero = jnp.zeros(6, quat.dtype)

    def one(x, qp, qc, wp, wc, inp):
        # x = [d_parent, d_child]: 6 tangents. The torque depends on w_child - w_parent, and
        # linearly (given the rotations), so its damping block comes in closed form as aux.
        torque, damping = joint_torque_q(
            gains, quat_mul(quat_exp(x[0:3]), qp), quat_mul(quat_exp(x[3:6]), qc), wp, wc, inp
        )
        return torque, (torque, damping)

    def val_jac(qp, qc, wp, wc, inp):
        k, (torque, damping) = jax.jacfwd(one, has_aux=True)(zero, qp, qc, wp, wc, inp)
        return torque, jnp.concatenate([k, damping], -1)

    return jax.vmap(val_jac)(quat[p], quat[c], omega[p], omega[c], inputs)


def _gyro_jacobians(model: Model, quat, omega):
    """The gyroscopic torque -w x (I w) of every body and its [d/d rot, d/d w] (B, 3, 6)."""

    def gyro(x, q, ib):
        r = quat_to_matrix(quat_mul(quat_exp(x[:3]), q))
        return -cross(x[3:], mv(r, mv(ib, mtv(r, x[3:]))))

    def gyro_val_jac(q, w, ib):
        x = jnp.concatenate([jnp.zeros(3, q.dtype), w])
        return gyro(x, q, ib), jax.jacfwd(gyro)(x, q, ib)

    return jax.vmap(gyro_val_jac)(quat, omega, model.inertia)


def joint_blocks(model: Model, gains: Gains, inputs: ControllerInputs, quat, omega):
    """Per joint, in closed form: its torque on the child and ``[dT/d rot_p, dT/d rot_c, dT/d w_c]``
    (C, 3, 9), rotations perturbed as ``exp(d) q``. With ``T = R_p y`` (:class:`JointAffine`),
    ``e`` the world rotation error and ``w = w_c - w_p``:

        dT/d rot_c = -Ks_w Jr^-1(e),   dT/d rot_p = -[T]x - dT/d rot_c - Kd_w [w]x,   dT/d w_c = -Kd_w,

    with ``Ks_w = R_p Ks R_p^T``, ``Kd_w = R_p Kd R_p^T``: the local error ``R_p^T e`` moves by
    ``R_p^T Jr^-1(e) (d_p - d_c)`` and ``R_p^T w`` by ``R_p^T [w]x d_p``, and T turns with R_p."""
    topo = model.topology
    c, p = topo.child, topo.parent
    aff = joint_affine(gains, inputs)
    torque, r_p, e = affine_torque(aff, quat[p], quat[c], omega[p], omega[c], inputs)
    w = omega[c] - omega[p]
    world = lambda k: mm(r_p, mmt(k, r_p))
    ks_w, kd_w = world(aff.ks), world(aff.kd)
    d_child = -mm(ks_w, right_jacobian_inv(e))
    d_parent = -skew(torque) - d_child - mm(kd_w, skew(w))
    return torque, jnp.concatenate([d_parent, d_child, -kd_w], -1)


def reference_drift(model: Model, gains: Gains, inputs: ControllerInputs, quat, omega, jac=None) -> Float[Array, "C 3"]:
    """Per joint, the torque (on the child) that moves the feedback's linearization with the
    reference over the step (``inputs.drift``).

    Eq. 2 predicts the stiff force at the step's end as ``k + K h v+ + D (v+ - v)``, as if the
    controller's target held still. The feedback acts on the error to a target that moves; its
    part of K and D must act on the deviation from the reference's own motion u:
    ``K_fb h (v+ - u+) + D_fb ((v+ - v) - (u+ - u))``. This returns ``-(K_fb h u+ + D_fb (u+ - u))``
    per joint, from the joint's blocks ``jac = [dT/d rot_p, dT/d rot_c, dT/d w_c]``
    (:func:`joint_blocks`) less the feedforward's share ``dT_ff/d rot_p = -[T_ff]x``. On the
    reference (the replay of the capture) it cancels the feedback's implicit terms exactly, so
    the discrete inverse dynamics (:mod:`neuromotor.physics.discrete`) does not depend on the
    gains."""
    topo = model.topology
    if jac is None:
        jac = joint_blocks(model, gains, inputs, quat, omega)[1]
    r_p = quat_to_matrix(quat[topo.parent])
    t_ff = mv(r_p, mv(inputs.local_axes, gains.feedforward * inputs.tau * inputs.active))
    d = inputs.drift
    assert d is not None  # reference_inputs sets it
    return -(
        mv(jac[..., 0:3] + skew(t_ff), d[..., 0:3]) + mv(jac[..., 3:6], d[..., 3:6]) + mv(jac[..., 6:9], d[..., 6:9])
    )


def gyro_blocks(model: Model, rot, omega):
    """The gyroscopic torque ``-w x L`` (L = I_w w) of every body and ``[d/d rot, d/d w]``
    (B, 3, 6) in closed form: ``[w]x [L]x - [w]x I_w [w]x`` and ``[L]x - [w]x I_w``."""
    iw = world_inertia(model, rot)
    ang = mv(iw, omega)
    wx, lx = skew(omega), skew(ang)
    wi = mm(wx, iw)
    return -cross(omega, ang), jnp.concatenate([mm(wx, lx) - mm(wi, wx), lx - wi], -1)


def stiff_blocks(
    model: Model,
    gains: Gains,
    inputs: ControllerInputs,
    state: State,
    jacobians: Jacobians = Jacobians.CLOSED_FORM,
    unrolled: bool = False,
) -> StiffBlocks:
    """The same K and D as :func:`stiff_jacobians`, as blocks on the body tree, plus the stiff
    torques; orientations enter as quaternions, perturbed as ``exp(d) q`` (the tangent of Eq. 2).
    ``unrolled``: the batched form of the sums over joint ends (:func:`static.dot_sums`)."""
    topo = model.topology
    if Jacobians(jacobians) is Jacobians.CLOSED_FORM:
        tq, jac = joint_blocks(model, gains, inputs, state.quat, state.omega)
        g, gj = gyro_blocks(model, state.rot, state.omega)
    else:
        tq, jac = _joint_jacobians(model, gains, inputs, state.quat, state.omega)
        g, gj = _gyro_jacobians(model, state.quat, state.omega)
    if inputs.drift is not None:  # an applied torque: K and D keep their blocks
        tq = tq + reference_drift(model, gains, inputs, state.quat, state.omega, jac)
    jac = jnp.concatenate([jac[..., :6], -jac[..., 6:9], jac[..., 6:9]], -1)
    # Child rows get +dT, parent rows -dT; diagonal blocks gather both ends of every joint.
    ends = (topo.sel_child.T, -topo.sel_parent.T)
    if unrolled:  # one sum per block: under vmap a concatenation of the blocks is a copy more
        # Fenced so that the blocks are computed once: unfenced, XLA:CPU fuses their arithmetic
        # into each kernel that reads them and repeats it there (docs/benchmarks.md, issue 17).
        tq, jac, g, gj = jax.lax.optimization_barrier((tq, jac, g, gj))
        k_sum = static.dot_sum(ends, (jac[:, :, 3:6], jac[:, :, 0:3]))
        d_sum = static.dot_sum(ends, (jac[:, :, 9:12], jac[:, :, 6:9]))
        tq_sum = body_torques(model, tq)
    else:  # K's, D's and the torques' in one dot
        at_child = jnp.concatenate([jac[:, :, 3:6], jac[:, :, 9:12], tq[:, :, None]], -1)
        at_parent = jnp.concatenate([jac[:, :, 0:3], jac[:, :, 6:9], tq[:, :, None]], -1)
        sums = static.dot_sum(ends, (at_child, at_parent), unrolled=False)  # (B, 3, 7)
        k_sum, d_sum, tq_sum = sums[..., 0:3], sums[..., 3:6], sums[..., 6]
    k_diag, d_diag, torque = gj[:, :, :3] + k_sum, gj[:, :, 3:] + d_sum, g + tq_sum
    return StiffBlocks(torque, k_diag, jac[:, :, 0:3], -jac[:, :, 3:6], d_diag, jac[:, :, 6:9], -jac[:, :, 9:12])


def explicit_forces(
    model: Model, gains: Gains, inputs: ControllerInputs, state: State, tree: bool
) -> StiffBlocks | DenseStiffness:
    """The stiff forces with K = D = 0 (``StepOptions.implicit = False``), in either representation."""
    k = muscle_and_gyro(model, gains, inputs, state.rot, state.omega)
    n, dtype = model.n_bodies, k.dtype
    if not tree:
        zero = jnp.zeros((6 * n, 6 * n), dtype)
        return DenseStiffness(k, zero, zero)
    diag, cpl = jnp.zeros((n, 3, 3), dtype), jnp.zeros((n - 1, 3, 3), dtype)
    return StiffBlocks(k.reshape(n, 6)[:, 3:], diag, cpl, cpl, diag, cpl, cpl)
