"""Static indexing (physics/static.py): takes and masked sums equal jnp.take and numpy, both forms,
also under vmap, for runs, repeats, gaps and empty rows."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.physics import static


@pytest.mark.parametrize("unrolled", [True, False])
def test_take_equals_jnp_take(unrolled):
    x = jnp.asarray(np.random.default_rng(0).normal(size=(9, 4, 3)))
    for idx in ([3, 3, 3, 4, 5, 6, 6, 2, 0], [[1, 2], [2, 2], [8, 0]], [5], np.zeros(0, np.int64)):
        idx = np.asarray(idx, np.int64)
        for axis in (0, 1):
            sub = idx % x.shape[axis]
            np.testing.assert_array_equal(static.take(x, sub, axis, unrolled), jnp.take(x, sub, axis=axis))
        batched = jax.vmap(lambda y: static.take(y, idx, 0, unrolled))(jnp.stack([x, 2 * x]))
        np.testing.assert_array_equal(batched[1], jnp.take(2 * x, idx, axis=0))


@pytest.mark.parametrize("unrolled", [True, False])
def test_gather_sum_equals_masked_sums(unrolled):
    rng = np.random.default_rng(1)
    index = rng.integers(0, 8, size=(6, 3))
    mask = (rng.random((6, 3)) < 0.6).astype(float)
    mask[2] = 0.0  # a row that sums nothing
    x = jnp.asarray(rng.normal(size=(8, 3, 3)))
    want = np.einsum("rw,rwij->rij", mask, np.asarray(x)[index])
    np.testing.assert_allclose(static.gather_sum(x, index, mask, unrolled), want, rtol=1e-15, atol=1e-15)
    got = jax.vmap(lambda y: static.gather_sum(y, index, mask, unrolled))(jnp.stack([x, -x]))
    np.testing.assert_allclose(got[1], -want, rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("unrolled", [True, False])
def test_dot_sums_equal_matrix_products(unrolled):
    rng = np.random.default_rng(2)
    mat = (rng.random((5, 7)) < 0.5).astype(float)
    xs = (jnp.asarray(rng.normal(size=(7,))), jnp.asarray(rng.normal(size=(7, 3))), jnp.asarray(rng.normal(size=(7, 3, 3))))
    got = static.dot_sums(mat, xs, unrolled)
    assert [g.shape for g in got] == [(5,), (5, 3), (5, 3, 3)]
    for g, x in zip(got, xs):
        np.testing.assert_allclose(g, np.tensordot(mat, np.asarray(x), axes=1), rtol=1e-14, atol=1e-14)
    batched = jax.vmap(lambda *ys: static.dot_sums(mat, ys, unrolled))(*[jnp.stack([x, -2 * x]) for x in xs])
    for g, x in zip(batched, xs):
        np.testing.assert_allclose(g[1], -2 * np.tensordot(mat, np.asarray(x), axes=1), rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("unrolled", [True, False])
def test_dot_sum_equals_sum_of_matrix_products(unrolled):
    rng = np.random.default_rng(3)
    mats = ((rng.random((5, 7)) < 0.5).astype(float), -(rng.random((5, 4)) < 0.5).astype(float))
    xs = (jnp.asarray(rng.normal(size=(7, 3, 3))), jnp.asarray(rng.normal(size=(4, 3, 3))))
    want = sum(np.tensordot(m, np.asarray(x), axes=1) for m, x in zip(mats, xs))
    np.testing.assert_allclose(static.dot_sum(mats, xs, unrolled), want, rtol=1e-14, atol=1e-14)
    got = jax.vmap(lambda a, b: static.dot_sum(mats, (a, b), unrolled))(*[jnp.stack([x, 3 * x]) for x in xs])
    np.testing.assert_allclose(got[1], 3 * want, rtol=1e-14, atol=1e-14)
