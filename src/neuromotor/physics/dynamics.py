"""Forward dynamics (Eq. 2): a linearly implicit step, post-stabilization, and the rollout.

One step from t to t + h (Anitescu & Potra's linearly implicit scheme, Section 4.1):

    [ M - h D - h^2 K   -J^T ] [ v+  ]   [ M v + h (k - D v) ]
    [       J             0  ] [ lam ] = [       b(t+h)      ]          (2)

with k = f_ext + H^T (tau + feedback) + perturbations, K = dk/dx over the position tangent space
(3 translations and 3 world-frame rotations per body) and D = dk/dv, both by ``jax.jacfwd``.
Only the stiff forces -- muscle torques and the gyroscopic term -- depend on the state, and
both are pure torques that depend on orientations and angular velocities only, so K and D live
in the angular-angular blocks. b carries the driven root's (and driven joints') velocity.
Positions then move with v+ (quaternions by the exponential map) and are projected back onto
the constraint manifold (Cline & Pai 2003): ``(J M^-1 J^T) mu = -C(x)``, ``x <- x + M^-1 J^T mu``,
a fixed number of Newton iterations so the step stays differentiable in both modes
(``SimConfig.stab_iters``, ``[sim] stabilization_steps`` in a config). Two by default: on the
default hit one iteration leaves up to 3.6e-8 m of violation (and runs about 20 % faster), two
leave 1e-14 m and give the same motion as three to 1e-13.

Three solvers give the same step (``SimConfig.solver``; tests check agreement to round-off):

* ``"nullspace"`` (default): K and D by ``jax.jacfwd`` of a per-joint torque function (a joint's
  muscle torque depends on its two bodies only) vmapped over joints, kept as 3x3 blocks on the
  body tree (:func:`stiff_blocks`); Eq. 2 solved by the null-space method -- v = S u over a
  basis of the ball joints' null space, one 54x54 LU, multipliers recovered from
  ``J^T lam = A v - r`` -- and each post-stabilization Newton step likewise with one Cholesky
  (:mod:`neuromotor.physics.nullspace`). Fewest XLA kernels per step, hence the fastest on a CPU.
* ``"tree"``: the same blocks; Eq. 2 and each Newton step by block elimination along the tree
  in linear time (:mod:`neuromotor.physics.treesolve`, Baraff 1996).
* ``"dense"``: one dense ``jacfwd`` over all bodies (:func:`stiff_jacobians`) and one dense
  LU of the (6B + nc) square matrix -- the reference path, and the assembly functions that
  other solvers (ball contact) build on.

Every path records the relative residual of the whole of Eq. 2 (both block rows, with J
applied row by row) and the constraint violation after post-stabilization at every step.

The rollout is one ``lax.scan``; divergence is recorded in the carry (first bad step and body)
and raised on the host by :func:`check_rollout`. Joint angles and rates are computed after the
scan for all states at once.
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor.physics.control import Gains, feedback_multipliers, joint_torque_magnitude, rate_feedback_gains
from neuromotor.physics.inverse import inverse_dynamics, sim_columns
from neuromotor.model.kinematics import Trajectory, body_kinematics, joint_angles_from_q
from neuromotor.physics.perturbation import ForcePulses, generalized_forces, no_pulses
from neuromotor.rotations import (
    AXIS,
    axis_rotation,
    matrix_to_quat,
    quat_log,
    quat_exp,
    quat_to_matrix,
    quat_turn,
    rotation_error,
    skew,
)
from neuromotor import vec3
from neuromotor.physics import nullspace, treesolve
from neuromotor.model.skeleton import Model
from neuromotor.physics.system import (
    State,
    dofs_to_per_joint,
    euler_axes_batched,
    joint_jacobian_blocks,
    joint_levers,
    per_joint_to_dofs,
    root_lever,
    solve3,
    topology,
    constraint_error,
    constraint_jacobian,
    dof_axes,
    gravity_forces,
    gyroscopic_forces,
    joint_angles,
    joint_rates,
    mass_matrix,
    world_inertia,
)


class SimulationDiverged(RuntimeError):
    """Raised when a rollout blows up; names the step, the time and the body."""

    def __init__(self, step: int, time: float, body: str, reason: str = "non-finite or runaway state"):
        self.step, self.time, self.body = step, time, body
        super().__init__(f"simulation diverged at step {step} (t = {time:.4f} s) in body {body!r}: {reason}")


class SimConfig(eqx.Module):
    """Static settings of a rollout."""

    h: float = eqx.field(static=True, default=1.0 / 120.0)
    n_steps: int = eqx.field(static=True, default=120)
    driven: tuple[int, ...] = eqx.field(static=True, default=())  # bodies driven along the mocap
    implicit: bool = eqx.field(static=True, default=True)  # False: K = D = 0 (explicit forces)
    # Newton steps of post-stabilization: 2 reach round-off (see the module docstring)
    stab_iters: int = eqx.field(static=True, default=2)
    max_speed: float = eqx.field(static=True, default=200.0)  # rad/s or m/s: beyond it, diverged
    free_root: bool = eqx.field(static=True, default=False)  # drop the 6 driven-root rows
    # "nullspace" (default): v = S u over the joint-space basis, one small LU (fastest);
    # "tree": linear-time block elimination along the body tree; both with K, D from per-joint
    # Jacobians. "dense": one dense jacfwd and one dense KKT solve (the reference path).
    solver: str = eqx.field(static=True, default="nullspace")


class Reference(eqx.Module):
    """Mocap targets on the simulation grid t_k = t0 + k h, k = 0..S."""

    time: Float[Array, " S1"]
    tau: Float[Array, "S1 n"]  # feedforward multipliers (Eq. 3)
    activation: Float[Array, "S1 n"]  # |T_j| of each DOF's joint (see control)
    theta: Float[Array, "S1 n"]  # desired Euler angles theta_d
    theta_dot: Float[Array, "S1 n"]
    root_origin: Float[Array, "S1 3"]
    root_rot: Float[Array, "S1 3 3"]
    root_vel: Float[Array, "S1 3"]
    root_omega: Float[Array, "S1 3"]
    rel_rot: Float[Array, "S1 B 3 3"]  # each body's desired rotation in its parent's frame
    rel_omega: Float[Array, "S1 B 3"]  # desired relative angular velocity, parent frame
    init: State
    # Derived from theta and rel_rot in make_reference, once for the whole grid, so that the
    # step does not rebuild them: they depend on the mocap only, never on the state.
    local_axes: Float[Array, "S1 C 3 3"]  # Euler axes h_i of each joint at theta_d, parent frame (columns)
    rel_quat: Float[Array, "S1 C 4"]  # quaternion of each joint's desired rotation (rel_rot of its child)

    def controller_inputs(self, k):
        """``(tau, activation, theta_d, rel_rot, rel_omega)`` at grid step k: what the muscle
        torques of :func:`muscle_and_gyro` and :func:`stiff_blocks` read from the mocap."""
        return self.tau[k], self.activation[k], self.theta[k], self.rel_rot[k], self.rel_omega[k]

    def stabilization_targets(self, k):
        """``(root_origin, root_rot, rel_rot)`` at grid step k + 1: what post-stabilization
        projects the positions of step k onto (the driven root and the driven joints)."""
        return self.root_origin[k + 1], self.root_rot[k + 1], self.rel_rot[k + 1]

    def joint_targets(self, k) -> tuple[Float[Array, "C 3 3"], Float[Array, "C 4"]]:
        """``(local_axes, rel_quat)`` at grid step k: the state-independent inputs of
        :func:`stiff_blocks`."""
        return self.local_axes[k], self.rel_quat[k]


def make_reference(model: Model, traj: Trajectory, t0: float, h: float, n_steps: int) -> Reference:
    """Sample the mocap targets on the simulation grid (inverse dynamics of Eq. 3 included)."""
    return _make_reference(model, traj, jnp.asarray(t0, jnp.float64), jnp.asarray(h, jnp.float64), n_steps)


# One compiled program rather than hundreds of eagerly dispatched small ops (each eager op is
# compiled on its own, which made preparing a run take longer than compiling the rollout).
@functools.partial(jax.jit, static_argnames=("n_steps",))
def _make_reference(model: Model, traj: Trajectory, t0, h, n_steps: int) -> Reference:
    times = t0 + h * jnp.arange(n_steps + 1)
    q = jax.vmap(traj.q)(times)
    qd = jax.vmap(traj.qd)(times)
    qdd = jax.vmap(traj.qdd)(times)
    kin = jax.vmap(lambda a, b, c: body_kinematics(model, a, b, c))(q, qd, qdd)
    pos, rot, vel, omega = kin[0], kin[1], kin[2], kin[3]
    cols = sim_columns(model)
    theta = jax.vmap(lambda a, t: joint_angles_from_q(model, a, traj.angle_reference(t)))(q, times)[:, cols]
    sol = inverse_dynamics(model, traj, times)
    # Euler rates from sum_i h_i thetadot_i = omega_child - omega_parent (exact, and much
    # cheaper to compile than a jvp through the Euler decomposition).
    theta_dot = jax.vmap(lambda ax, w: joint_rates(model, ax, w))(sol.axes, omega)
    activation = joint_torque_magnitude(model, sol.axes, sol.tau)
    par = jnp.array([max(p, 0) for p in model.body_parent], dtype=jnp.int32)
    rel = jnp.swapaxes(rot[:, par], -1, -2) @ rot
    rel_w = jnp.einsum("tbji,tbj->tbi", rot[:, par], omega - omega[:, par])
    init = State(pos[0], matrix_to_quat(rot[0]), vel[0], omega[0])
    root_origin = pos[:, 0] - jnp.einsum("tij,j->ti", rot[:, 0], model.com[0])
    child = topology(model)["child"]
    local_axes = jax.vmap(lambda th: joint_local_axes(model, th))(theta)
    rel_quat = matrix_to_quat(rel[:, child])
    return Reference(times, sol.tau, activation, theta, theta_dot, root_origin,
                     rot[:, 0], qd[:, 0:3], omega[:, 0], rel, rel_w, init, local_axes, rel_quat)


def _active_mask(model: Model, driven: tuple[int, ...], dtype) -> Float[Array, " n"]:
    return jnp.array([0.0 if b in driven else 1.0 for b in model.dof_body], dtype)


DAMPING = 0.02  # damped least squares at gimbal lock (singular value scale of the Euler axes)


def damped_solve(a: Float[Array, "... 3 3"], e: Float[Array, "... 3"], mu: float = DAMPING):
    """x = A^T (A A^T + mu^2 I)^-1 e: A^-1 e away from singularity, bounded at gimbal lock."""
    at = jnp.swapaxes(a, -1, -2)
    gram = a @ at + mu**2 * jnp.eye(3, dtype=a.dtype)
    return jnp.einsum("...ij,...j->...i", at, solve3(gram, e))


def _joint_errors(rot_p, rot_c, w_p, w_c, a, rel_d, rel_w_d):
    """Angle and rate errors of joints (any leading shape) resolved along their axes ``a``
    (columns h_i); see :func:`dof_errors`."""
    rel = jnp.swapaxes(rot_p, -1, -2) @ rot_c
    e_local = quat_log(matrix_to_quat(rel_d @ jnp.swapaxes(rel, -1, -2)))
    e_world = jnp.einsum("...ij,...j->...i", rot_p, e_local)
    w_err = jnp.einsum("...ij,...j->...i", rot_p, rel_w_d) - (w_c - w_p)
    return damped_solve(a, e_world), damped_solve(a, w_err)


def dof_errors(model: Model, rot, omega, axes, rel_d, rel_w_d):
    """Per-DOF angle and rate errors (desired minus simulated) from rotation errors.

    The joint's rotation error (rotation vector taking the simulated relative orientation to
    the desired one, world frame) and relative angular-velocity error are resolved along the
    Euler axes h_i. To first order this is exactly theta_d - theta and thetadot_d - thetadot of
    the BVH decomposition, it is always the shortest rotation (no wrapping issue), and it stays
    bounded at gimbal lock, where Euler differences are ill-defined.
    """
    topo = topology(model)
    c, p = topo["child"], topo["parent"]
    a = jnp.swapaxes(dofs_to_per_joint(model, axes), -1, -2)
    d_theta, d_rate = _joint_errors(rot[p], rot[c], omega[p], omega[c], a, rel_d[c], rel_w_d[c])
    return per_joint_to_dofs(model, d_theta), per_joint_to_dofs(model, d_rate)


def _joint_inputs(model: Model, gains: Gains, ref_k, active):
    """Per-joint slices (leading axis C) of the reference and of the per-DOF gains."""
    tau, act, theta_d, rel_d, rel_w_d = ref_k
    c = topology(model)["child"]
    per = lambda x: dofs_to_per_joint(model, x)
    return (per(tau), per(act), per(theta_d), rel_d[c], rel_w_d[c], per(gains.scale),
            per(gains.floor), per(gains.reference_torque), per(active))


def _joint_torque(order: str, gains: Gains, rot_p, rot_c, w_p, w_c, inputs):
    """World muscle torque ``T_j = sum_i h_i (psi_i + gamma_i)`` of one joint on its child
    (Eq. 4 and Section 5.2; the parent gets -T_j). Depends on the joint's two bodies only."""
    tau, act, theta_d, rel_d, rel_w_d, scale, floor, ref_torque, active = inputs
    a = jnp.swapaxes(euler_axes_batched(rot_p, theta_d, order), -1, -2)  # columns h_i
    d_theta, d_rate = _joint_errors(rot_p, rot_c, w_p, w_c, a, rel_d, rel_w_d)
    g = dataclasses.replace(gains, scale=scale, floor=floor, reference_torque=ref_torque)
    mult = feedback_multipliers(g, tau, act, d_theta, d_rate, active)
    return jnp.einsum("...ij,...j->...i", a, mult)


