"""Linear-time solve of the KKT systems of Eq. 2 and of post-stabilization on the body tree.

Both systems have the form

    [ A   -J^T ] [ v   ]   [ r ]
    [ J    E   ] [ lam ] = [ s ]

with A (6B x 6B) nonzero only in the diagonal 6x6 blocks and in the blocks that couple a body
with its parent (A = M - h D - h^2 K: the feedback torque of a joint depends on its two bodies
only), and J made of rows that each touch one body and its parent (a ball joint, a driven
joint) or the root alone (the driven root). E is zero except on padding rows (identity, with
zero right-hand side, so their multiplier is zero).

Grouping each body with the constraint rows of the joint that attaches it to its parent gives a
"super node" of size 6 + m whose couplings form the body tree itself. Eliminating leaves first
(Baraff 1996, "Linear-time dynamics using Lagrange multipliers") creates no fill-in: every
eliminated node only updates the 6x6 diagonal block and the right-hand side of its parent.
Bodies of equal depth are independent and are eliminated together (one batched operation per
tree level), then the root is solved and the other bodies follow by back substitution, root to
leaves. Cost: O(B) small dense solves instead of one (6B + nc)^3 factorization.

The small solves use Gauss-Jordan elimination without pivoting, written as elementwise array
operations so they vectorize across a batch of trajectories (``vmap``) instead of calling
LAPACK once per tiny matrix. Pivots are safe in natural order: the first 6 pivots are those of A
(symmetric part positive definite: mass plus positive damping and stiffness), the last m are
those of E + J A^-1 J^T (positive definite for full-rank J).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor.model.topology import Topology
from neuromotor.physics.solvers.base import KKTSolver, relative_residual
from neuromotor.physics.system import embed_angular, joint_jacobian_blocks, mass_blocks, root_lever, world_inertia
from neuromotor.rotations import skew


class TreeKKT(eqx.Module):
    """Blocks of the system above; row ``c`` of the per-joint arrays belongs to body ``c + 1``."""

    a_diag: Float[Array, "B 6 6"]
    a_up: Float[Array, "C 6 6"]  # A[body, its parent]
    a_down: Float[Array, "C 6 6"]  # A[parent, body]
    j_root: Float[Array, "m0 6"]  # rows owned by the root (root columns only)
    j_own: Float[Array, "C m 6"]  # rows owned by a body: its own columns
    j_par: Float[Array, "C m 6"]  # the same rows: the parent's columns
    pad: Float[Array, "C m"]  # 1 on padding rows (E), else 0


def _selectors(topo: Topology) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-hot forms of the elimination schedule ``topo.levels``: (L, W, B+1) node and parent
    bodies, (L, W, C+1) rows. Gathers and scatter-adds by these become small matrix products,
    which stay fast under ``vmap`` (a batched scatter is a slow serial loop on CPU)."""
    rows, parents = topo.levels
    n = topo.n_bodies
    return np.eye(n + 1)[rows + 1], np.eye(n + 1)[parents], np.eye(n)[rows]


def gauss_jordan(s: Float[Array, "... n n"], b: Float[Array, "... n k"]) -> Float[Array, "... n k"]:
    """s^-1 b by Gauss-Jordan elimination without pivoting (see the module docstring)."""
    n = s.shape[-1]
    aug = jnp.concatenate([s, b], -1)
    eye = jnp.eye(n, dtype=s.dtype)
    for i in range(n):
        row = aug[..., i, :] / aug[..., i, i, None]
        # Row i becomes the normalized pivot row; every other row loses its column-i entry.
        aug = aug - (aug[..., :, i] - eye[:, i])[..., :, None] * row[..., None, :]
    return aug[..., :, n:]


def _node_matrix(a, j_own, pad):
    """Super-node block ``[[A_bb, -J_own^T], [J_own, E]]``."""
    top = jnp.concatenate([a, -jnp.swapaxes(j_own, -1, -2)], -1)
    bottom = jnp.concatenate([j_own, _diag(pad)], -1)
    return jnp.concatenate([top, bottom], -2)


def _diag(pad):
    return pad[..., :, None] * jnp.eye(pad.shape[-1], dtype=pad.dtype)


