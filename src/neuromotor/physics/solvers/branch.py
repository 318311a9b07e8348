"""The joint-space matrix of the null-space method, factored along the body tree.

The null-space form of Eq. 2 (:mod:`neuromotor.physics.solvers.nullspace`) solves
``H u = f`` with ``H = S^T A S`` over one rotation column per non-root body. ``H_kl`` is zero
unless k is l or one of its ancestors, or the other way round: H has *branch-induced sparsity*
(Featherstone 2005, "Efficient factorization of the joint-space inertia matrix for branched
kinematic trees"). Eliminating the deepest bodies first then creates no fill-in: eliminating
body k only changes the blocks ``H_ab`` between its ancestors a and b.

So H is never assembled. Each body k keeps its *path*: the blocks of its row and column against
each ancestor l (and itself), ``R[k, l] = H_kl`` and ``U[k, l] = H_lk``, indexed by the depth of l.
The factorization visits the tree level by level, deepest first; all bodies of one depth are
independent and are eliminated together by elementwise 3x3 arithmetic (no LAPACK call, so a
``vmap`` over trajectories vectorizes along the batch instead of looping over small
factorizations). A level's updates of its ancestors' blocks are summed onto the parents once and
carried up (:func:`factor`), so the factorization and the solve take a fixed number of
operations per level, and bodies within a level are kept in depth-first order, so that the
children of a body are adjacent. Pivots need no exchange: the diagonal blocks of ``S^T M S`` are positive definite
and the stiff part is a small perturbation of it (the same assumption as the dense LU's).

Path blocks in closed form (pivot p_l of column l, subtree quantities of k from
:func:`subtree_moments`: mass m_k, first moment s_k, inertia about the root COM J_k):

    M part:  H_kl = C_k + [a_k]x [p_l]x,    C_k = J_k - (p_k . s_k) 1 + s_k p_k^T,  a_k = s_k - m_k p_k
    G part:  (S^T G S)_kl = inner_k + up_k  (l a strict ancestor),  inner_k on the diagonal,
             (S^T G S)_lk = inner_k + down_k

with ``inner_k`` the sum of G's blocks within the subtree of k and up/down its blocks between k
and its parent (G = h D + h^2 K, angular blocks on the tree, as in ``stiffness.StiffBlocks``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor.model.topology import Topology
from neuromotor.physics import static
from neuromotor.rotations import dot, inv3, mm, mv


@dataclasses.dataclass(frozen=True, eq=False)
class Schedule:
    """Static (numpy) layout of the elimination; see :func:`schedule`. Level t holds the bodies
    at depth t (t = 1..t_max, entry t - 1 of the tuples); blocks and vectors are stored per level."""

    t_max: int  # depth of the deepest body
    levels: tuple[np.ndarray, ...]  # bodies at each depth
    anc_at: np.ndarray  # (B, t_max + 1): ancestor of each body at depth t (0 past its own depth)
    valid: np.ndarray  # (B, t_max): slot t - 1 holds a block (t <= depth)
    strict: np.ndarray  # (B, t_max): slot t - 1 is a strict ancestor (t < depth)
    # children[d - 2] = (index, mask), each (w_{d-1}, c): the children of each level-(d-1) body, as
    # positions in level d (sums over them replace a scatter, which is slow batched)
    children: tuple[tuple[np.ndarray, np.ndarray], ...]
    parent_pos: tuple[np.ndarray, ...]  # [d - 2]: (w_d,) position of each level-d body's parent in level d - 1
    order: np.ndarray  # (B,): position of each body in the levels' concatenation (root: 0, masked)
    unrolled: bool  # static indexing as slices (batches) or gathers (one trajectory): physics/static.py


def _children(parent: np.ndarray, level: np.ndarray, level_up: np.ndarray):
    """Per body of ``level_up``, the positions in ``level`` (one deeper) of its children (padded)."""
    owners = [np.flatnonzero(parent[level] == b) for b in level_up]
    width = max(1, max(len(o) for o in owners))
    index, mask = np.zeros((len(level_up), width), np.int64), np.zeros((len(level_up), width))
    for i, o in enumerate(owners):
        index[i, : len(o)], mask[i, : len(o)] = o, 1.0
    return index, mask


def _preorder(parent) -> np.ndarray:
    """Position of each body in a depth-first pre-order walk of the tree (children in index order)."""
    children: list[list[int]] = [[] for _ in parent]
    for b, p in enumerate(parent):
        if p >= 0:
            children[p].append(b)
    pos, stack, i = np.zeros(len(parent), np.int64), [0], 0
    while stack:
        b = stack.pop()
        pos[b], i = i, i + 1
        stack.extend(reversed(children[b]))
    return pos


def _schedule(topo: Topology, unrolled: bool) -> Schedule:
    n, depth = topo.n_bodies, np.asarray(topo.depth)
    t_max = int(depth.max())
    anc_at = np.zeros((n, t_max + 1), np.int64)
    for b in range(n):
        k = b
        while True:
            anc_at[b, depth[k]] = k
            if k == 0:
                break
            k = topo.body_parent[k]
    t = np.arange(1, t_max + 1)
    # Within a level, bodies in depth-first pre-order: the children of any body are then adjacent
    # in the next level (sums over them are sums of adjacent slices).
    pre = _preorder(topo.body_parent)
    levels = tuple(np.array(sorted(np.flatnonzero(depth == d), key=lambda b: pre[b]), np.int64) for d in t)
    pos = np.zeros(n, np.int64)
    for lv in levels:
        pos[lv] = np.arange(len(lv))
    parent = np.asarray(topo.body_parent)
    children = tuple(_children(parent, levels[d - 1], levels[d - 2]) for d in t[1:])
    parent_pos = tuple(pos[parent[levels[d - 1]]] for d in t[1:])
    order = np.zeros(n, np.int64)
    order[np.concatenate(levels)] = np.arange(n - 1)
    strict = (t[None] < depth[:, None]).astype(float)
    return Schedule(
        t_max, levels, anc_at, (t[None] <= depth[:, None]).astype(float), strict, children, parent_pos, order, unrolled
    )


def schedule(topo: Topology, unrolled: bool = True) -> Schedule:
    """The elimination schedule of a tree (built once per topology); ``unrolled``: static
    indexing as slices, the form for batches (:mod:`neuromotor.physics.static`)."""
    return topo.derived(_schedule, bool(unrolled))


def _take(sch: Schedule, x, idx):
    return static.take(x, idx, unrolled=sch.unrolled)


class Paths(eqx.Module):
    """Per tree level (depth d = 1..t_max, entry d - 1), each of its bodies' row and column
    blocks of H against its ancestors: ``row[d - 1][i, t - 1] = H[k, anc_t(k)]`` for t = 1..d
    (the diagonal last) and ``col[d - 1][i, t - 1] = H[anc_t(k), k]`` for the strict ancestors
    (t < d), k the i-th body of the level. Stored level by level, so no slot is padding."""

    row: tuple[Float[Array, "w d 3 3"], ...]
    col: tuple[Float[Array, "w d-1 3 3"], ...]


def _times_skew(a: Float[Array, "... 3"], p: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """[a]x [p]x = p a^T - (a . p) 1."""
    eye = jnp.eye(3, dtype=a.dtype)
    return p[..., :, None] * a[..., None, :] - dot(a, p)[..., None, None] * eye


def _level_paths(sch: Schedule, c_blocks, first, pivot, stiff) -> Paths:
    """:func:`paths_of` level by level: each level's blocks in one loop over its own slots."""
    rows, cols = [], []
    for d, lv in enumerate(sch.levels, 1):
        at = lambda x: _take(sch, x, lv)[:, None]
        row = at(c_blocks) + _times_skew(at(first), _take(sch, pivot, sch.anc_at[lv, 1 : d + 1]))
        col = jnp.swapaxes(row[:, :-1], -1, -2)
        if stiff is not None:
            inner, up, down = map(at, stiff)
            row = row - inner - jnp.asarray(np.arange(d) < d - 1, up.dtype)[:, None, None] * up
            col = col - inner - down
        rows.append(row)
        cols.append(col)
    return Paths(tuple(rows), tuple(cols))


