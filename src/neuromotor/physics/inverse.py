"""Inverse dynamics on the mocap (Eq. 3 and Section 5.1).

With accelerations known from the splines, the second row of Eq. 1 drops out and

    [J^T  H^T] [lam; tau] = M a - f_ext          (3)

For a tree of ball joints with the root driven by 6 rows, ``[J^T H^T]`` is square
(6B = 6 + 3(B-1) + 3(B-1)), so Eq. 3 has one exact solution per frame: the feedforward torque
multipliers tau_i (Eq. 4) and the constraint forces lam.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor import compiler
from neuromotor.model.kinematics import Trajectory, body_kinematics, joint_angles_from_q
from neuromotor.model.skeleton import Model
from neuromotor.model.topology import Topology
from neuromotor.physics.system import (
    dof_axes,
    external_forces,
    joint_jacobian_blocks,
    per_joint_to_dofs,
    root_lever,
    world_inertia,
)
from neuromotor.rotations import matrix_to_quat, mm, skew


class InverseDynamics(eqx.Module):
    """Per-time-sample solution of Eq. 3."""

    time: Float[Array, " T"]
    tau: Float[Array, "T n"]  # feedforward torque multipliers of the simulated DOFs
    lam: Float[Array, "T nc"]  # constraint multipliers: root (6) then 3 per ball joint
    axes: Float[Array, "T n 3"]  # world Euler axes h_i
    residual: Float[Array, " T"]  # ||A x - b|| / ||b|| of Eq. 3


def mocap_angles(model: Model, traj: Trajectory, t):
    """Euler angles of every non-root channel and their first two time derivatives (jvp)."""
    ref = traj.angle_reference(t)
    q, qd, qdd = traj.q(t), traj.qd(t), traj.qdd(t)

    def rate(q_, qd_):
        return jax.jvp(lambda x: joint_angles_from_q(model, x, ref), (q_,), (qd_,))

    (theta, theta_dot), (_, theta_ddot) = jax.jvp(rate, (q, qd), (qd, qdd))
    return theta, theta_dot, theta_ddot


def sim_columns(model: Model):
    return jnp.array(model.sim_dof_columns, dtype=jnp.int32)


def _eq3_layout(topo: Topology) -> np.ndarray:
    """Static placement of the nonzero blocks of ``[J^T H^T]`` (Eq. 3): for every entry of the
    (6B, nc + n) matrix, its index in the flat vector of block values of :func:`eq3_matrix`,
    or the index of a trailing zero. One gather then assembles the matrix, instead of scatters
    and one-hot contractions that each compile to kernels of their own."""
    body_parent, dof_body = topo.body_parent, topo.dof_body
    n_bodies, n_dofs = len(body_parent), len(dof_body)
    nc = 6 + 3 * (n_bodies - 1)
    n_vals = 36 + 36 * (n_bodies - 1) + 6 * n_dofs
    index = np.full((6 * n_bodies, nc + n_dofs), n_vals, dtype=np.int64)
    block = lambda start, rows, cols: start + np.arange(rows * cols).reshape(rows, cols)
    index[0:6, 0:6] = block(0, 6, 6)  # driven root: J_root^T on body 0
    for c in range(n_bodies - 1):
        child, parent, col = c + 1, body_parent[c + 1], 6 + 3 * c
        index[6 * parent : 6 * parent + 6, col : col + 3] = block(36 + 36 * c, 6, 3)
        index[6 * child : 6 * child + 6, col : col + 3] = block(36 + 36 * c + 18, 6, 3)
    start = 36 + 36 * (n_bodies - 1)
    for i, child in enumerate(dof_body):  # +h_i on the child's torque rows, -h_i on the parent's
        parent = body_parent[child]
        index[6 * child + 3 : 6 * child + 6, nc + i] = start + 6 * i + np.arange(3)
        index[6 * parent + 3 : 6 * parent + 6, nc + i] = start + 6 * i + 3 + np.arange(3)
    return index


def eq3_matrix(model: Model, rot: Float[Array, "B 3 3"], axes: Float[Array, "n 3"]) -> Float[Array, "6B N"]:
    """``[J^T H^T]`` of Eq. 3, entry for entry the transposes of :func:`system.constraint_jacobian`
    and :func:`system.muscle_jacobian` (same block values, placed by a static gather)."""
    dtype = rot.dtype
    eye = jnp.eye(3, dtype=dtype)
    zero = jnp.zeros((3, 3), dtype)
    # Root rows of J: joint origin velocity v - [r0]x omega, angular velocity omega.
    root = jnp.block([[eye, -skew(root_lever(model, rot))], [zero, eye]])
    blk_parent, blk_child = joint_jacobian_blocks(model, rot)  # (C, 3, 6) rows of J
    vals = jnp.concatenate(
        [
            root.T.reshape(-1),
            jnp.concatenate([jnp.swapaxes(blk_parent, -1, -2), jnp.swapaxes(blk_child, -1, -2)], 1).reshape(-1),
            jnp.concatenate([axes, -axes], -1).reshape(-1),
            jnp.zeros((1,), dtype),
        ]
    )
    return vals[model.topology.derived(_eq3_layout)]


def solve_eq3(model: Model, q, qd, qdd, theta_sim, local_axes=None):
    """Solve Eq. 3 at one instant; returns (lam, tau, axes, relative residual). ``local_axes``
    (C, 3, 3), columns in each parent's frame: the axes h_i of the multipliers (None: the Euler
    axes at ``theta_sim``, Eq. 4)."""
    _, rot, _, omega, acc, alpha = body_kinematics(model, q, qd, qdd)
    if local_axes is None:
        axes = dof_axes(model, rot, theta_sim)
    else:
        axes = per_joint_to_dofs(model, jnp.swapaxes(mm(rot[model.topology.parent], local_axes), -1, -2))
    # M a with M block diagonal, diag(m I3, R I R^T) per body.
    m_a = jnp.concatenate([model.mass[:, None] * acc, jnp.einsum("bij,bj->bi", world_inertia(model, rot), alpha)], -1)
    rhs = m_a.reshape(-1) - external_forces(model, rot, omega)
    lhs = eq3_matrix(model, rot, axes)
    x = jnp.linalg.solve(lhs, rhs)
    residual = jnp.linalg.norm(lhs @ x - rhs) / jnp.maximum(jnp.linalg.norm(rhs), 1e-300)
    nc = model.n_constraints
    return x[:nc], x[nc:], axes, residual


@compiler.jit
def inverse_dynamics(
    model: Model, traj: Trajectory, times: Float[Array, " T"], local_axes: Float[Array, "T C 3 3"] | None = None
) -> InverseDynamics:
    """Eq. 3 at every time in ``times`` (vmapped), from the spline of the mocap (``local_axes``:
    see :func:`solve_eq3`)."""

    def one(t, la):
        theta = joint_angles_from_q(model, traj.q(t), traj.angle_reference(t))
        return solve_eq3(model, traj.q(t), traj.qd(t), traj.qdd(t), theta[sim_columns(model)], la)

    lam, tau, axes, res = jax.vmap(one)(times, local_axes)
    return InverseDynamics(times, tau, lam, axes, res)


def idyn_arrays(model: Model, traj: Trajectory, times: np.ndarray | Array) -> dict[str, np.ndarray]:
    """Everything ``neuromotor idyn`` writes (see the README's file contract)."""
    times = jnp.asarray(times)
    sol = inverse_dynamics(model, traj, times)
    q = jax.vmap(traj.q)(times)
    qd = jax.vmap(traj.qd)(times)
    qdd = jax.vmap(traj.qdd)(times)
    theta, theta_dot, theta_ddot = jax.vmap(lambda t: mocap_angles(model, traj, t))(times)
    kin = jax.vmap(lambda a, b, c: body_kinematics(model, a, b, c))(q, qd, qdd)
    rot, omega, alpha = kin[1], kin[3], kin[5]
    n_all = len(model.all_dof_names)
    cols = np.array(model.sim_dof_columns, dtype=np.int64)
    tau_all = np.zeros((len(times), n_all))
    tau_all[:, cols] = np.asarray(sol.tau)
    # Muscle torque on each joint's child body: sum over its DOFs of h_i tau_i.
    torque = np.zeros((len(times), len(model.joint_names), 3))
    contrib = np.asarray(sol.axes * sol.tau[..., None])
    for i, b in enumerate(model.dof_body):
        torque[:, model.body_joint[b]] += contrib[:, i]
    return {
        "time": np.asarray(times),
        "dof_names": np.array(model.all_dof_names),
        "theta": np.asarray(theta),
        "theta_dot": np.asarray(theta_dot),
        "theta_ddot": np.asarray(theta_ddot),
        "tau": tau_all,
        "root_pos": np.asarray(q[:, 0:3]),
        "root_quat": np.asarray(matrix_to_quat(rot[:, 0])),
        "root_lin_vel": np.asarray(qd[:, 0:3]),  # the spline's own derivative
        "root_ang_vel": np.asarray(omega[:, 0]),
        "root_lin_acc": np.asarray(qdd[:, 0:3]),
        "root_ang_acc": np.asarray(alpha[:, 0]),
        "joint_torque_world": torque,
        "root_wrench": np.asarray(sol.lam[:, 0:6]),
        "kkt_residual": np.asarray(sol.residual),
    }