def solve(sys: TreeKKT, topo: Topology, r: Float[Array, "B 6"], s_root: Float[Array, " m0"], s: Float[Array, "C m"]):
    """Solve the tree KKT system; returns ``v (B,6)``, ``lam_root (m0,)``, ``lam (C,m)``."""
    n = topo.n_bodies
    rows, parents = topo.levels
    nj, m = sys.j_own.shape[0], sys.j_own.shape[1]
    dtype = r.dtype
    # Ghost node (body n, joint row nj): identity blocks, no coupling, zero rhs.
    ghost = lambda x, fill: jnp.concatenate([x, fill[None]], 0)
    a_diag = ghost(sys.a_diag, jnp.eye(6, dtype=dtype))
    r = ghost(r, jnp.zeros(6, dtype))
    a_up = ghost(sys.a_up, jnp.zeros((6, 6), dtype))
    a_down = ghost(sys.a_down, jnp.zeros((6, 6), dtype))
    j_own = ghost(sys.j_own, jnp.zeros((m, 6), dtype))
    j_par = ghost(sys.j_par, jnp.zeros((m, 6), dtype))
    pad = ghost(sys.pad, jnp.ones((m,), dtype))
    s = ghost(s, jnp.zeros((m,), dtype))

    # Everything but the carried diagonal blocks and rhs is gathered per level once, outside
    # the loop (fewer, wider kernels per step).
    static = (
        j_own[rows],
        pad[rows],
        s[rows],
        jnp.concatenate([a_up[rows], j_par[rows]], -2),  # (L, W, 6+m, 6)
        jnp.concatenate([a_down[rows], -jnp.swapaxes(j_par[rows], -1, -2)], -1),
    )  # (L, W, 6, 6+m)

    sel_node, sel_par, sel_row = (jnp.asarray(x, dtype) for x in topo.derived(_selectors))
    take = lambda sel, x: jnp.einsum("wb,b...->w...", sel, x)  # x[index] as a product
    put = lambda sel, x: jnp.einsum("wb,w...->b...", sel, x)  # zeros.at[index].add(x)

    def eliminate(carry, level):  # leaves first
        a_diag, r = carry
        s_node, s_par, (jo, pd, sw, up, down) = level
        node = _node_matrix(take(s_node, a_diag), jo, pd)
        rhs = jnp.concatenate([take(s_node, r), sw], -1)[..., None]
        sol = gauss_jordan(node, jnp.concatenate([up, rhs], -1))
        w, y = sol[..., :6], sol[..., 6]
        # Schur complement onto the parent: only its 6x6 block and its rhs change.
        a_diag = a_diag - put(s_par, down @ w)
        r = r - put(s_par, jnp.einsum("kij,kj->ki", down, y))
        return (a_diag, r), (w, y)

    (a_diag, r), (w, y) = jax.lax.scan(eliminate, (a_diag, r), (sel_node, sel_par, static))
    m0 = sys.j_root.shape[0]
    root = _node_matrix(a_diag[0], sys.j_root, jnp.zeros((m0,), dtype))
    x0 = gauss_jordan(root, jnp.concatenate([r[0], s_root])[:, None])[:, 0]
    v = jnp.zeros((n + 1, 6), dtype).at[0].set(x0[:6])
    lam = jnp.zeros((nj + 1, m), dtype)

    def substitute(carry, level):  # root to leaves; every body and row is written once
        v, lam = carry
        s_node, s_par, s_row, w, y = level
        x = y - jnp.einsum("kij,kj->ki", w, take(s_par, v))
        return (v + put(s_node, x[..., :6]), lam + put(s_row, x[..., 6:])), None

    (v, lam), _ = jax.lax.scan(substitute, (v, lam), (sel_node, sel_par, sel_row, w, y), reverse=True)
    return v[:n], x0[6:], lam[:nj]


def matvec(sys: TreeKKT, topo: Topology, v, lam_root, lam):
    """The system's left-hand side applied to ``(v, lam_root, lam)`` (for residuals)."""
    child, parent = topo.child, topo.parent
    # (C, B) one-hot: no scatter under vmap; in v's precision
    sel_c, sel_p = jnp.asarray(topo.sel_child, v.dtype), jnp.asarray(topo.sel_parent, v.dtype)
    put = lambda sel, x: jnp.einsum("cb,c...->b...", sel, x)
    mv = lambda a, x: jnp.einsum("...ij,...j->...i", a, x)
    mtv = lambda a, x: jnp.einsum("...ji,...j->...i", a, x)
    top = mv(sys.a_diag, v)
    top = top + put(sel_c, mv(sys.a_up, v[parent]) - mtv(sys.j_own, lam))
    top = top + put(sel_p, mv(sys.a_down, v[child]) - mtv(sys.j_par, lam))
    top = top.at[0].add(-mtv(sys.j_root, lam_root))
    bottom = mv(sys.j_own, v[child]) + mv(sys.j_par, v[parent]) + sys.pad * lam
    return top, mv(sys.j_root, v[0]), bottom