def _joint_torques(model: Model, gains: Gains, ref_k, active, rot, omega) -> Float[Array, "C 3"]:
    topo = topology(model)
    c, p = topo["child"], topo["parent"]
    inputs = _joint_inputs(model, gains, ref_k, active)
    out = jnp.zeros((model.n_bodies - 1, 3), rot.dtype)
    for order, bodies, rows in topo["groups"]:
        sub = jax.tree_util.tree_map(lambda x: x[rows], inputs)
        part = _joint_torque(order, gains, rot[p[rows]], rot[c[rows]], omega[p[rows]], omega[c[rows]], sub)
        out = part if len(rows) == model.n_bodies - 1 else out.at[rows].set(part)
    return out


def _body_torques(model: Model, joint_torque: Float[Array, "C 3"]) -> Float[Array, "B 3"]:
    """+T_j on each joint's child, -T_j on its parent (static one-hot selectors, no scatter)."""
    topo = topology(model)
    sel = np.eye(model.n_bodies)[topo["child"]] - np.eye(model.n_bodies)[topo["parent"]]
    return jnp.einsum("cb,ci->bi", sel, joint_torque)


def muscle_and_gyro(model: Model, gains: Gains, ref_k, active, rot, omega):
    """Stiff generalized forces: muscle torques (feedforward + feedback) and gyroscopic term.

    The Euler axes h_i come from the desired joint angles placed in the simulated parent's
    frame: exactly Eq. 4 on the mocap, and the feedforward sum h_i tau_i stays well-conditioned
    near gimbal lock where the individual tau_i are large and of opposite signs.
    """
    torque = _body_torques(model, _joint_torques(model, gains, ref_k, active, rot, omega))
    muscle = jnp.concatenate([jnp.zeros_like(torque), torque], -1).reshape(-1)
    return gyroscopic_forces(model, rot, omega) + muscle


