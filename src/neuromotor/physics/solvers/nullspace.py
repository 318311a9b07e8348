"""The KKT systems of Eq. 2 and of post-stabilization solved by the null-space method.

Eq. 2 is a saddle-point system in maximal coordinates,

    [ A   -J^T ] [ v   ]   [ r ]
    [ J    0   ] [ lam ] = [ b ],        A = M - h D - h^2 K,

where J stacks the ball-joint rows (joint point seen from parent minus from child), the driven
root's 6 rows and the driven joints' 3 rows each. The null-space method (Benzi, Golub & Liesen
2005, Section 6) writes v = S u with the columns of S spanning the null space of the ball-joint
rows, so that ``S^T J_ball^T = 0`` and the multipliers drop out:

    (S^T A S) u = S^T r.                                              (Eq. 2 projected)

Here S is explicit and cheap. Its columns are a translation v0 of the whole body and one
rotation u_k per body k: the root's rotation about its COM, and each other body's relative
angular velocity at the joint that attaches it (world frame). A body i moves with

    omega_i = sum_{k in anc(i)} u_k,      v_i = v0 + sum_{k in anc(i)} u_k x (c_i - p_k),

where anc(i) is i and its ancestors (a static 0/1 matrix), c_i the COM and p_k the pivot of
column k. Geometry is taken from the joint levers, the same vectors J is made of, so J_ball S = 0
holds to round-off whatever the constraint drift. The root's 6 columns (when the root is driven)
and the columns of driven joints are known from b; the others (3 per free joint) are solved for.

S^T M S is the joint-space inertia matrix, assembled in closed form from subtree sums
(composite inertias, as in the composite-rigid-body algorithm; see :func:`reduced_inertia`).
The stiff blocks of A (hD + h^2 K, angular, on the tree) reduce by subtree sums as well. Where
the root is driven and every joint is free (the common case) the joint-space matrix is never
assembled: it is factored along the body tree (:mod:`.branch`, no fill-in, no LAPACK call);
otherwise its free block is assembled and solved by one dense LU. (The dense LU of the common
case, :func:`solve_kkt`, is kept as the tests' check of the tree factorization: a 54 x 54 LAPACK
LU and its layout copies took longer than the whole level-by-level factorization.) The
multipliers are recovered exactly from ``J^T lam = A v - r`` by subtree sums of the residual
force (the ball joints) and by the projected residual (root and driven joints).

Post-stabilization (Cline & Pai 2003) projects positions onto the constraints in the metric of M:
``min |dx|_M  s.t.  J dx = -C(x)``. A particular solution translates every subtree by its joint's
gap and turns the root and driven joints by their errors; the null-space part is then
``w = -(S^T M S)^-1 S^T M dx_p``, the same projection as ``dx = M^-1 J^T (J M^-1 J^T)^-1 (-C)``.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg  # noqa: F401  (cho_factor, cho_solve)
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor.model.topology import Topology
from neuromotor.physics import static
from neuromotor.physics.solvers import branch
from neuromotor.physics.solvers.base import ContactResponses, KKTSolver, relative_residual
from neuromotor.physics.stiffness import tree_matvec
from neuromotor.physics.system import joint_levers, root_lever, world_inertia
from neuromotor.rotations import cross, mv, skew


@dataclasses.dataclass(frozen=True, eq=False)
class Structure:
    """Static (numpy) index data of a tree with given driven bodies; see :func:`structure`."""

    anc: np.ndarray  # (B, B): anc[i, k] = 1 if k is i or an ancestor of i
    strict_up: np.ndarray  # (B, B): 1 if l is a strict ancestor of k
    free: np.ndarray  # scalar indices of the unknown entries of u
    known: np.ndarray  # scalar indices of the known entries of u
    order: np.ndarray  # u = concat(u_free, u_known)[order]
    driven: tuple[int, ...]
    free_root: bool
    tree: branch.Schedule  # elimination order of the joint-space matrix (common case)
    unrolled: bool  # static indexing as slices (batched solver) or gathers (:mod:`neuromotor.physics.static`)

    @property
    def by_tree(self) -> bool:
        """Driven root, every joint free: H is factored along the tree (:mod:`.branch`)."""
        return not (self.free_root or self.driven)


def _structure(topo: Topology, driven: tuple[int, ...], free_root: bool, unrolled: bool) -> Structure:
    n = topo.n_bodies
    anc = topo.anc
    strict_up = anc - np.eye(n)
    # u = [v0 (3), u_0 (3), u_1 (3), ..., u_{B-1} (3)]
    known_blocks = ([] if free_root else [0, 1]) + [1 + b for b in driven]
    known = np.array([3 * blk + j for blk in known_blocks for j in range(3)], dtype=np.int64)
    free = np.setdiff1d(np.arange(3 * (n + 1)), known)
    order = np.argsort(np.concatenate([free, known]))
    return Structure(
        anc, strict_up, free, known, order, tuple(driven), free_root, branch.schedule(topo, unrolled), unrolled
    )


def structure(
    topo: Topology, driven: tuple[int, ...] = (), free_root: bool = False, unrolled: bool = False
) -> Structure:
    """Static structure of the null-space basis (built once per topology and driven set);
    ``unrolled``: static indexing as slices, the form for batches (:mod:`neuromotor.physics.static`)."""
    if any(b <= 0 or b >= topo.n_bodies for b in driven):
        raise ValueError(f"driven bodies must be non-root bodies of the tree, got {driven}")
    # Driven joints keep the given order: it is the row order of their constraints in J.
    return topo.derived(_structure, tuple(driven), bool(free_root), bool(unrolled))


def _tree_sum(st: Structure, mat: np.ndarray, *xs):
    """``mat @ x`` over the leading (body) axis with a static 0/1 matrix, for each x: dots
    (faster than unrolled sums, batched or not: XLA:CPU leaves long chains of one-row sums
    unfused), one for all of them unless batched (:func:`static.dot_sums`)."""
    out = static.dot_sums(mat, xs, st.unrolled)
    return out[0] if len(xs) == 1 else out


class Geometry(eqx.Module):
    """Positions relative to the root COM, from the joint levers (so that J S = 0 exactly)."""

    com: Float[Array, "B 3"]  # c_i - c_0
    pivot: Float[Array, "B 3"]  # p_k - c_0: 0 for the root, the joint point for the others
    r0: Float[Array, 3]  # root COM -> root joint origin (the driven root's lever)


def geometry(
    st: Structure, r_parent: Float[Array, "C 3"], r_child: Float[Array, "C 3"], r0: Float[Array, 3]
) -> Geometry:
    """COMs and pivots by chaining levers from the root: c_i = c_parent + r_parent - r_child."""
    zero = jnp.zeros((1, 3), r_parent.dtype)
    step = jnp.concatenate([zero, r_parent - r_child], 0)
    com = _tree_sum(st, st.anc, step)
    pivot = jnp.concatenate([zero, com[1:] + r_child], 0)
    return Geometry(com, pivot, r0)


def apply_basis(
    st: Structure, geo: Geometry, u: Float[Array, " N"], shift: Float[Array, "B 3"] | None = None
) -> Float[Array, "B 6"]:
    """v = S u: per body ``[v_i, omega_i]``; ``shift``: per body a displacement that moves its
    whole subtree (added to v, summed in the same dot)."""
    n = geo.com.shape[0]
    v0, uk = u[:3], u[3:].reshape(n, 3)
    moved = cross(uk, geo.pivot) if shift is None else cross(uk, geo.pivot) - shift
    omega, moved = _tree_sum(st, st.anc, uk, moved)
    vel = v0 + cross(omega, geo.com) - moved
    return jnp.concatenate([vel, omega], -1)


def project_forces(st: Structure, geo: Geometry, f: Float[Array, "B 6"]) -> Float[Array, " N"]:
    """S^T f: the total force, and per column k the moment about p_k of the forces on the
    subtree of k."""
    force, torque = f[:, :3], f[:, 3:]
    sub_force, sub_moment = _tree_sum(st, st.anc.T, force, torque + cross(geo.com, force))
    sub_moment = sub_moment - cross(geo.pivot, sub_force)
    return jnp.concatenate([jnp.sum(force, 0), sub_moment.reshape(-1)])


def project_body_rows(
    st: Structure, geo: Geometry, body: Int[Array, " K"], rows: Float[Array, "K d 6"]
) -> Float[Array, "Kd N"]:
    """S^T f for wrenches on one body each (row (k, j): ``[force, torque]`` on ``body[k]``):
    :func:`project_forces` of each in closed form, the force in the translation columns and, in
    the column of the body and of each of its ancestors l, the wrench's moment about p_l (the
    contact Jacobian in joint space, ``(Jc S)``, without a sum over the tree per row)."""
    force, torque = rows[..., :3], rows[..., 3:]
    reach = jnp.asarray(st.anc, rows.dtype)[body]  # (K, B): anc[b, l] = 1 for l = b and its ancestors
    about = torque + cross(geo.com[body][:, None, :], force)  # (K, d, 3): moment about the root COM
    moment = about[:, :, None, :] - cross(geo.pivot[None, None], force[:, :, None, :])  # (K, d, B, 3)
    k, d = rows.shape[:2]
    moment = (reach[:, None, :, None] * moment).reshape(k, d, -1)
    return jnp.concatenate([force, moment], -1).reshape(k * d, -1)


def inertia_blocks(st: Structure, geo: Geometry, mass: Float[Array, " B"], inertia: Float[Array, "B 3 3"]):
    """S^T M S in closed form from subtree sums: the (B, 3, B, 3) blocks of the rotation columns
    and the first moments ``s_k - m_k p_k`` (B, 3) that couple them with the translation.

    For columns k, l with d the deeper of the two (zero block if neither is an ancestor of the
    other), m_d, s_d = sum m_i c_i and J_d = sum (I_i + m_i (|c_i|^2 1 - c_i c_i^T)) over the
    subtree of d:

        H_kl = J_d + (m_d p_k.p_l - (p_k + p_l).s_d) 1 + s_d p_k^T + p_l s_d^T - m_d p_l p_k^T,
        H_{v0,k} = -[s_k - m_k p_k]x,     H_{v0,v0} = (sum m_i) 1.
    """
    dtype = geo.com.dtype
    eye = jnp.eye(3, dtype=dtype)
    m_sub, s_sub, j_sub = branch.subtree_moments(st.anc.T, mass, inertia, geo.com, st.unrolled)
    # Blocks are built in the (k, i, l, j) layout of the flattened matrix, and "the deeper of
    # k and l" is a pair of static masks rather than a gather: no transpose or gather kernels.
    at_k, at_l = _deep_masks(st, dtype)  # (B, B): d = k, d = l
    md = at_k * m_sub[:, None] + at_l * m_sub[None, :]  # (k, l)
    sd_klx = at_k[..., None] * s_sub[:, None, :] + at_l[..., None] * s_sub[None, :, :]
    sd_kxl = at_k[:, None, :] * s_sub[:, :, None] + at_l[:, None, :] * s_sub.T[None, :, :]
    jd = at_k[:, None, :, None] * j_sub[:, :, None, :] + at_l[:, None, :, None] * jnp.swapaxes(j_sub, 0, 1)[None]
    p = geo.pivot
    pk_dot_pl = p @ p.T
    scalar = md * pk_dot_pl - jnp.sum((p[:, None, :] + p[None, :, :]) * sd_klx, -1)  # (k, l)
    blocks = (
        jd
        + scalar[:, None, :, None] * eye[None, :, None, :]
        + sd_kxl[..., None] * p[:, None, None, :]  # s_d p_k^T
        + p.T[None, :, :, None] * sd_klx[:, None, :, :]  # p_l s_d^T
        - md[:, None, :, None] * p.T[None, :, :, None] * p[:, None, None, :]
    )  # m_d p_l p_k^T
    first = s_sub - m_sub[:, None] * geo.pivot
    return blocks, first


def _deep_masks(st: Structure, dtype):
    """(B, B) masks of the pairs whose deeper body is k (l an ancestor of k, or l = k) and of
    those whose deeper body is l (k a strict ancestor of l); unrelated pairs are in neither."""
    return jnp.asarray(st.anc, dtype), jnp.asarray(st.strict_up.T, dtype)


def _flat(blocks: Float[Array, "K 3 L 3"]) -> Float[Array, "3K 3L"]:
    return blocks.reshape(3 * blocks.shape[0], 3 * blocks.shape[2])


def reduced_inertia(
    st: Structure, geo: Geometry, mass: Float[Array, " B"], inertia: Float[Array, "B 3 3"]
) -> Float[Array, "N N"]:
    """S^T M S over all columns ``[v0, u_0, ..., u_{B-1}]`` (see :func:`inertia_blocks`)."""
    n = geo.com.shape[0]
    blocks, first = inertia_blocks(st, geo, mass, inertia)
    cross_row = -skew(first)  # (B, 3, 3): H_{v0,k}
    eye = jnp.eye(3, dtype=geo.com.dtype)
    top = jnp.concatenate([jnp.sum(mass) * eye, jnp.swapaxes(cross_row, 0, 1).reshape(3, 3 * n)], 1)
    left = jnp.swapaxes(cross_row, 1, 2).reshape(3 * n, 3)
    return jnp.concatenate([top, jnp.concatenate([left, _flat(blocks)], 1)], 0)


def stiffness_blocks(
    st: Structure, g_diag: Float[Array, "B 3 3"], g_up: Float[Array, "C 3 3"], g_down: Float[Array, "C 3 3"]
) -> Float[Array, "B 3 B 3"]:
    """Rotation blocks of S^T G S for an angular block-tree matrix G (diagonal blocks, body <- parent ``g_up`` and
    parent <- body ``g_down``), i.e. the sum of G's blocks over subtree(k) x subtree(l)."""
    dtype = g_diag.dtype
    inner, up, down = _stiff_subtrees(st, g_diag, g_up, g_down)
    at_k, at_l = _deep_masks(st, dtype)
    mask = lambda m: m[:, None, :, None]
    return (
        mask(at_k) * inner[:, :, None, :]
        + mask(at_l) * jnp.swapaxes(inner, 0, 1)[None]
        + mask(jnp.asarray(st.strict_up, dtype)) * up[:, :, None, :]
        + mask(jnp.asarray(st.strict_up.T, dtype)) * jnp.swapaxes(down, 0, 1)[None]
    )