def _body_paths(sch: Schedule, c_blocks, first, pivot, stiff) -> Paths:
    """:func:`paths_of` over every body and slot at once (padded), then split by level: fewer
    kernels, the form for one trajectory."""
    valid = jnp.asarray(sch.valid, pivot.dtype)[..., None, None]
    row = valid * (c_blocks[:, None] + _times_skew(first[:, None], _take(sch, pivot, sch.anc_at[:, 1:])))
    col = jnp.swapaxes(row, -1, -2)
    if stiff is not None:
        inner, up, down = stiff
        strict = jnp.asarray(sch.strict, pivot.dtype)[..., None, None]
        row = row - valid * inner[:, None] - strict * up[:, None]
        col = col - valid * inner[:, None] - strict * down[:, None]
    return of_bodies(sch, row, col)


def paths_of(
    sch: Schedule,
    c_blocks: Float[Array, "B 3 3"],
    first: Float[Array, "B 3"],
    pivot: Float[Array, "B 3"],
    stiff: tuple | None = None,
) -> Paths:
    """Paths of ``S^T M S`` (``H_kl = C_k + [a_k]x [p_l]x``, symmetric), minus those of
    ``S^T G S`` when ``stiff = (inner, up, down)``: G's blocks summed within each subtree and its
    body/parent couplings (zero rows for the root), ``inner_k + up_k`` in the row of a strict
    ancestor, ``inner_k + down_k`` in its column, ``inner_k`` on the diagonal (module docstring).
    Built level by level in the batched form (no padded slot is computed or moved), over all
    bodies at once otherwise."""
    return (_level_paths if sch.unrolled else _body_paths)(sch, c_blocks, first, pivot, stiff)