def _rotate(delta: Float[Array, "B 3"], rot: Float[Array, "B 3 3"]) -> Float[Array, "B 3 3"]:
    return quat_to_matrix(quat_exp(delta)) @ rot


def stiff_jacobians(model, gains, ref_k, active, rot, omega):
    """k_stiff, K and D restricted to angular coordinates: (6B,), (6B, 3B), (6B, 3B)."""
    n = model.n_bodies

    def f(delta, w):
        return muscle_and_gyro(model, gains, ref_k, active, _rotate(delta, rot), w)

    zero = jnp.zeros((n, 3), rot.dtype)
    k = f(zero, omega)
    kmat = jax.jacfwd(f, argnums=0)(zero, omega).reshape(6 * n, 3 * n)
    dmat = jax.jacfwd(f, argnums=1)(zero, omega).reshape(6 * n, 3 * n)
    return k, kmat, dmat


class StiffBlocks(eqx.Module):
    """K = dk/dx and D = dk/dv of the stiff torques, angular 3x3 blocks on the body tree."""

    k: Float[Array, "B 3"]  # stiff torques per body (muscles and gyroscopic term)
    k_diag: Float[Array, "B 3 3"]
    k_up: Float[Array, "C 3 3"]  # d torque(child) / d rotation(parent)
    k_down: Float[Array, "C 3 3"]  # d torque(parent) / d rotation(child)
    d_diag: Float[Array, "B 3 3"]
    d_up: Float[Array, "C 3 3"]
    d_down: Float[Array, "C 3 3"]


def _local_axes(theta: Float[Array, "C 3"], order: str) -> Float[Array, "C 3 3"]:
    """Euler axes of joints in their parent's frame, as columns: ``h_i = R_p L[:, i]`` (Eq. 4).
    They depend on the desired angles only, so they stay outside the state Jacobians."""
    a0, a1, a2 = (AXIS[ax] for ax in order)
    eye = jnp.eye(3, dtype=theta.dtype)
    r1 = axis_rotation(a0, theta[..., 0])
    r2 = vec3.mm(r1, axis_rotation(a1, theta[..., 1]))
    return jnp.stack([jnp.broadcast_to(eye[a0], theta.shape), r1[..., :, a1], r2[..., :, a2]], -1)


def joint_local_axes(model: Model, theta_d: Float[Array, " n"]) -> Float[Array, "C 3 3"]:
    """:func:`_local_axes` of every joint, each group of joints with its own rotation order."""
    per = dofs_to_per_joint(model, theta_d)
    out = jnp.zeros((model.n_bodies - 1, 3, 3), theta_d.dtype)
    for order, _, rows in topology(model)["groups"]:
        if len(rows) == model.n_bodies - 1:
            return _local_axes(per, order)
        out = out.at[rows].set(_local_axes(per[rows], order))
    return out