def reduced_stiffness(
    st: Structure, g_diag: Float[Array, "B 3 3"], g_up: Float[Array, "C 3 3"], g_down: Float[Array, "C 3 3"]
) -> Float[Array, "N N"]:
    """S^T G S over all columns (zero in the translation rows and columns)."""
    n = g_diag.shape[0]
    out = jnp.zeros((3 * (n + 1), 3 * (n + 1)), g_diag.dtype)
    rot = _flat(stiffness_blocks(st, g_diag, g_up, g_down))
    return jnp.concatenate([out[:3], jnp.concatenate([out[3:, :3], rot], 1)], 0)


def _take(x, idx: np.ndarray, axis: int = 0):
    """``x`` at static indices along ``axis`` (slices, no gather kernel)."""
    return static.take(x, idx, axis, unrolled=False)


def _free_block(st: Structure, h: Float[Array, "N N"]) -> Float[Array, "F F"]:
    return _take(_take(h, st.free), st.free, axis=1)


def _assemble(st: Structure, u_free, u_known):
    """u from its free and known entries (a concatenation when the known ones come first)."""
    if np.array_equal(st.known, np.arange(st.known.size)):
        return jnp.concatenate([u_known, u_free])
    return jnp.concatenate([u_free, u_known])[st.order]


def _split(st: Structure, h: Float[Array, "N N"], rhs: Float[Array, " N"], u_known):
    """Solve the free part: ``H_FF u_F = rhs_F - H_FK u_K``; returns the full u."""
    f, k = st.free, st.known
    rhs_f = _take(rhs, f)
    if k.size:
        rhs_f = rhs_f - _take(_take(h, f), k, axis=1) @ u_known
    u_free = jnp.linalg.solve(_free_block(st, h), rhs_f)
    return _assemble(st, u_free, u_known)


