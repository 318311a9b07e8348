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
import numpy as np
from jaxtyping import Array, Float

from neuromotor.model.skeleton import Model
from neuromotor.physics import static
from neuromotor.rotations import (
    euler_angles_and_rates,
    euler_axes,
    mm,
    mmt,
    mv,
    quat_conj,
    quat_entries,
    quat_mul,
    quat_rotate,
    quat_to_matrix,
    quat_turn,
    rotation_error,
    skew,
)


def per_joint_to_dofs(model: Model, values: Float[Array, "C 3 ..."]) -> Float[Array, "n ..."]:
    """Scatter per-joint triples (rows in body order 1..B-1) to the DOF layout."""
    topo = model.topology
    if topo.contiguous:
        return values.reshape((-1,) + values.shape[2:])
    out = jnp.zeros((model.n_dofs,) + values.shape[2:], values.dtype)
    return out.at[topo.joint_dofs.reshape(-1)].set(values.reshape((-1,) + values.shape[2:]))


def dofs_to_per_joint(model: Model, values: Float[Array, "n ..."]) -> Float[Array, "C 3 ..."]:
    topo = model.topology
    if topo.contiguous:
        return values.reshape((model.n_bodies - 1, 3) + values.shape[1:])
    return values[topo.joint_dofs]


def solve3(a: Float[Array, "... 3 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """x = a^-1 b by Cramer's rule: a handful of fused elementwise ops instead of a LAPACK
    call per tiny matrix (the 3x3 systems here are well scaled or damped)."""
    c0, c1, c2 = a[..., :, 0], a[..., :, 1], a[..., :, 2]
    r0, r1, r2 = jnp.cross(c1, c2), jnp.cross(c2, c0), jnp.cross(c0, c1)  # rows of adj(a)
    det = jnp.sum(c0 * r0, -1)
    adj_b = jnp.stack([jnp.sum(r0 * b, -1), jnp.sum(r1 * b, -1), jnp.sum(r2 * b, -1)], -1)
    return adj_b / det[..., None]


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
    return mmt(mm(rot, model.inertia), rot)


def mass_matrix(model: Model, rot: Float[Array, "B 3 3"]) -> Float[Array, "6B 6B"]:
    """Block-diagonal M: one ``diag(m I3, R I R^T)`` block per body."""
    n = model.n_bodies
    blocks = jnp.zeros((n, 6, 6), rot.dtype)
    blocks = blocks.at[:, :3, :3].set(model.mass[:, None, None] * jnp.eye(3, dtype=rot.dtype))
    blocks = blocks.at[:, 3:, 3:].set(world_inertia(model, rot))
    return _block_diag(blocks)


def apply_inverse_mass(model: Model, rot, g: Float[Array, "... 6B"]) -> Float[Array, "... 6B"]:
    """M^-1 g for generalized vectors (rows of g)."""
    inv_m = 1.0 / model.mass
    inv_i = rot @ jnp.linalg.inv(model.inertia) @ jnp.swapaxes(rot, -1, -2)
    g = g.reshape(g.shape[:-1] + (model.n_bodies, 6))
    lin = g[..., :3] * inv_m[:, None]
    ang = jnp.einsum("bij,...bj->...bi", inv_i, g[..., 3:])
    return jnp.concatenate([lin, ang], -1).reshape(g.shape[:-2] + (6 * model.n_bodies,))


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
    parent = np.asarray(model.body_parent[1:])
    anchor_parent = model.joint_offset[np.asarray(model.body_joint[1:])] - model.com[parent]
    r_parent = mv(rot[parent], anchor_parent)
    r_child = -mv(rot[1:], model.com[1:])
    return r_parent, r_child


def root_lever(model: Model, rot) -> Float[Array, 3]:
    """World vector from the root COM to the root joint's origin."""
    return -mv(rot[0], model.com[0])


def constraint_jacobian(model: Model, rot) -> Float[Array, "nc 6B"]:
    """J of Eq. 1: 6 driven-root rows, then 3 rows per ball joint (parent minus child point)."""
    n = model.n_bodies
    dtype = rot.dtype
    eye = jnp.eye(3, dtype=dtype)
    r0 = root_lever(model, rot)
    # Root joint origin velocity v + omega x r = v - [r]x omega; root angular velocity omega.
    root = jnp.zeros((6, n, 6), dtype)
    root = root.at[0:3, 0, 0:3].set(eye).at[0:3, 0, 3:6].set(-skew(r0)).at[3:6, 0, 3:6].set(eye)
    blk_parent, blk_child = joint_jacobian_blocks(model, rot)
    topo = model.topology
    # One-hot selectors (static) place every joint's two 3x6 blocks in one contraction.
    sel_p, sel_c = jnp.asarray(topo.sel_parent, dtype), jnp.asarray(topo.sel_child, dtype)
    rows = jnp.einsum("cb,cij->cibj", sel_p, blk_parent) + jnp.einsum("cb,cij->cibj", sel_c, blk_child)
    return jnp.concatenate([root.reshape(6, 6 * n), rows.reshape(3 * (n - 1), 6 * n)], 0)


def full_constraints(model: Model, driven: tuple[int, ...], rot, free_root: bool = False) -> Float[Array, "nc 6B"]:
    """J with extra rows for driven joints (relative angular velocity of child and parent);
    without the 6 root rows when the root floats free."""
    jac = constraint_jacobian(model, rot)[6 if free_root else 0 :]
    if not driven:
        return jac
    n = model.n_bodies
    rows = jnp.zeros((3 * len(driven), 6 * n), rot.dtype)
    eye = jnp.eye(3, dtype=rot.dtype)
    for i, b in enumerate(driven):
        p = model.body_parent[b]
        rows = rows.at[3 * i : 3 * i + 3, 6 * b + 3 : 6 * b + 6].set(eye)
        rows = rows.at[3 * i : 3 * i + 3, 6 * p + 3 : 6 * p + 6].set(-eye)
    return jnp.concatenate([jac, rows], 0)


def joint_jacobian_blocks(model: Model, rot) -> tuple[Float[Array, "C 3 6"], Float[Array, "C 3 6"]]:
    """Per ball joint, its 3 rows of J restricted to the parent's and the child's 6 columns."""
    r_parent, r_child = joint_levers(model, rot)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=rot.dtype), r_parent.shape + (3,))
    return (jnp.concatenate([eye, -skew(r_parent)], -1), jnp.concatenate([-eye, skew(r_child)], -1))