def _joint_torque_q(gains: Gains, q_p, q_c, w_p, w_c, inputs):
    """:func:`_joint_torque` on quaternions, written with :mod:`vec3` (fusion-friendly).
    Returns the torque and ``d torque / d w_c`` (= -d torque / d w_p), the joint's damping block.

    The joint's rotation error is ``log(q_p q_d q_c^-1)``, the world-frame rotation vector of
    ``R_p R_d R_c^T`` -- the same vector as ``R_p log(R_d R_rel^T)`` of :func:`_joint_errors`.
    The rate error ``w_err = R_p w_d - (w_c - w_p)`` enters the torque ``a m`` linearly, through
    ``d_rate = P w_err`` with ``P = a^T (a a^T + mu^2 1)^-1`` and the slope ``c`` of
    :func:`rate_feedback_gains`, so the damping block is ``-a diag(c) P`` in closed form."""
    local, q_rel_d, rel_w_d, tau, act, scale, floor, ref_torque, active = inputs
    r_p = vec3.qmatrix(q_p)
    a = r_p @ local  # columns h_i (a dot: materialized once, used by every later line)
    # The barrier materializes the error quaternion and its tangents: fused into its consumers,
    # XLA recomputed the whole product chain for every entry of the Jacobian (1.4x in batch).
    q_err = jax.lax.optimization_barrier(vec3.qmul(vec3.qmul(q_p, q_rel_d), vec3.qconj(q_c)))
    e_world = vec3.qlog(q_err)
    w_err = vec3.mv(r_p, rel_w_d) - (w_c - w_p)
    gram = vec3.mmt(a, a) + DAMPING**2 * jnp.eye(3, dtype=a.dtype)
    proj = jnp.swapaxes(a, -1, -2) @ vec3.inv(gram)  # P (a dot, materialized as above)
    d = proj @ jnp.stack([e_world, w_err], -1)  # both right-hand sides at once
    d_theta, d_rate = d[..., 0], d[..., 1]
    g = dataclasses.replace(gains, scale=scale, floor=floor, reference_torque=ref_torque)
    damping = -(a * rate_feedback_gains(g, act, active)[..., None, :]) @ proj
    # A dot, not vec3.mv: it materializes a and the multipliers, which XLA would otherwise
    # recompute inside every entry of the (nested) Jacobian.
    return jnp.einsum("...ij,...j->...i", a, feedback_multipliers(g, tau, act, d_theta, d_rate, active)), damping


def stiff_blocks(model: Model, gains: Gains, ref_k, active, rot, omega, quat=None, targets=None) -> StiffBlocks:
    """The same K and D as :func:`stiff_jacobians`: K by ``jax.jacfwd`` of a per-joint function
    along its 6 rotation tangents (both bodies), vmapped over joints, D in closed form (see
    :func:`_joint_torque_q`), plus the gyroscopic term per body. The tree sparsity is exact, not an approximation: joint j's torque
    depends on its two bodies only. Orientations enter as quaternions (``quat``, else from
    ``rot``); rotations are perturbed as ``exp(d) q`` in the world frame, the tangent of Eq. 2.
    ``targets`` = ``ref.joint_targets(k)`` (the Euler axes and desired rotations, precomputed
    for the whole grid); without it they are built here from ``ref_k``."""
    topo = topology(model)
    c, p = topo["child"], topo["parent"]
    if quat is None:
        quat = matrix_to_quat(rot)
    tau, act, theta_d, rel_d, rel_w_d = ref_k
    per = lambda x: dofs_to_per_joint(model, x)
    local_all, q_rel_d = targets if targets is not None else (joint_local_axes(model, theta_d), matrix_to_quat(rel_d[c]))
    nj = model.n_bodies - 1
    tq = jnp.zeros((nj, 3), quat.dtype)
    jac = jnp.zeros((nj, 3, 9), quat.dtype)
    zero = jnp.zeros(6, quat.dtype)

    def one(x, qp, qc, wp, wc, inp):
        # x = [d_parent, d_child]: 6 tangents. The torque depends on w_child - w_parent, and
        # linearly (given the rotations), so its damping block comes in closed form as aux.
        torque, damping = _joint_torque_q(gains, vec3.qmul(vec3.qexp(x[0:3]), qp),
                                          vec3.qmul(vec3.qexp(x[3:6]), qc), wp, wc, inp)
        return torque, (torque, damping)

    def val_jac(qp, qc, wp, wc, inp):
        k, (torque, damping) = jax.jacfwd(one, has_aux=True)(zero, qp, qc, wp, wc, inp)
        return torque, jnp.concatenate([k, damping], -1)

    for order, bodies, rows in topo["groups"]:
        full = len(rows) == nj
        take = (lambda x: x) if full else (lambda x: x[rows])  # no gather for a single order
        inputs = (take(local_all), take(q_rel_d), take(rel_w_d[c]), take(per(tau)),
                  take(per(act)), take(per(gains.scale)), take(per(gains.floor)),
                  take(per(gains.reference_torque)), take(per(active)))
        t_g, j_g = jax.vmap(val_jac)(quat[p[rows]], quat[c[rows]], omega[p[rows]], omega[c[rows]], inputs)
        tq = t_g if full else tq.at[rows].set(t_g)
        jac = j_g if full else jac.at[rows].set(j_g)
    jac = jnp.concatenate([jac[..., :6], -jac[..., 6:9], jac[..., 6:9]], -1)

    def gyro(x, q, ib):
        r = vec3.qmatrix(vec3.qmul(vec3.qexp(x[:3]), q))
        return -vec3.cross(x[3:], vec3.mv(r, vec3.mv(ib, vec3.mtv(r, x[3:]))))

    def gyro_val_jac(q, w, ib):
        x = jnp.concatenate([jnp.zeros(3, q.dtype), w])
        return gyro(x, q, ib), jax.jacfwd(gyro)(x, q, ib)

    g, gj = jax.vmap(gyro_val_jac)(quat, omega, model.inertia)
    sel_c = np.eye(model.n_bodies)[c]
    sel_p = np.eye(model.n_bodies)[p]
    # Child rows get +dT, parent rows -dT; diagonal blocks gather both ends of every joint.
    diag = lambda dp, dc: jnp.einsum("cb,cij->bij", sel_c, dc) - jnp.einsum("cb,cij->bij", sel_p, dp)
    k_diag = gj[:, :, :3] + diag(jac[:, :, 0:3], jac[:, :, 3:6])
    d_diag = gj[:, :, 3:] + diag(jac[:, :, 6:9], jac[:, :, 9:12])
    torque = g + _body_torques(model, tq)
    return StiffBlocks(torque, k_diag, jac[:, :, 0:3], -jac[:, :, 3:6], d_diag, jac[:, :, 6:9], -jac[:, :, 9:12])