def known_velocities(st: Structure, r0: Float[Array, 3], b: Float[Array, " nc"]) -> Float[Array, " K"]:
    """Known entries of u from the driven root's and driven joints' rows of b (``J v = b``)."""
    parts = []
    m0 = 0 if st.free_root else 6
    if not st.free_root:
        w0 = b[3:6]
        parts += [b[0:3] - cross(w0, r0), w0]  # origin velocity v0 + w0 x r0 = b[0:3]
    n = st.anc.shape[0]
    if st.driven:
        parts.append(b[m0 + 3 * (n - 1) :])
    return jnp.concatenate(parts) if parts else jnp.zeros((0,), b.dtype)


def multipliers(st: Structure, geo: Geometry, f: Float[Array, "B 6"]) -> Float[Array, " nc"]:
    """lam from ``J^T lam = f`` (f = A v - r), in the row order of ``system.full_constraints``.

    Ball joint k: minus the total force on its subtree. Root rows: the total force, and the
    total moment about the root COM less the lever's share. Driven joint k: the moment about
    p_k of the forces on its subtree (its column of S^T f)."""
    n = geo.com.shape[0]
    proj = project_forces(st, geo, f)
    ball = -_tree_sum(st, st.anc.T, f[:, :3])[1:]
    parts = []
    if not st.free_root:
        total = proj[:3]
        parts += [total, proj[3:6] - cross(geo.r0, total)]
    parts.append(ball.reshape(-1))
    if st.driven:
        parts.append(proj[3:].reshape(n, 3)[np.array(st.driven)].reshape(-1))
    return jnp.concatenate(parts)