def of_bodies(sch: Schedule, row: Float[Array, "B T 3 3"], col: Float[Array, "B T 3 3"]) -> Paths:
    """Paths from per-body arrays, slot ``t - 1`` for the ancestor at depth t (one take of each
    into level order, then slices)."""
    cut = lambda x, extra: tuple(a[:, : d + extra] for d, a in enumerate(_by_level(sch, x), 1))
    return Paths(cut(row, 0), cut(col, -1))


class Factor(eqx.Module):
    """The factored H, per level (deepest first): inverse pivots, ``X = P^-1 R`` against the
    strict ancestors, and the column blocks used by the forward substitution."""

    pinv: tuple[Float[Array, "w 3 3"], ...]
    x: tuple[Float[Array, "w d 3 3"], ...]
    col: tuple[Float[Array, "w d 3 3"], ...]


def _by_level(sch: Schedule, x) -> list:
    """Per level (depth 1, 2, ...), the rows of x (per body) of that level's bodies: one take into
    level order, then slices."""
    flat = _take(sch, x, np.concatenate(sch.levels))
    ends = np.cumsum([len(lv) for lv in sch.levels])
    return [flat[e - len(lv) : e] for e, lv in zip(ends, sch.levels)]


def _to_parents(sch: Schedule, d: int, x):
    """Sums of x (rows: the bodies at depth d) over the children of each body at depth d - 1."""
    return static.gather_sum(x, *sch.children[d - 2], unrolled=sch.unrolled)


def factor(sch: Schedule, paths: Paths) -> Factor:
    """Block LDU of H without fill-in, deepest level first (module docstring).

    Eliminating body k updates ``H_ab -= H_ak P_k^-1 H_kb`` for every pair of its ancestors a, b.
    The updates of a level are summed onto the parents once; the part for the parent's own row
    and column is applied there and the rest (pairs of strict ancestors of the parent) is carried
    up with the parent's own updates, so a level costs one sum over children, not one per
    ancestor level."""
    rows, cols = list(paths.row), list(paths.col)
    pinv, xs, used = [], [], []
    carry = None  # updates (w_d, d - 1, d - 1, 3, 3) for the pairs of strict ancestors of level d
    for d in range(sch.t_max, 0, -1):
        rk, ck = rows[d - 1], cols[d - 1]
        p_inv = inv3(rk[:, d - 1])
        x = mm(p_inv[:, None], rk[:, : d - 1])
        pinv.append(p_inv)
        xs.append(x)
        used.append(ck)
        if d == 1:
            break
        # prod[k, a, b] = U[k, a] X[k, b] for ancestor slots a, b of k
        prod = mm(ck[:, :, None], x[:, None, :])
        acc = _to_parents(sch, d, prod if carry is None else prod + carry)  # (w_{d-1}, d-1, d-1, 3, 3)
        own = d - 2  # the parent's own slot
        rows[d - 2] = rows[d - 2] - acc[:, own, : own + 1]  # its row: H[parent, b], b <= parent
        if own > 0:
            cols[d - 2] = cols[d - 2] - acc[:, :own, own]  # its column: H[a, parent], a above it
        carry = acc[:, :own, :own] if own > 0 else None
    return Factor(tuple(pinv), tuple(xs), tuple(used))