def _angular_embed(mat: Float[Array, "N 3B"], n: int) -> Float[Array, "N 6B"]:
    """Place columns over angular coordinates into the full 6B layout."""
    out = jnp.zeros((mat.shape[0], n, 6), mat.dtype)
    out = out.at[:, :, 3:].set(mat.reshape(mat.shape[0], n, 3))
    return out.reshape(mat.shape[0], 6 * n)


def full_constraints(model: Model, driven: tuple[int, ...], rot, free_root: bool = False) -> Float[Array, "nc 6B"]:
    """J with extra rows for driven joints (relative angular velocity of child and parent);
    without the 6 root rows when the root floats free."""
    jac = constraint_jacobian(model, rot)[6 if free_root else 0:]
    if not driven:
        return jac
    n = model.n_bodies
    rows = jnp.zeros((3 * len(driven), 6 * n), rot.dtype)
    eye = jnp.eye(3, dtype=rot.dtype)
    for i, b in enumerate(driven):
        p = model.body_parent[b]
        rows = rows.at[3 * i:3 * i + 3, 6 * b + 3:6 * b + 6].set(eye)
        rows = rows.at[3 * i:3 * i + 3, 6 * p + 3:6 * p + 6].set(-eye)
    return jnp.concatenate([jac, rows], 0)


def full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root=False):
    err = constraint_error(model, pos, rot, root_origin, root_rot)[6 if free_root else 0:]
    if not driven:
        return err
    drv = jnp.array(driven)
    par = jnp.array([model.body_parent[b] for b in driven])
    target = rot[par] @ rel_rot[drv]
    extra = rotation_error(rot[drv], target).reshape(-1)
    return jnp.concatenate([err, extra])


def constraint_velocity(model, driven, rot, root_vel, root_omega, rel_omega, free_root=False):
    """b of Eq. 2: driven root origin velocity and angular velocity, driven joints' rates."""
    b = jnp.zeros(model.n_constraints, rot.dtype)
    b = b.at[0:3].set(root_vel).at[3:6].set(root_omega)[6 if free_root else 0:]
    if not driven:
        return b
    par = jnp.array([model.body_parent[bb] for bb in driven])
    extra = jnp.einsum("dij,dj->di", rot[par], rel_omega[jnp.array(driven)]).reshape(-1)
    return jnp.concatenate([b, extra])


def inverse_mass_blocks(model: Model, rot):
    inv_i = rot @ jnp.linalg.inv(model.inertia) @ jnp.swapaxes(rot, -1, -2)
    return 1.0 / model.mass, inv_i


def apply_inverse_mass(model, rot, g: Float[Array, "... 6B"]):
    inv_m, inv_i = inverse_mass_blocks(model, rot)
    g = g.reshape(g.shape[:-1] + (model.n_bodies, 6))
    lin = g[..., :3] * inv_m[:, None]
    ang = jnp.einsum("bij,...bj->...bi", inv_i, g[..., 3:])
    return jnp.concatenate([lin, ang], -1).reshape(g.shape[:-2] + (6 * model.n_bodies,))


def post_stabilize(model: Model, driven, pos, quat, targets, iters: int, free_root: bool = False):
    """Project positions onto the constraint manifold (Cline & Pai 2003), fixed Newton steps."""
    root_origin, root_rot, rel_rot = targets

    def body(carry, _):
        pos, quat = carry
        rot = quat_to_matrix(quat)
        c = full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root)
        jac = full_constraints(model, driven, rot, free_root)
        minv_jt = apply_inverse_mass(model, rot, jac).T  # (6B, nc)
        mu = jnp.linalg.solve(jac @ minv_jt, -c)
        delta = (minv_jt @ mu).reshape(model.n_bodies, 6)
        pos = pos + delta[:, :3]
        quat = quat_turn(quat, delta[:, 3:])
        return (pos, quat), None

    (pos, quat), _ = jax.lax.scan(body, (pos, quat), None, length=iters)
    rot = quat_to_matrix(quat)
    c = full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root)
    return pos, quat, c


# ---------------------------------------------------------------- tree (fast) path


def _tree_constraints(model: Model, driven: tuple[int, ...], rot, free_root: bool):
    """Rows of :func:`full_constraints` grouped by owner: the root's rows and, per non-root
    body, its ball joint's 3 rows followed (when any joint is driven) by 3 driven-joint rows
    or 3 padding rows."""
    dtype = rot.dtype
    eye = jnp.eye(3, dtype=dtype)
    zero3 = jnp.zeros((3, 3), dtype)
    r0 = root_lever(model, rot)
    j_root = jnp.block([[eye, -skew(r0)], [zero3, eye]])[: 0 if free_root else 6]
    j_par, j_own = joint_jacobian_blocks(model, rot)
    nj = model.n_bodies - 1
    pad = jnp.zeros((nj, 3), dtype)
    if driven:
        is_drv = np.zeros((nj, 1, 1))
        is_drv[np.array(driven) - 1] = 1.0
        ang = jnp.asarray(is_drv) * jnp.concatenate([jnp.zeros((3, 3), dtype), eye], -1)
        j_own = jnp.concatenate([j_own, ang], 1)
        j_par = jnp.concatenate([j_par, -ang], 1)
        pad = jnp.concatenate([pad, jnp.asarray(1.0 - is_drv[:, :, 0]) * jnp.ones((nj, 3), dtype)], 1)
    return j_root, j_own, j_par, pad