# ---------------------------------------------------------------- the solver strategy


def tree_constraints(model, driven: tuple[int, ...], rot, free_root: bool):
    """Rows of ``system.full_constraints`` grouped by owner: the root's rows and, per
    non-root body, its ball joint's 3 rows followed (when any joint is driven) by 3 driven-joint
    rows or 3 padding rows. Returns ``(j_root, j_own, j_par, pad)``."""
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


def split_rows(n_bodies: int, driven, values: Float[Array, " nc"], free_root: bool):
    """A vector over the rows of ``system.full_constraints`` in tree layout (root, (C, m))."""
    m0 = 0 if free_root else 6
    nj = n_bodies - 1
    root, joints = values[:m0], values[m0 : m0 + 3 * nj].reshape(nj, 3)
    if driven:
        extra = jnp.zeros((nj, 3), values.dtype).at[np.array(driven) - 1].set(values[m0 + 3 * nj :].reshape(-1, 3))
        joints = jnp.concatenate([joints, extra], 1)
    return root, joints


def join_rows(driven, root, joints):
    """Inverse of :func:`split_rows` (padding rows dropped)."""
    out = [root, joints[:, :3].reshape(-1)]
    if driven:
        out.append(joints[np.array(driven) - 1, 3:].reshape(-1))
    return jnp.concatenate(out)


class TreeSystem(eqx.Module):
    """Eq. 2 at one state in tree layout, with what maps its rows to ``full_constraints``."""

    kkt: TreeKKT
    topo: Topology = eqx.field(static=True)
    driven: tuple[int, ...] = eqx.field(static=True)
    free_root: bool = eqx.field(static=True)

    def split(self, values):
        return split_rows(self.topo.n_bodies, self.driven, values, self.free_root)


class TreeSolver(KKTSolver):
    """Eq. 2 and each Newton step of post-stabilization by block elimination along the tree."""

    tree_blocks = True

    def assemble(self, model, cfg, rot, inertia, stiff, h):
        g_diag, g_up, g_down = stiff.g_blocks(h)
        kkt = TreeKKT(
            mass_blocks(model, inertia) - embed_angular(g_diag),
            -embed_angular(g_up),
            -embed_angular(g_down),
            *tree_constraints(model, cfg.driven, rot, cfg.free_root),
        )
        return TreeSystem(kkt, model.topology, cfg.driven, cfg.free_root)

    def solve(self, system, r, b):
        v, lam_root, lam = solve(system.kkt, system.topo, r, *system.split(b))
        return v, (lam_root, lam)

    def multipliers(self, system, r, b, v, aux):
        s_root, s_joint = system.split(b)
        top, bot_root, bot = matvec(system.kkt, system.topo, v, *aux)
        res = jnp.concatenate([(top - r).reshape(-1), bot_root - s_root, (bot - s_joint).reshape(-1)])
        rhs_norm = jnp.sqrt(jnp.sum(r**2) + jnp.sum(s_root**2) + jnp.sum(s_joint**2))
        return join_rows(system.driven, *aux), relative_residual(res, rhs_norm)

    def projection_step(self, model, cfg, rot, c):
        # [M -J^T; J 0][dx; mu] = [0; -C]: the same projection, dx = M^-1 J^T mu, J dx = -C.
        zero = jnp.zeros((model.n_bodies - 1, 6, 6), rot.dtype)
        kkt = TreeKKT(
            mass_blocks(model, world_inertia(model, rot)),
            zero,
            zero,
            *tree_constraints(model, cfg.driven, rot, cfg.free_root),
        )
        c_root, c_joint = split_rows(model.n_bodies, cfg.driven, c, cfg.free_root)
        delta, _, _ = solve(kkt, model.topology, jnp.zeros((model.n_bodies, 6), rot.dtype), -c_root, -c_joint)
        return delta
