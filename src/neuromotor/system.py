"""Assembly of the block system of Eq. 1 in maximal coordinates.

    [ M  -J^T  -H^T ] [  a  ]   [ f_ext ]
    [ J    0     0  ] [ lam ] = [   0   ]          (1)
                      [ tau ]

Every body has its own 6-DOF state; generalized vectors are laid out per body as
``[linear (3), angular (3)]`` in the world frame, with the body's COM as reference point, so M
is block diagonal ``diag(m I3, R I R^T)``. J stacks 6 rows that drive the root joint along the
mocap (position of the root joint's origin and orientation of the root body) and 3 rows per ball
joint (coincidence of the joint point seen from parent and child). H has one row per simulated
rotational DOF: the world-frame Euler axis h_i as +torque on the child and -torque on the parent.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .rotations import (
    euler_axes,
    matrix_to_euler,
    quat_to_matrix,
    rotation_error,
    skew,
)
from .skeleton import Model


class State(eqx.Module):
    """Maximal-coordinate state: per body COM position, orientation, and velocities (world)."""

    pos: Float[Array, "B 3"]
    quat: Float[Array, "B 4"]  # w, x, y, z
    vel: Float[Array, "B 3"]
    omega: Float[Array, "B 3"]

    @property
    def rot(self) -> Float[Array, "B 3 3"]:
        return quat_to_matrix(self.quat)

    @property
    def v(self) -> Float[Array, " 6B"]:
        """Generalized velocity, ``[vel_b, omega_b]`` per body."""
        return jnp.concatenate([self.vel, self.omega], -1).reshape(-1)


def world_inertia(model: Model, rot: Float[Array, "B 3 3"]) -> Float[Array, "B 3 3"]:
    return rot @ model.inertia @ jnp.swapaxes(rot, -1, -2)


def mass_matrix(model: Model, rot: Float[Array, "B 3 3"]) -> Float[Array, "6B 6B"]:
    """Block-diagonal M: one ``diag(m I3, R I R^T)`` block per body."""
    n = model.n_bodies
    blocks = jnp.zeros((n, 6, 6), rot.dtype)
    blocks = blocks.at[:, :3, :3].set(model.mass[:, None, None] * jnp.eye(3, dtype=rot.dtype))
    blocks = blocks.at[:, 3:, 3:].set(world_inertia(model, rot))
    return _block_diag(blocks)


def _block_diag(blocks: Float[Array, "n 6 6"]) -> Float[Array, "6n 6n"]:
    n = blocks.shape[0]
    eye = jnp.eye(n, dtype=blocks.dtype)
    return jnp.einsum("ab,aij->aibj", eye, blocks).reshape(6 * n, 6 * n)


def gravity_forces(model: Model) -> Float[Array, " 6B"]:
    """Gravity m g on each COM (no torque)."""
    force = model.mass[:, None] * model.gravity
    return jnp.concatenate([force, jnp.zeros_like(force)], -1).reshape(-1)


def gyroscopic_forces(model: Model, rot, omega) -> Float[Array, " 6B"]:
    """The gyroscopic term -omega x (I omega) of each body (torque only)."""
    iw = world_inertia(model, rot)
    torque = -jnp.cross(omega, jnp.einsum("bij,bj->bi", iw, omega))
    return jnp.concatenate([jnp.zeros_like(torque), torque], -1).reshape(-1)


def external_forces(model: Model, rot, omega) -> Float[Array, " 6B"]:
    """f_ext of Eq. 1: gravity on each COM and the gyroscopic term -omega x (I omega)."""
    return gravity_forces(model) + gyroscopic_forces(model, rot, omega)


def joint_levers(model: Model, rot) -> tuple[Float[Array, "C 3"], Float[Array, "C 3"]]:
    """World vectors from parent COM and from child COM to each ball joint point."""
    child = jnp.arange(1, model.n_bodies)
    parent = jnp.array(model.body_parent[1:])
    joint = jnp.array(model.body_joint[1:])
    anchor_parent = model.joint_offset[joint] - model.com[parent]
    r_parent = jnp.einsum("cij,cj->ci", rot[parent], anchor_parent)
    r_child = -jnp.einsum("cij,cj->ci", rot[child], model.com[child])
    return r_parent, r_child


def root_lever(model: Model, rot) -> Float[Array, "3"]:
    """World vector from the root COM to the root joint's origin."""
    return -rot[0] @ model.com[0]