def _split_rows(model: Model, driven, values: Float[Array, " nc"], free_root: bool):
    """A vector over the rows of :func:`full_constraints` in tree layout (root, (C, m))."""
    m0 = 0 if free_root else 6
    nj = model.n_bodies - 1
    root, joints = values[:m0], values[m0:m0 + 3 * nj].reshape(nj, 3)
    if driven:
        extra = jnp.zeros((nj, 3), values.dtype).at[np.array(driven) - 1].set(
            values[m0 + 3 * nj:].reshape(-1, 3))
        joints = jnp.concatenate([joints, extra], 1)
    return root, joints


def _join_rows(driven, root, joints):
    """Inverse of :func:`_split_rows` (padding rows dropped)."""
    out = [root, joints[:, :3].reshape(-1)]
    if driven:
        out.append(joints[np.array(driven) - 1, 3:].reshape(-1))
    return jnp.concatenate(out)


def _embed_angular(blocks: Float[Array, "... 3 3"]) -> Float[Array, "... 6 6"]:
    z = jnp.zeros(blocks.shape[:-2] + (3, 3), blocks.dtype)
    return jnp.concatenate([jnp.concatenate([z, z], -1), jnp.concatenate([z, blocks], -1)], -2)


def _mass_blocks(model: Model, rot) -> Float[Array, "B 6 6"]:
    lin = model.mass[:, None, None] * jnp.eye(3, dtype=rot.dtype)
    z = jnp.zeros_like(lin)
    ang = world_inertia(model, rot)
    return jnp.concatenate([jnp.concatenate([lin, z], -1), jnp.concatenate([z, ang], -1)], -2)


def post_stabilize_tree(model: Model, driven, pos, quat, targets, iters: int, free_root: bool = False):
    """:func:`post_stabilize` with each Newton step's system ``[M -J^T; J 0][dx; mu] = [0; -C]``
    solved by tree elimination (the same projection: dx = M^-1 J^T mu, J dx = -C)."""
    root_origin, root_rot, rel_rot = targets

    def body(carry, _):
        pos, quat = carry
        rot = quat_to_matrix(quat)
        c = full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root)
        j_root, j_own, j_par, pad = _tree_constraints(model, driven, rot, free_root)
        zero = jnp.zeros((model.n_bodies - 1, 6, 6), rot.dtype)
        sys = treesolve.TreeKKT(_mass_blocks(model, rot), zero, zero, j_root, j_own, j_par, pad)
        c_root, c_joint = _split_rows(model, driven, c, free_root)
        # Full Newton (refactored at every iterate), exactly as the dense projection.
        delta, _, _ = treesolve.solve(sys, model.body_parent, jnp.zeros((model.n_bodies, 6), rot.dtype),
                                      -c_root, -c_joint)
        pos = pos + delta[:, :3]
        quat = quat_turn(quat, delta[:, 3:])
        return (pos, quat), None

    (pos, quat), _ = jax.lax.scan(body, (pos, quat), None, length=iters)
    rot = quat_to_matrix(quat)
    c = full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root)
    return pos, quat, c


def _tree_matvec(model: Model, diag: Float[Array, "B 3 3"], up: Float[Array, "C 3 3"],
                 down: Float[Array, "C 3 3"], w: Float[Array, "B 3"]) -> Float[Array, "B 3"]:
    """An angular block-tree matrix times w: diagonal, body <- parent and parent <- child blocks
    (one-hot sums, no scatter under vmap)."""
    topo = topology(model)
    c, p = topo["child"], topo["parent"]
    sel_c, sel_p = np.eye(model.n_bodies)[c], np.eye(model.n_bodies)[p]
    return (jnp.einsum("bij,bj->bi", diag, w) + jnp.einsum("cb,cij,cj->bi", sel_c, up, w[p])
            + jnp.einsum("cb,cij,cj->bi", sel_p, down, w[c]))


def _step_tree(model: Model, gains: Gains, pulses: ForcePulses, cfg: SimConfig, ref: Reference, k, state: State):
    """Eq. 2 with the block structure of the tree (see :mod:`neuromotor.physics.treesolve`)."""
    h = cfg.h
    n = model.n_bodies
    rot = state.rot
    dtype = rot.dtype
    active = _active_mask(model, cfg.driven, dtype)
    ref_k = ref.controller_inputs(k)
    mass = _mass_blocks(model, rot)
    if cfg.implicit:
        sb = stiff_blocks(model, gains, ref_k, active, rot, state.omega, targets=ref.joint_targets(k))
        torque = sb.k
        a_diag = mass - _embed_angular(h * sb.d_diag + h * h * sb.k_diag)
        a_up = -_embed_angular(h * sb.d_up + h * h * sb.k_up)
        a_down = -_embed_angular(h * sb.d_down + h * h * sb.k_down)
        dv = _tree_matvec(model, sb.d_diag, sb.d_up, sb.d_down, state.omega)
    else:
        k_stiff = muscle_and_gyro(model, gains, ref_k, active, rot, state.omega).reshape(n, 6)
        torque = k_stiff[:, 3:]
        a_diag = mass
        a_up = a_down = jnp.zeros((n - 1, 6, 6), dtype)
        dv = jnp.zeros((n, 3), dtype)
    f_pert, per_body, points = generalized_forces(pulses, ref.time[k], n, state.pos, rot, model.com)
    kvec = (gravity_forces(model) + f_pert).reshape(n, 6)
    kvec = kvec.at[:, 3:].add(torque)
    mv = jnp.einsum("bij,bj->bi", mass, state.v.reshape(n, 6))
    r = mv + h * kvec.at[:, 3:].add(-dv)
    j_root, j_own, j_par, pad = _tree_constraints(model, cfg.driven, rot, cfg.free_root)
    sys = treesolve.TreeKKT(a_diag, a_up, a_down, j_root, j_own, j_par, pad)
    b = constraint_velocity(model, cfg.driven, rot, ref.root_vel[k + 1], ref.root_omega[k + 1],
                            ref.rel_omega[k + 1], cfg.free_root)
    s_root, s_joint = _split_rows(model, cfg.driven, b, cfg.free_root)
    v_new, lam_root, lam = treesolve.solve(sys, model.body_parent, r, s_root, s_joint)
    top, bot_root, bot = treesolve.matvec(sys, model.body_parent, v_new, lam_root, lam)
    res = jnp.concatenate([(top - r).reshape(-1), bot_root - s_root, (bot - s_joint).reshape(-1)])
    rhs_norm = jnp.sqrt(jnp.sum(r**2) + jnp.sum(s_root**2) + jnp.sum(s_joint**2))
    residual = jnp.linalg.norm(res) / jnp.maximum(rhs_norm, 1e-300)
    return _advance(model, cfg, ref, k, state, v_new, post_stabilize_tree,
                    (residual, per_body, points, _join_rows(cfg.driven, lam_root, lam)))