def solve_kkt(
    st: Structure,
    geo: Geometry,
    mass: Float[Array, " B"],
    inertia_world: Float[Array, "B 3 3"],
    g_diag,
    g_up,
    g_down,
    r: Float[Array, "B 6"],
    b: Float[Array, " nc"],
) -> Float[Array, "B 6"]:
    """v+ of Eq. 2 with ``A = M - G`` (G = h D + h^2 K, angular blocks on the tree)."""
    rhs, u_known = project_forces(st, geo, r), known_velocities(st, geo.r0, b)
    if st.free_root or st.driven:
        h = reduced_inertia(st, geo, mass, inertia_world) - reduced_stiffness(st, g_diag, g_up, g_down)
        return apply_basis(st, geo, _split(st, h, rhs, u_known))
    # Driven root, every joint free (the common case): only the joints' blocks are assembled,
    # and the known root motion enters through its two block columns.
    blocks, first = inertia_blocks(st, geo, mass, inertia_world)
    blocks = blocks - stiffness_blocks(st, g_diag, g_up, g_down)
    v0, w0 = u_known[:3], u_known[3:6]
    known = jnp.einsum("kij,j->ki", blocks[1:, :, 0], w0) + cross(first[1:], v0)  # H_{k,u0} w0 + H_{k,v0} v0
    u_free = jnp.linalg.solve(_flat(blocks[1:, :, 1:]), rhs[6:] - known.reshape(-1))
    return apply_basis(st, geo, jnp.concatenate([u_known, u_free]))