def solve(sch: Schedule, fac: Factor, rhs: Float[Array, "B 3"]) -> Float[Array, "B 3"]:
    """u with ``H u = rhs`` (rows of the non-root bodies; the root row is ignored and returned 0).
    Forward: each level's ``H_ak z_k`` for all its ancestors a summed onto the parents once (the
    parent's own share applied, the rest carried up); back: each body's ancestors' u gathered
    from its parent's (one take per level)."""
    r = _by_level(sch, rhs)
    z: list[Any] = [None] * sch.t_max
    carry = None  # (w_d, d - 1, 3): pending H_ak z_k for the strict ancestors of level d
    for i, d in enumerate(range(sch.t_max, 0, -1)):  # forward: leaves first
        z[d - 1] = mv(fac.pinv[i], r[d - 1])
        if d == 1:
            break
        y = mv(fac.col[i], z[d - 1][:, None])  # (w_d, d - 1, 3)
        acc = _to_parents(sch, d, y if carry is None else y + carry)
        r[d - 2] = r[d - 2] - acc[:, d - 2]
        carry = acc[:, : d - 2] if d > 2 else None
    u = [z[0]]
    anc = None  # (w_d, d - 1, 3): u of each level-d body's ancestors, slot t - 1 for depth t
    for d in range(2, sch.t_max + 1):  # back: root side first
        up = u[d - 2][:, None] if anc is None else jnp.concatenate([anc, u[d - 2][:, None]], 1)
        anc = _take(sch, up, sch.parent_pos[d - 2])
        u.append(z[d - 1] - jnp.sum(mv(fac.x[sch.t_max - d], anc), 1))
    out = _take(sch, jnp.concatenate(u, 0), sch.order)
    return out * jnp.asarray(np.arange(len(sch.order)) > 0, rhs.dtype).reshape((-1,) + (1,) * (out.ndim - 1))


def subtree_moments(desc: np.ndarray, mass, inertia, com, unrolled: bool = True):
    """Per body, sums over its subtree: mass m, first moment s = sum m c, and J = sum (I + m
    (|c|^2 1 - c c^T)), the inertia about the origin of ``com`` (the root COM); ``unrolled``:
    the batched form of the sums (:func:`static.dot_sums`)."""
    eye = jnp.eye(3, dtype=com.dtype)
    own = inertia + mass[:, None, None] * (dot(com, com)[:, None, None] * eye - com[:, :, None] * com[:, None, :])
    return static.dot_sums(desc, (mass, mass[:, None] * com, own), unrolled)


def pivot_blocks(m_sub, s_sub, j_sub, pivot):
    """``C_k = J_k - (p_k . s_k) 1 + s_k p_k^T`` and ``a_k = s_k - m_k p_k`` (module docstring);
    ``C_k`` is also the block ``H_{k, root rotation}`` (the root's pivot is the origin)."""
    eye = jnp.eye(3, dtype=pivot.dtype)
    c_blocks = j_sub - dot(pivot, s_sub)[:, None, None] * eye + s_sub[:, :, None] * pivot[:, None, :]
    return c_blocks, s_sub - m_sub[:, None] * pivot


def matvec(sch: Schedule, paths: Paths, x: Float[Array, "B 3"]) -> Float[Array, "B 3"]:
    """H x from the paths (root row 0): every stored block times x at its column's body, summed
    into its row's body (one product over all blocks, one sum by a 0/1 matrix)."""
    per_level = list(enumerate(sch.levels, 1))
    src = np.concatenate(
        [sch.anc_at[lv, 1 : d + 1].ravel() for d, lv in per_level]  # row blocks H[k, anc]
        + [np.repeat(lv, d - 1) for d, lv in per_level]
    )  # column blocks H[anc, k]
    dst = np.concatenate(
        [np.repeat(lv, d) for d, lv in per_level] + [sch.anc_at[lv, 1:d].ravel() for d, lv in per_level]
    )
    blocks = jnp.concatenate([b.reshape(-1, 3, 3) for b in (*paths.row, *paths.col)])
    return jnp.tensordot(jnp.asarray(np.eye(len(sch.order))[dst].T, x.dtype), mv(blocks, _take(sch, x, src)), axes=1)


def transposed(sch: Schedule, paths: Paths) -> Paths:
    """The paths of H^T: a body's row against its strict ancestors is its column transposed."""
    swap = lambda a: jnp.swapaxes(a, -1, -2)
    return Paths(
        tuple(jnp.concatenate([swap(c), swap(r[:, -1:])], 1) for r, c in zip(paths.row, paths.col)),
        tuple(swap(r[:, :-1]) for r in paths.row),
    )


def linear_solve(
    sch: Schedule, paths: Paths, fac: Factor, rhs: Float[Array, "B 3"], symmetric: bool = False
) -> Float[Array, "B 3"]:
    """``H^-1 rhs`` with derivatives by implicit differentiation (``lax.custom_linear_solve``):
    a tangent costs one more solve with the same factor and one product with the tangent of H,
    not the derivative of the factorization. ``fac`` must be ``factor(sch, stop_gradient(paths))``."""

    def transpose_solve(_, y):
        return solve(sch, factor(sch, jax.lax.stop_gradient(transposed(sch, paths))), y)

    return jax.lax.custom_linear_solve(
        lambda v: matvec(sch, paths, v),
        rhs,
        lambda _, y: solve(sch, fac, y),
        transpose_solve=None if symmetric else transpose_solve,
        symmetric=symmetric,
    )