def constraint_error(model: Model, pos, rot, root_origin, root_rot) -> Float[Array, " nc"]:
    """Position-level C(x): root origin and orientation errors, then joint point gaps."""
    r0 = root_lever(model, rot)
    err_root_pos = pos[0] + r0 - root_origin
    err_root_rot = rotation_error(rot[0], root_rot)
    r_parent, r_child = joint_levers(model, rot)
    gaps = (pos[np.asarray(model.body_parent[1:])] + r_parent) - (pos[1:] + r_child)
    return jnp.concatenate([err_root_pos, err_root_rot, gaps.reshape(-1)])


def joint_angles_and_rates(model: Model, quat, omega, reference: Float[Array, " n"] | None = None):
    """Simulated DOF angles theta_i (the mocap's Euler decomposition of each body's rotation in
    its parent's frame; with a ``reference`` the branch and 2 pi multiple nearest it) and their
    rates theta_dot (what :func:`joint_rates` solves for over :func:`dof_axes`), from body
    quaternions and angular velocities. Written for observing many states at once: parents by
    static slices rather than gathers, relative rotations as quaternions, and the rates by
    :func:`neuromotor.rotations.euler_angles_and_rates` rather than a 3x3 solve per joint."""
    if model.n_bodies < 2:
        return jnp.zeros((0,), quat.dtype), jnp.zeros((0,), quat.dtype)
    topo = model.topology
    q_p = static.take(quat, topo.parent)
    rel = quat_mul(quat_conj(q_p), static.take(quat, topo.child))
    w_rel = quat_rotate(quat_conj(q_p), static.take(omega, topo.child) - static.take(omega, topo.parent))
    ref = None if reference is None else dofs_to_per_joint(model, reference)
    theta, rates = jnp.zeros((2, model.n_bodies - 1, 3), quat.dtype)
    for order, _bodies, rows in topo.groups:  # usually one order per skeleton
        whole = len(rows) == model.n_bodies - 1
        pick = (lambda x: x) if whole else (lambda x: static.take(x, rows))
        ang, rate = euler_angles_and_rates(
            quat_entries(pick(rel)), pick(w_rel), order, None if ref is None else pick(ref)
        )
        theta, rates = (ang, rate) if whole else (theta.at[rows].set(ang), rates.at[rows].set(rate))
    return per_joint_to_dofs(model, theta), per_joint_to_dofs(model, rates)