class DenseFactor(eqx.Module):
    """A square matrix and the pivoted LU of its stop-gradient (for :func:`lu_solve`)."""

    a: Float[Array, "n n"]
    lu: Float[Array, "n n"]
    perm: Int[Array, " n"]  # rows: P a = L U with (P x)_i = x[perm_i]


def lu_factor(a: Float[Array, "n n"]) -> DenseFactor:
    lu, _, perm = jax.lax.linalg.lu(jax.lax.stop_gradient(a))
    return DenseFactor(a, lu, perm)


def _lu_apply(f: DenseFactor, y, transpose: bool):
    tri = jax.lax.linalg.triangular_solve
    if not transpose:  # a x = y:  L U x = P y
        z = tri(f.lu, y[f.perm][:, None], left_side=True, lower=True, unit_diagonal=True)
        return tri(f.lu, z, left_side=True, lower=False)[:, 0]
    # a^T x = y:  U^T L^T P x = y
    z = tri(f.lu, y[:, None], left_side=True, lower=False, transpose_a=True)
    z = tri(f.lu, z, left_side=True, lower=True, unit_diagonal=True, transpose_a=True)[:, 0]
    return jnp.zeros_like(z).at[f.perm].set(z)


def lu_solve(f: DenseFactor, b: Float[Array, " n"]) -> Float[Array, " n"]:
    """a^-1 b from the factor, with derivatives by implicit differentiation (as
    ``jnp.linalg.solve``): one factorization serves every right-hand side of a step, where each
    ``jnp.linalg.solve`` call would factor (and convert its pivots) again."""
    return jax.lax.custom_linear_solve(
        lambda x: f.a @ x,
        b,
        lambda _, y: _lu_apply(f, y, False),
        transpose_solve=lambda _, y: _lu_apply(f, y, True),
    )


class Dense(eqx.Module):
    """Eq. 2 projected on the free columns (a floating root or driven joints): the whole H (its
    known columns move the right-hand side) and the LU of its free block."""

    h: Float[Array, "N N"]
    factor: DenseFactor


def reduce_dense(st: Structure, geo: Geometry, mass, inertia_world, g_diag, g_up, g_down) -> Dense:
    h = reduced_inertia(st, geo, mass, inertia_world) - reduced_stiffness(st, g_diag, g_up, g_down)
    return Dense(h, lu_factor(_free_block(st, h)))


def solve_dense(st: Structure, geo: Geometry, den: Dense, r: Float[Array, "B 6"], b: Float[Array, " nc"]):
    """v+ of Eq. 2 from the factored :class:`Dense` (any number of right-hand sides reuse it)."""
    rhs, u_known = project_forces(st, geo, r), known_velocities(st, geo.r0, b)
    f, k = st.free, st.known
    rhs_f = _take(rhs, f)
    if k.size:
        rhs_f = rhs_f - _take(_take(den.h, f), k, axis=1) @ u_known
    return apply_basis(st, geo, _assemble(st, lu_solve(den.factor, rhs_f), u_known))


class Reduced(eqx.Module):
    """Eq. 2 projected on the joints (driven root, every joint free): H = S^T A S factored
    along the tree (:mod:`.branch`), and the root's two block columns of H, through which the
    known root motion enters."""

    paths: branch.Paths
    factor: branch.Factor  # of the paths without their tangents (see branch.linear_solve)
    root_rot: Float[Array, "B 3 3"]  # H_{k, u0}
    first: Float[Array, "B 3"]  # H_{k, v0} v0 = first_k x v0


def reduce_tree(st: Structure, geo: Geometry, mass, inertia_world, g_diag, g_up, g_down) -> Reduced:
    """:class:`Reduced` at one state, ``A = M - G``."""
    sch = st.tree
    c_blocks, first = _moments(st, geo, mass, inertia_world)
    inner, up, down = _stiff_subtrees(st, g_diag, g_up, g_down)
    paths = branch.paths_of(sch, c_blocks, first, geo.pivot, (inner, up, down))
    return Reduced(paths, branch.factor(sch, jax.lax.stop_gradient(paths)), c_blocks - inner - up, first)