def constraint_jacobian(model: Model, rot) -> Float[Array, "nc 6B"]:
    """J of Eq. 1: 6 driven-root rows, then 3 rows per ball joint (parent minus child point)."""
    n = model.n_bodies
    dtype = rot.dtype
    jac = jnp.zeros((model.n_constraints, 6 * n), dtype)
    eye = jnp.eye(3, dtype=dtype)
    r0 = root_lever(model, rot)
    # Root joint origin velocity v + omega x r = v - [r]x omega; root angular velocity omega.
    jac = jac.at[0:3, 0:3].set(eye).at[0:3, 3:6].set(-skew(r0))
    jac = jac.at[3:6, 3:6].set(eye)
    r_parent, r_child = joint_levers(model, rot)
    for c in range(1, n):
        p = model.body_parent[c]
        row = 6 + 3 * (c - 1)
        jac = jac.at[row:row + 3, 6 * p:6 * p + 3].set(eye)
        jac = jac.at[row:row + 3, 6 * p + 3:6 * p + 6].set(-skew(r_parent[c - 1]))
        jac = jac.at[row:row + 3, 6 * c:6 * c + 3].set(-eye)
        jac = jac.at[row:row + 3, 6 * c + 3:6 * c + 6].set(skew(r_child[c - 1]))
    return jac


def constraint_error(model: Model, pos, rot, root_origin, root_rot) -> Float[Array, " nc"]:
    """Position-level C(x): root origin and orientation errors, then joint point gaps."""
    r0 = root_lever(model, rot)
    err_root_pos = pos[0] + r0 - root_origin
    err_root_rot = rotation_error(rot[0], root_rot)
    r_parent, r_child = joint_levers(model, rot)
    parent = jnp.array(model.body_parent[1:])
    gaps = (pos[parent] + r_parent) - (pos[1:] + r_child)
    return jnp.concatenate([err_root_pos, err_root_rot, gaps.reshape(-1)])


def relative_rotations(model: Model, rot) -> Float[Array, "B 3 3"]:
    """Orientation of each body in its parent's frame (identity for the root)."""
    parent = jnp.array([max(p, 0) for p in model.body_parent])
    rel = jnp.swapaxes(rot[parent], -1, -2) @ rot
    return rel.at[0].set(jnp.eye(3, dtype=rot.dtype))


def joint_angles(model: Model, rot, reference: Float[Array, " n"] | None = None) -> Float[Array, " n"]:
    """Simulated DOF angles theta_i from the body orientations (same Euler decomposition as the
    mocap; with a ``reference`` the branch and 2 pi multiple nearest it)."""
    rel = relative_rotations(model, rot)
    out = []
    for b in range(1, model.n_bodies):
        dofs = model.dofs_of_body(b)
        order = model.joint_order[model.body_joint[b]]
        ref = None if reference is None else reference[jnp.array(dofs)]
        out.append(matrix_to_euler(rel[b], order, ref))
    return jnp.concatenate(out) if out else jnp.zeros((0,), rot.dtype)


def dof_axes(model: Model, rot, angles: Float[Array, " n"]) -> Float[Array, "n 3"]:
    """World-frame Euler axes h_i of every simulated DOF (Eq. 4)."""
    axes = []
    for b in range(1, model.n_bodies):
        dofs = jnp.array(model.dofs_of_body(b))
        order = model.joint_order[model.body_joint[b]]
        axes.append(euler_axes(rot[model.body_parent[b]], angles[dofs], order))
    return jnp.concatenate(axes, 0)


def muscle_jacobian(model: Model, axes: Float[Array, "n 3"]) -> Float[Array, "n 6B"]:
    """H: row i applies torque +h_i to DOF i's child body and -h_i to its parent."""
    n = model.n_bodies
    child = jnp.array(model.dof_body)
    parent = jnp.array([model.body_parent[b] for b in model.dof_body])
    rows = jnp.zeros((model.n_dofs, n, 6), axes.dtype)
    idx = jnp.arange(model.n_dofs)
    rows = rows.at[idx, child, 3:].add(axes)
    rows = rows.at[idx, parent, 3:].add(-axes)
    return rows.reshape(model.n_dofs, 6 * n)


def joint_rates(model: Model, axes: Float[Array, "n 3"], omega: Float[Array, "B 3"]) -> Float[Array, " n"]:
    """theta_dot of each DOF: solve sum_i h_i thetadot_i = omega_child - omega_parent per joint."""
    out = []
    for b in range(1, model.n_bodies):
        dofs = jnp.array(model.dofs_of_body(b))
        w_rel = omega[b] - omega[model.body_parent[b]]
        out.append(jnp.linalg.solve(axes[dofs].T, w_rel))
    return jnp.concatenate(out)


def kkt_matrix(model: Model, rot, axes) -> Float[Array, "N N2"]:
    """The block matrix of Eq. 1, ``[[M, -J^T, -H^T], [J, 0, 0]]``."""
    m = mass_matrix(model, rot)
    jac = constraint_jacobian(model, rot)
    h = muscle_jacobian(model, axes)
    nc, nd = jac.shape[0], h.shape[0]
    top = jnp.concatenate([m, -jac.T, -h.T], 1)
    bottom = jnp.concatenate([jac, jnp.zeros((nc, nc + nd), m.dtype)], 1)
    return jnp.concatenate([top, bottom], 0)
