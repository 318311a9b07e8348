"""Indexing and sums by static (numpy) indices, in the form XLA:CPU runs fastest.

The body tree is known when a program is traced, so "the bodies of one tree level", "each
body's parent in the level above" or "the sum over each body's children" use indices that are
numpy constants. Two ways to write them, with the same results to the last bit:

* gathers (``unrolled=False``): one kernel each. Best for a single trajectory, whose step is
  bound by the number of kernels (XLA:CPU leaves dozens of tiny slices and adds unfused, one
  kernel each);
* contiguous slices, adds and one concatenation (``unrolled=True``): under ``vmap`` XLA:CPU
  runs a gather with per-element index arithmetic (it was the largest share of a batched step),
  while slices and adds fuse into a few loops over the batch. The batched solver
  (``Solver.BRANCH``) uses this form.

Sums over whole subtrees stay dots with static 0/1 matrices in either case: unrolled into
one-row sums they were slower, batched or not. Several sums with one matrix are one dot over the
operands side by side for a single trajectory (a kernel fewer each), but one dot each under
``vmap``, where XLA:CPU fuses every operand's move of the batch axis into its producer and a
concatenation would be a copy more (:func:`dot_sums`); a sum of products with several matrices
likewise (:func:`dot_sum`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def _runs(idx: np.ndarray) -> list[tuple[int, int, int]]:
    """``idx`` (1-D) as maximal runs ``(start, length, step)``: consecutive indices (step 1) or
    one index repeated (step 0)."""
    out: list[list[int]] = []
    for i in idx.tolist():
        if out:
            start, n, step = out[-1]
            if (n == 1 or step == 1) and i == start + n:
                out[-1] = [start, n + 1, 1]
                continue
            if (n == 1 or step == 0) and i == start:
                out[-1] = [start, n + 1, 0]
                continue
        out.append([i, 1, 1])
    return [(a, b, c) for a, b, c in out]


def _piece(x, start: int, n: int, step: int, axis: int):
    if step == 1:
        return jax.lax.slice_in_dim(x, start, start + n, axis=axis)
    one = jax.lax.slice_in_dim(x, start, start + 1, axis=axis)
    return jnp.broadcast_to(one, x.shape[:axis] + (n,) + x.shape[axis + 1 :])


def take(x, idx, axis: int = 0, unrolled: bool = True):
    """``jnp.take(x, idx, axis)`` for a static integer array ``idx`` of any shape (the result
    has ``idx.shape`` in place of ``axis``): slices of ``x`` when ``unrolled``, else one gather
    (a slice where the indices are one run)."""
    idx = np.asarray(idx, np.int64)
    axis = axis % x.ndim
    flat = idx.reshape(-1)
    runs = _runs(flat)
    if not unrolled and len(runs) > 1:
        return jnp.take(x, idx, axis=axis)
    if flat.size == 0:
        shape = x.shape[:axis] + (0,) + x.shape[axis + 1 :]
        out = jnp.zeros(shape, x.dtype)
    else:
        parts = [_piece(x, *run, axis) for run in runs]
        out = parts[0] if len(parts) == 1 else jnp.concatenate(parts, axis)
    return out.reshape(x.shape[:axis] + idx.shape + x.shape[axis + 1 :])


def gather_sum(x, index, mask, unrolled: bool = True):
    """Row i: ``sum_j mask[i, j] x[index[i, j]]`` over the leading axis of x (static ``index``
    and 0/1 ``mask`` of shape (rows, width)); rows with no entry are zero. Sums of one-row
    slices when ``unrolled``, else one gather and one reduction."""
    index, mask = np.asarray(index), np.asarray(mask)
    if not unrolled:
        picked = jnp.take(x, index, axis=0) * jnp.asarray(mask, x.dtype).reshape(mask.shape + (1,) * (x.ndim - 1))
        return jnp.sum(picked, 1)
    rows = []
    for i in range(index.shape[0]):
        terms = [jax.lax.slice_in_dim(x, int(j), int(j) + 1, axis=0) for j, on in zip(index[i], mask[i]) if on]
        rows.append(sum(terms[1:], terms[0]) if terms else jnp.zeros((1,) + x.shape[1:], x.dtype))
    return rows[0] if len(rows) == 1 else jnp.concatenate(rows, 0)


def dot_sums(mat, xs, unrolled: bool = True) -> tuple:
    """``mat @ x`` over the leading axis for each x (static ``mat``): one dot each when
    ``unrolled`` (the batched form), else one dot over the operands side by side."""
    mat = jnp.asarray(mat, xs[0].dtype)
    if unrolled or len(xs) == 1:
        return tuple(jnp.tensordot(mat, x, axes=1) for x in xs)
    flat = jnp.tensordot(mat, jnp.concatenate([x.reshape(x.shape[0], -1) for x in xs], 1), axes=1)
    ends = np.cumsum([0] + [int(np.prod(x.shape[1:])) for x in xs])
    return tuple(flat[:, a:b].reshape((mat.shape[0],) + x.shape[1:]) for a, b, x in zip(ends[:-1], ends[1:], xs))


def dot_sum(mats, xs, unrolled: bool = True):
    """``sum_i mats[i] @ xs[i]`` over the leading axes (static ``mats``): one dot each when
    ``unrolled`` (the batched form), else one dot with the matrices side by side and the
    operands stacked."""
    if unrolled:
        return sum(jnp.tensordot(jnp.asarray(m, x.dtype), x, axes=1) for m, x in zip(mats, xs))
    return jnp.tensordot(jnp.asarray(np.concatenate(mats, 1), xs[0].dtype), jnp.concatenate(xs, 0), axes=1)