def solve_reduced(
    st: Structure, geo: Geometry, red: Reduced, r: Float[Array, "B 6"], b: Float[Array, " nc"]
) -> Float[Array, "B 6"]:
    """v+ of Eq. 2 from the factored :class:`Reduced` (any number of right-hand sides reuse it)."""
    rhs, u_known = project_forces(st, geo, r), known_velocities(st, geo.r0, b)
    v0, w0 = u_known[:3], u_known[3:6]
    known = mv(red.root_rot, w0) + cross(red.first, v0)
    u = branch.linear_solve(st.tree, red.paths, red.factor, rhs[3:].reshape(-1, 3) - known)
    return apply_basis(st, geo, jnp.concatenate([u_known, u[1:].reshape(-1)]))


def _moments(st: Structure, geo: Geometry, mass, inertia_world):
    """``(C_k, a_k)`` of every body (:func:`branch.pivot_blocks`)."""
    m_sub, s_sub, j_sub = branch.subtree_moments(st.anc.T, mass, inertia_world, geo.com, st.unrolled)
    return branch.pivot_blocks(m_sub, s_sub, j_sub, geo.pivot)


def _stiff_subtrees(st: Structure, g_diag, g_up, g_down):
    """G's blocks summed within each subtree, and its body/parent couplings (root rows zero)."""
    zero = jnp.zeros((1, 3, 3), g_diag.dtype)
    up, down = jnp.concatenate([zero, g_up], 0), jnp.concatenate([zero, g_down], 0)
    strict_desc = st.anc.T - np.eye(st.anc.shape[0])
    return static.dot_sum((st.anc.T, strict_desc), (g_diag, up + down), st.unrolled), up, down


def particular_correction(st: Structure, geo: Geometry, c: Float[Array, " nc"]) -> Float[Array, "B 6"]:
    """A dx with ``J dx = -C`` (not of least norm): every subtree moves by its joint's gap, the
    root and the driven joints turn (and the root shifts) by their errors."""
    n = geo.com.shape[0]
    m0 = 0 if st.free_root else 6
    u = jnp.zeros(3 * (n + 1), c.dtype)
    if not st.free_root:
        d_theta0 = -c[3:6]
        u = u.at[3:6].set(d_theta0).at[0:3].set(-c[0:3] - cross(d_theta0, geo.r0))
    if st.driven:
        cols = np.array([3 * (1 + b) + j for b in st.driven for j in range(3)])
        u = u.at[cols].set(-c[m0 + 3 * (n - 1) :])
    gaps = jnp.concatenate([jnp.zeros((1, 3), c.dtype), c[m0 : m0 + 3 * (n - 1)].reshape(n - 1, 3)], 0)
    return apply_basis(st, geo, u, shift=gaps)


class SpdFactor(eqx.Module):
    """A symmetric positive definite matrix and its Cholesky factor (for :func:`spd_solve`)."""

    a: Float[Array, "n n"]
    factor: tuple  # jax.scipy.linalg.cho_factor of stop_gradient(a)


def spd_factor(a: Float[Array, "n n"]) -> SpdFactor:
    return SpdFactor(a, jax.scipy.linalg.cho_factor(jax.lax.stop_gradient(a)))


def spd_solve(a: Float[Array, "n n"] | SpdFactor, b: Float[Array, " n"]) -> Float[Array, " n"]:
    """a^-1 b for symmetric positive definite a by Cholesky, with derivatives by implicit
    differentiation (``lax.custom_linear_solve``): a tangent costs two triangular solves with
    the same factor, not the derivative of the factorization (as for ``jnp.linalg.solve``)."""
    f = a if isinstance(a, SpdFactor) else spd_factor(a)
    return jax.lax.custom_linear_solve(
        lambda x: f.a @ x, b, lambda _, y: jax.scipy.linalg.cho_solve(f.factor, y), symmetric=True
    )


class Metric(eqx.Module):
    """The joint-space inertia ``S^T M S`` of post-stabilization at one configuration, factored:
    along the tree (``paths``, ``factor``) or by a dense Cholesky (``dense``)."""

    paths: branch.Paths | None = None
    factor: branch.Factor | None = None
    dense: SpdFactor | None = None


def projection_metric(st: Structure, geo: Geometry, mass, inertia_world, tree: bool = False) -> Metric:
    """:class:`Metric` at one configuration: along the tree (:mod:`.branch`) when ``tree`` and
    the structure allows, else the free block by a dense Cholesky."""
    if tree and st.by_tree:
        c_blocks, first = _moments(st, geo, mass, inertia_world)
        paths = branch.paths_of(st.tree, c_blocks, first, geo.pivot)
        return Metric(paths, branch.factor(st.tree, jax.lax.stop_gradient(paths)))
    if st.free_root or st.driven:
        h_free = _free_block(st, reduced_inertia(st, geo, mass, inertia_world))
    else:  # driven root, free joints: the joints' blocks only
        h_free = _flat(inertia_blocks(st, geo, mass, inertia_world)[0][1:, :, 1:])
    return Metric(dense=spd_factor(h_free))