def _advance(model: Model, cfg: SimConfig, ref: Reference, k, state: State, v_new: Float[Array, "B 6"],
             post_stabilize_fn, diagnostics):
    """Positions move with v+ (quaternions by the exponential map), then post-stabilization;
    ``diagnostics = (residual, per-body force, points, lam * h)`` become the step's info."""
    residual, per_body, points, lam_h = diagnostics
    vel, omega = v_new[:, :3], v_new[:, 3:]
    pos, quat = nullspace.retract(state.pos, state.quat, cfg.h * v_new)
    pos, quat, cerr = post_stabilize_fn(model, cfg.driven, pos, quat, ref.stabilization_targets(k), cfg.stab_iters,
                                        cfg.free_root)
    violation = jnp.max(jnp.abs(cerr)) if cerr.size else jnp.zeros((), pos.dtype)
    return State(pos, quat, vel, omega), StepInfo(residual, violation, per_body, points, lam_h / cfg.h)


def post_stabilize_nullspace(model: Model, driven, pos, quat, targets, iters: int, free_root: bool = False):
    """:func:`post_stabilize` with each Newton step solved by the null-space method
    (:func:`nullspace.projection_step`): the same projection, ``dx = M^-1 J^T mu``, ``J dx = -C``.
    Full Newton (refactored at every iterate), exactly as the dense projection: reusing the first
    factor saved 6 % of a step but moved the motion by 3e-8 rad, off the reference path."""
    root_origin, root_rot, rel_rot = targets
    st = nullspace.structure(model.body_parent, driven, free_root)
    for _ in range(iters):  # a fixed, small number of Newton steps (unrolled)
        rot = quat_to_matrix(quat)
        c = full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root)
        geo = nullspace.geometry(st, *joint_levers(model, rot), root_lever(model, rot))
        dx = nullspace.projection_step(st, geo, model.mass, world_inertia(model, rot), c)
        pos, quat = nullspace.retract(pos, quat, dx)
    rot = quat_to_matrix(quat)
    c = full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root)
    return pos, quat, c


def _step_nullspace(model: Model, gains: Gains, pulses: ForcePulses, cfg: SimConfig, ref: Reference, k,
                    state: State):
    """Eq. 2 by the null-space method (see :mod:`neuromotor.physics.nullspace`), K and D as tree blocks."""
    h = cfg.h
    n = model.n_bodies
    rot = state.rot
    dtype = rot.dtype
    active = _active_mask(model, cfg.driven, dtype)
    ref_k = ref.controller_inputs(k)
    if cfg.implicit:
        sb = stiff_blocks(model, gains, ref_k, active, rot, state.omega, state.quat, ref.joint_targets(k))
        torque = sb.k
        g_diag, g_up, g_down = (h * sb.d_diag + h * h * sb.k_diag, h * sb.d_up + h * h * sb.k_up,
                                h * sb.d_down + h * h * sb.k_down)
        dv = _tree_matvec(model, sb.d_diag, sb.d_up, sb.d_down, state.omega)
    else:
        torque = muscle_and_gyro(model, gains, ref_k, active, rot, state.omega).reshape(n, 6)[:, 3:]
        g_diag = jnp.zeros((n, 3, 3), dtype)
        g_up = g_down = jnp.zeros((n - 1, 3, 3), dtype)
        dv = jnp.zeros((n, 3), dtype)
    f_pert, per_body, points = generalized_forces(pulses, ref.time[k], n, state.pos, rot, model.com)
    kvec = (gravity_forces(model) + f_pert).reshape(n, 6)
    kvec = kvec.at[:, 3:].add(torque)
    inertia = world_inertia(model, rot)
    mass_v = lambda x: jnp.concatenate([model.mass[:, None] * x[:, :3], jnp.einsum("bij,bj->bi", inertia, x[:, 3:])], -1)
    r = mass_v(state.v.reshape(n, 6)) + h * kvec.at[:, 3:].add(-dv)
    b = constraint_velocity(model, cfg.driven, rot, ref.root_vel[k + 1], ref.root_omega[k + 1],
                            ref.rel_omega[k + 1], cfg.free_root)
    st = nullspace.structure(model.body_parent, cfg.driven, cfg.free_root)
    r_par, r_chi = joint_levers(model, rot)
    geo = nullspace.geometry(st, r_par, r_chi, root_lever(model, rot))
    v_new = nullspace.solve_kkt(st, geo, model.mass, inertia, g_diag, g_up, g_down, r, b)
    # A v+ - r = J^T lam gives the multipliers; the residual of the whole of Eq. 2 checks the solve.
    av = mass_v(v_new).at[:, 3:].add(-_tree_matvec(model, g_diag, g_up, g_down, v_new[:, 3:]))
    lam = nullspace.multipliers(st, geo, av - r)
    res = jnp.concatenate(nullspace.kkt_residual(st, geo, r_par, r_chi, av - r, v_new, lam, b,
                                                 topology(model)["parent"]))
    rhs_norm = jnp.sqrt(jnp.sum(r**2) + jnp.sum(b**2))
    residual = jnp.linalg.norm(res) / jnp.maximum(rhs_norm, 1e-300)
    return _advance(model, cfg, ref, k, state, v_new, post_stabilize_nullspace, (residual, per_body, points, lam))


class StepInfo(eqx.Module):
    residual: Float[Array, ""]  # relative residual of the KKT solve of Eq. 2
    violation: Float[Array, ""]  # max |C(x)| after post-stabilization (m or rad)
    force: Float[Array, "B 3"]  # perturbation force per body (world, N)
    points: Float[Array, "P 3"]  # world application points of the pulses
    lam: Float[Array, " nc"]