def joint_axes(model: Model, rot, angles: Float[Array, " n"]) -> Float[Array, "C 3 3"]:
    """Per non-root body, the rows h_1, h_2, h_3 of its joint (Eq. 4)."""
    topo = model.topology
    ang = dofs_to_per_joint(model, angles)
    out = jnp.zeros((model.n_bodies - 1, 3, 3), rot.dtype)
    for order, bodies, rows in topo.groups:
        part = euler_axes(rot[topo.parent[rows]], ang[rows], order)
        out = part if len(bodies) == model.n_bodies - 1 else out.at[rows].set(part)
    return out


def dof_axes(model: Model, rot, angles: Float[Array, " n"]) -> Float[Array, "n 3"]:
    """World-frame Euler axes h_i of every simulated DOF (Eq. 4)."""
    return per_joint_to_dofs(model, joint_axes(model, rot, angles))


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
    topo = model.topology
    w_rel = omega[topo.child] - omega[topo.parent]
    a = jnp.swapaxes(dofs_to_per_joint(model, axes), -1, -2)  # columns h_i
    return per_joint_to_dofs(model, solve3(a, w_rel))


def kkt_matrix(model: Model, rot, axes) -> Float[Array, "N N2"]:
    """The block matrix of Eq. 1, ``[[M, -J^T, -H^T], [J, 0, 0]]``."""
    m = mass_matrix(model, rot)
    jac = constraint_jacobian(model, rot)
    h = muscle_jacobian(model, axes)
    nc, nd = jac.shape[0], h.shape[0]
    top = jnp.concatenate([m, -jac.T, -h.T], 1)
    bottom = jnp.concatenate([jac, jnp.zeros((nc, nc + nd), m.dtype)], 1)
    return jnp.concatenate([top, bottom], 0)


def mass_times(model: Model, inertia: Float[Array, "B 3 3"], x: Float[Array, "B 6"]) -> Float[Array, "B 6"]:
    """M x with M block diagonal (``inertia``: the world inertias of :func:`world_inertia`)."""
    return jnp.concatenate([model.mass[:, None] * x[:, :3], mv(inertia, x[:, 3:])], -1)


def mass_blocks(model: Model, inertia: Float[Array, "B 3 3"]) -> Float[Array, "B 6 6"]:
    """The diagonal blocks ``diag(m I3, R I R^T)`` of M."""
    lin = model.mass[:, None, None] * jnp.eye(3, dtype=inertia.dtype)
    z = jnp.zeros_like(lin)
    return jnp.concatenate([jnp.concatenate([lin, z], -1), jnp.concatenate([z, inertia], -1)], -2)


def embed_angular(x: Float[Array, ...], axes: tuple[int, ...] = (-2, -1)) -> Float[Array, ...]:
    """Angular coordinates placed in the ``[linear, angular]`` layout of a body: every axis in
    ``axes`` (size 3) gets 3 zeros in front (3x3 blocks become 6x6, (..., 3) rows become 6)."""
    pad = [(0, 0)] * x.ndim
    for a in axes:
        pad[a] = (3, 0)
    return jnp.pad(x, pad)


def retract(pos: Float[Array, "B 3"], quat: Float[Array, "B 4"], dx: Float[Array, "B 6"]):
    """x (+) dx: positions add, orientations turn by exp(dtheta) (world frame)."""
    return pos + dx[:, :3], quat_turn(quat, dx[:, 3:])