def projection_step(st: Structure, geo: Geometry, mass, inertia_world, c: Float[Array, " nc"], tree: bool = False):
    """The projection of post-stabilization: ``dx`` (B, 6) with ``J dx = -C`` of least M-norm,
    ``dx = dx_p + S w`` with ``(S^T M S) w = -S^T M dx_p`` (:func:`projection_metric`)."""
    x_p = particular_correction(st, geo, c)
    mx = jnp.concatenate([mass[:, None] * x_p[:, :3], mv(inertia_world, x_p[:, 3:])], -1)
    rhs = -project_forces(st, geo, mx)
    metric = projection_metric(st, geo, mass, inertia_world, tree)
    if metric.dense is None:
        assert metric.paths is not None and metric.factor is not None  # the tree form
        w = branch.linear_solve(st.tree, metric.paths, metric.factor, rhs[3:].reshape(-1, 3), symmetric=True)
        u = jnp.concatenate([jnp.zeros(6, c.dtype), w[1:].reshape(-1)])
        return x_p + apply_basis(st, geo, u)
    w = spd_solve(metric.dense, _take(rhs, st.free))
    u = _assemble(st, w, jnp.zeros(st.known.size, c.dtype))
    return x_p + apply_basis(st, geo, u)


def kkt_residual(
    st: Structure,
    geo: Geometry,
    r_parent,
    r_child,
    f: Float[Array, "B 6"],
    v: Float[Array, "B 6"],
    lam: Float[Array, " nc"],
    b: Float[Array, " nc"],
    parent: np.ndarray,
):
    """Both block rows of the residual of Eq. 2, ``(A v - r) - J^T lam`` and ``J v - b``, with
    J applied joint by joint (the same rows as ``system.full_constraints``)."""
    n = geo.com.shape[0]
    m0 = 0 if st.free_root else 6
    child = np.arange(1, n)
    lam_ball = lam[m0 : m0 + 3 * (n - 1)].reshape(n - 1, 3)
    one_hot = lambda idx: jnp.asarray(np.eye(n)[idx], f.dtype)  # (rows, B): sums without scatter
    put = lambda idx, x: jnp.tensordot(one_hot(idx), x, axes=([0], [0]))
    jt = put(parent, jnp.concatenate([lam_ball, cross(r_parent, lam_ball)], -1)) - put(
        child, jnp.concatenate([lam_ball, cross(r_child, lam_ball)], -1)
    )
    at = lambda x, body: static.take(x, body, unrolled=st.unrolled)
    point = lambda body, lever: at(v[:, :3], body) + cross(at(v[:, 3:], body), lever)
    rows = [(point(parent, r_parent) - point(child, r_child)).reshape(-1)]
    if not st.free_root:
        lam_lin, lam_ang = lam[0:3], lam[3:6]
        jt = jt.at[0].add(jnp.concatenate([lam_lin, cross(geo.r0, lam_lin) + lam_ang]))
        rows.insert(0, jnp.concatenate([v[0, :3] + cross(v[0, 3:], geo.r0), v[0, 3:]]))
    if st.driven:
        drv = np.array(st.driven)
        par = np.array([parent[d - 1] for d in st.driven])
        mu = lam[m0 + 3 * (n - 1) :].reshape(-1, 3)
        jt = (
            jt
            + put(drv, jnp.concatenate([jnp.zeros_like(mu), mu], -1))
            - put(par, jnp.concatenate([jnp.zeros_like(mu), mu], -1))
        )
        rows.append((v[drv, 3:] - v[par, 3:]).reshape(-1))
    return (f - jt).reshape(-1), jnp.concatenate(rows) - b


# ---------------------------------------------------------------- the solver strategy


class NullSpaceKKT(eqx.Module):
    """Eq. 2 at one state in null-space form: the basis geometry, M and G = h D + h^2 K."""

    st: Structure = eqx.field(static=True)
    topo: Topology = eqx.field(static=True)
    geo: Geometry
    mass: Float[Array, " B"]
    inertia: Float[Array, "B 3 3"]  # world inertias
    g_diag: Float[Array, "B 3 3"]
    g_up: Float[Array, "C 3 3"]
    g_down: Float[Array, "C 3 3"]
    r_parent: Float[Array, "C 3"]  # joint levers (the rows of J)
    r_child: Float[Array, "C 3"]
    reduced: Reduced | None  # H factored along the tree (BranchSolver, where Structure.by_tree)
    dense: Dense | None = None  # else its free block by one LU per step

    def a_times(self, v: Float[Array, "B 6"]) -> Float[Array, "B 6"]:
        """A v = M v - G v."""
        mv_ = jnp.concatenate([self.mass[:, None] * v[:, :3], jnp.einsum("bij,bj->bi", self.inertia, v[:, 3:])], -1)
        gv = tree_matvec(self.topo, self.g_diag, self.g_up, self.g_down, v[:, 3:])
        return mv_ - jnp.concatenate([jnp.zeros_like(gv), gv], -1)