def step(model: Model, gains: Gains, pulses: ForcePulses, cfg: SimConfig, ref: Reference, k, state: State):
    """One linearly implicit step from t_k to t_k + h (Eq. 2 plus post-stabilization).

    ``cfg.solver`` picks the null-space method (default), the tree elimination or the dense
    reference solve; all three solve the same equations and agree to round-off.
    """
    if cfg.solver == "nullspace":
        return _step_nullspace(model, gains, pulses, cfg, ref, k, state)
    if cfg.solver == "tree":
        return _step_tree(model, gains, pulses, cfg, ref, k, state)
    if cfg.solver != "dense":
        raise ValueError(f"SimConfig.solver must be 'nullspace', 'tree' or 'dense', got {cfg.solver!r}")
    h = cfg.h
    n = model.n_bodies
    rot = state.rot
    active = _active_mask(model, cfg.driven, rot.dtype)
    ref_k = ref.controller_inputs(k)
    t = ref.time[k]
    if cfg.implicit:
        k_stiff, kmat, dmat = stiff_jacobians(model, gains, ref_k, active, rot, state.omega)
        kmat, dmat = _angular_embed(kmat, n), _angular_embed(dmat, n)
    else:
        k_stiff = muscle_and_gyro(model, gains, ref_k, active, rot, state.omega)
        kmat = dmat = jnp.zeros((6 * n, 6 * n), rot.dtype)
    gravity = gravity_forces(model)
    f_pert, per_body, points = generalized_forces(pulses, t, n, state.pos, rot, model.com)
    kvec = k_stiff + gravity + f_pert
    m = mass_matrix(model, rot)
    jac = full_constraints(model, cfg.driven, rot, cfg.free_root)
    nc = jac.shape[0]
    v = state.v
    a11 = m - h * dmat - h * h * kmat
    lhs = jnp.block([[a11, -jac.T], [jac, jnp.zeros((nc, nc), rot.dtype)]])
    b = constraint_velocity(model, cfg.driven, rot, ref.root_vel[k + 1], ref.root_omega[k + 1],
                            ref.rel_omega[k + 1], cfg.free_root)
    rhs = jnp.concatenate([m @ v + h * (kvec - dmat @ v), b])
    sol = jnp.linalg.solve(lhs, rhs)
    residual = jnp.linalg.norm(lhs @ sol - rhs) / jnp.maximum(jnp.linalg.norm(rhs), 1e-300)
    return _advance(model, cfg, ref, k, state, sol[: 6 * n].reshape(n, 6), post_stabilize,
                    (residual, per_body, points, sol[6 * n:]))


class Rollout(eqx.Module):
    """States at t_0..t_S, simulated joint angles, and per-step diagnostics."""

    time: Float[Array, " S1"]
    states: State  # leaves with leading axis S+1
    theta: Float[Array, "S1 n"]
    theta_dot: Float[Array, "S1 n"]
    residual: Float[Array, " S"]
    violation: Float[Array, " S"]
    force: Float[Array, "S1 B 3"]
    points: Float[Array, "S1 P 3"]
    diverged_step: Int[Array, ""]  # -1 if the run stayed finite
    diverged_body: Int[Array, ""]


def _badness(state: State, max_speed: float):
    finite = (jnp.all(jnp.isfinite(state.pos), -1) & jnp.all(jnp.isfinite(state.quat), -1)
              & jnp.all(jnp.isfinite(state.vel), -1) & jnp.all(jnp.isfinite(state.omega), -1))
    speed = jnp.maximum(jnp.linalg.norm(state.vel, axis=-1), jnp.linalg.norm(state.omega, axis=-1))
    score = jnp.where(finite, speed / max_speed, jnp.inf)
    return score


def observe(model: Model, state: State, ref: Reference, k):
    rot = state.rot
    theta = joint_angles(model, rot, reference=ref.theta[k])
    axes = dof_axes(model, rot, theta)
    return theta, joint_rates(model, axes, state.omega)


def rollout(model: Model, gains: Gains, pulses: ForcePulses, ref: Reference, cfg: SimConfig) -> Rollout:
    """Simulate ``cfg.n_steps`` steps from the reference's initial state (one ``lax.scan``)."""
    if ref.time.shape[0] < cfg.n_steps + 1:
        raise ValueError(f"reference has {ref.time.shape[0] - 1} steps, config asks for {cfg.n_steps}")
    if pulses is None:
        pulses = no_pulses()

    def body(carry, k):
        state, bad_step, bad_body = carry
        new, info = step(model, gains, pulses, cfg, ref, k, state)
        score = _badness(new, cfg.max_speed)
        is_bad = jnp.max(score) > 1.0
        first = is_bad & (bad_step < 0)
        bad_step = jnp.where(first, k, bad_step)
        bad_body = jnp.where(first, jnp.argmax(score), bad_body)
        # After a blow-up keep the last good state so NaNs do not spread through the batch.
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(bad_step >= 0, a, b), state, new)
        return (new, bad_step, bad_body), (new, info)

    init = ref.init
    carry0 = (init, jnp.asarray(-1), jnp.asarray(-1))
    (_, bad_step, bad_body), (states, info) = jax.lax.scan(
        body, carry0, jnp.arange(cfg.n_steps)
    )
    stack = lambda a, b: jnp.concatenate([a[None], b], 0)
    states = jax.tree_util.tree_map(stack, init, states)
    # Joint angles and rates of all states at once after the scan: the per-step loop keeps
    # only the dynamics, and the observation runs as a few wide vectorized ops.
    theta, theta_dot = jax.vmap(lambda st, k: observe(model, st, ref, k))(
        states, jnp.arange(cfg.n_steps + 1))
    _, f0, p0 = generalized_forces(pulses, ref.time[0], model.n_bodies, init.pos, init.rot, model.com)
    return Rollout(
        ref.time[: cfg.n_steps + 1],
        states,
        theta,
        theta_dot,
        info.residual,
        info.violation,
        stack(f0, info.force),
        stack(p0, info.points),
        bad_step,
        bad_body,
    )


def check_rollout(model: Model, run: Rollout) -> Rollout:
    """Raise :class:`SimulationDiverged` (step, time, body) if the rollout blew up."""
    step_ = int(run.diverged_step)
    if step_ >= 0:
        raise SimulationDiverged(step_, float(run.time[step_ + 1]), model.body_names[int(run.diverged_body)])
    return run