class NullSpaceSolver(KKTSolver):
    """Eq. 2 by the null-space method (see the module docstring): H and the post-stabilization
    metric factored along the body tree, static indexing by gathers (fewest kernels:
    the fastest single trajectory on a CPU); a dense LU where the root floats or joints are
    driven."""

    tree_blocks = True
    unrolled = False  # static indexing as gathers (one trajectory; physics/static.py)

    def assemble(self, model, cfg, rot, inertia, stiff, h):
        st = structure(model.topology, cfg.driven, cfg.free_root, self.unrolled)
        r_par, r_chi = joint_levers(model, rot)
        geo = geometry(st, r_par, r_chi, root_lever(model, rot))
        g = stiff.g_blocks(h)
        if st.by_tree:
            red, den = reduce_tree(st, geo, model.mass, inertia, *g), None
        else:
            red, den = None, reduce_dense(st, geo, model.mass, inertia, *g)
        return NullSpaceKKT(st, model.topology, geo, model.mass, inertia, *g, r_par, r_chi, red, den)

    def solve(self, system, r, b):
        s = system
        if s.reduced is not None:
            return solve_reduced(s.st, s.geo, s.reduced, r, b), None
        if s.dense is not None:
            return solve_dense(s.st, s.geo, s.dense, r, b), None
        return solve_kkt(s.st, s.geo, s.mass, s.inertia, s.g_diag, s.g_up, s.g_down, r, b), None

    def multipliers(self, system, r, b, v, aux):
        # A v+ - r = J^T lam gives the multipliers; the residual of the whole of Eq. 2 checks the solve.
        s = system
        f = s.a_times(v) - r
        lam = multipliers(s.st, s.geo, f)
        res = jnp.concatenate(kkt_residual(s.st, s.geo, s.r_parent, s.r_child, f, v, lam, b, s.topo.parent))
        rhs_norm = jnp.sqrt(jnp.sum(r**2) + jnp.sum(b**2))
        return lam, relative_residual(res, rhs_norm)

    def projection_step(self, model, cfg, rot, c):
        st = structure(model.topology, cfg.driven, cfg.free_root, self.unrolled)
        geo = geometry(st, *joint_levers(model, rot), root_lever(model, rot))
        return projection_step(st, geo, model.mass, world_inertia(model, rot), c, tree=True)

    def contact_responses(self, system, n_bodies, body, rows, b):
        # In joint space: G = Jc S row by row in closed form, u = H^-1 G^T (the known entries of u
        # are 0 for b = 0), W = G u; the rows never pass through the basis (S^T, S) one by one.
        s = system
        g = project_body_rows(s.st, s.geo, body, rows)  # (R, N)
        u = jax.vmap(lambda rhs: _unit_solve(s, rhs))(g).T  # (N, R)
        return ContactResponses(u, g @ u)

    def lift(self, system, x):
        return jax.vmap(lambda u: apply_basis(system.st, system.geo, u).reshape(-1), in_axes=1, out_axes=1)(x)


def _unit_solve(s: NullSpaceKKT, rhs: Float[Array, " N"]) -> Float[Array, " N"]:
    """u of Eq. 2 projected for the projected right-hand side ``rhs`` with b = 0 (the known entries of
    u are zero): the solve of :func:`solve_reduced` or :func:`solve_dense` before the basis."""
    st = s.st
    if s.reduced is not None:
        red = s.reduced
        u = branch.linear_solve(st.tree, red.paths, red.factor, rhs[3:].reshape(-1, 3))
        return jnp.concatenate([jnp.zeros(6, rhs.dtype), u[1:].reshape(-1)])
    assert s.dense is not None
    return _assemble(st, lu_solve(s.dense.factor, _take(rhs, st.free)), jnp.zeros(st.known.size, rhs.dtype))


class BranchSolver(NullSpaceSolver):
    """The same equations as :class:`NullSpaceSolver` with the static indexing of the tree
    factorization written as slices (:mod:`neuromotor.physics.static`): under ``vmap`` they fuse
    into loops over the batch where gathers would run element by element (the solver of sweeps
    and batches). Falls back to the dense LU where the root floats or joints are driven."""

    unrolled = True  # static indexing as slices: fused loops over the batch
