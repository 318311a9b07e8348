"""The tree factorization of the joint-space matrix (physics/solvers/branch.py) against dense
linear algebra: paths equal the dense blocks of S^T M S and S^T G S, and factor + solve equal
``numpy.linalg.solve`` on trees of every shape, with a non-symmetric stiffness part."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.model.topology import of_tree
from neuromotor.physics.solvers import branch, nullspace

from test_nullspace import PARENT, _random_tree


def _random_parents(rng, n):
    """A random tree: each body hangs from any earlier one (chains, stars and mixtures)."""
    return (-1,) + tuple(int(rng.integers(0, b)) for b in range(1, n))


def _dense_from_paths(sch, paths, n):
    """H over the non-root bodies (3(n-1) square) from the paths (per level, exactly each
    body's own slots)."""
    h = np.zeros((3 * n, 3 * n))
    for d, lv in enumerate(sch.levels, 1):
        row, col = np.asarray(paths.row[d - 1]), np.asarray(paths.col[d - 1])
        assert row.shape == (len(lv), d, 3, 3) and col.shape == (len(lv), d - 1, 3, 3)
        for i, k in enumerate(lv):
            for t in range(1, d + 1):
                a = sch.anc_at[k, t]
                h[3 * k:3 * k + 3, 3 * a:3 * a + 3] = row[i, t - 1]
                if a != k:
                    h[3 * a:3 * a + 3, 3 * k:3 * k + 3] = col[i, t - 1]
    return h[3:, 3:]


@pytest.mark.parametrize("unrolled", [True, False])
@pytest.mark.parametrize("seed", range(4))
def test_factor_and_solve_equal_dense_solve_on_random_trees(seed, unrolled):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 24))
    parents = PARENT if seed == 0 else _random_parents(rng, n)
    n = len(parents)
    sch = branch.schedule(of_tree(parents), unrolled)
    t = sch.anc_at.shape[1] - 1
    # Random paths, made diagonally dominant so that no pivoting is needed (as for M - G).
    row = rng.normal(size=(n, t, 3, 3)) * sch.valid[..., None, None]
    col = rng.normal(size=(n, t, 3, 3)) * sch.strict[..., None, None]
    depth = np.asarray(of_tree(parents).depth)
    for k in range(1, n):
        row[k, depth[k] - 1] += 6.0 * t * np.eye(3)
    paths = branch.of_bodies(sch, jnp.asarray(row), jnp.asarray(col))
    h = _dense_from_paths(sch, paths, n)
    rhs = rng.normal(size=(n, 3))
    got = jax.jit(lambda p, r: branch.solve(sch, branch.factor(sch, p), r))(paths, jnp.asarray(rhs))
    want = np.linalg.solve(h, rhs[1:].reshape(-1))
    np.testing.assert_allclose(np.asarray(got)[1:].reshape(-1), want, rtol=0, atol=1e-12 * np.abs(want).max())
    assert np.all(np.asarray(got)[0] == 0.0)


@pytest.mark.parametrize("unrolled", [True, False])
def test_paths_are_the_blocks_of_the_reduced_matrices(unrolled):
    """Both ways of building the paths (level by level for batches, padded over every body for
    one trajectory) give the dense blocks of S^T M S and of S^T (M - G) S."""
    rng, n, mass, inertia, r_parent, r_child, r0 = _random_tree(3)
    st = nullspace.structure(of_tree(PARENT), unrolled=unrolled)
    geo = nullspace.geometry(st, jnp.asarray(r_parent), jnp.asarray(r_child), jnp.asarray(r0))
    c_blocks, first = nullspace._moments(st, geo, jnp.asarray(mass), jnp.asarray(inertia))
    inertia_h = _dense_from_paths(st.tree, branch.paths_of(st.tree, c_blocks, first, geo.pivot), n)
    dense = np.asarray(nullspace.reduced_inertia(st, geo, jnp.asarray(mass), jnp.asarray(inertia)))[6:, 6:]
    np.testing.assert_allclose(inertia_h, dense, atol=1e-12 * np.abs(dense).max())
    g = [jnp.asarray(rng.normal(size=s)) for s in ((n, 3, 3), (n - 1, 3, 3), (n - 1, 3, 3))]
    paths = branch.paths_of(st.tree, c_blocks, first, geo.pivot, nullspace._stiff_subtrees(st, *g))
    dense = dense - np.asarray(nullspace.reduced_stiffness(st, *g))[6:, 6:]
    np.testing.assert_allclose(_dense_from_paths(st.tree, paths, n), dense, atol=1e-12 * np.abs(dense).max())


@pytest.mark.parametrize("unrolled", [True, False])
def test_matvec_transpose_and_derivatives_of_the_linear_solve(unrolled):
    """H x and H^T from the paths equal the dense products; jacfwd and grad of the implicitly
    differentiated solve equal those of numpy's solve (central differences as the check)."""
    rng = np.random.default_rng(7)
    parents = _random_parents(rng, 12)
    n = len(parents)
    sch = branch.schedule(of_tree(parents), unrolled)
    t = sch.anc_at.shape[1] - 1
    depth = np.asarray(of_tree(parents).depth)
    row = rng.normal(size=(n, t, 3, 3)) * sch.valid[..., None, None]
    col = rng.normal(size=(n, t, 3, 3)) * sch.strict[..., None, None]
    for k in range(1, n):
        row[k, depth[k] - 1] += 6.0 * t * np.eye(3)
    paths = branch.of_bodies(sch, jnp.asarray(row), jnp.asarray(col))
    h = _dense_from_paths(sch, paths, n)
    x = rng.normal(size=(n, 3))
    np.testing.assert_allclose(np.asarray(jax.jit(lambda p, v: branch.matvec(sch, p, v))(paths, jnp.asarray(x)))[1:].reshape(-1),
                               h @ x[1:].reshape(-1), atol=1e-12 * np.abs(h).max())
    np.testing.assert_allclose(_dense_from_paths(sch, branch.transposed(sch, paths), n), h.T, atol=0)

    direction = branch.of_bodies(sch, jnp.asarray(rng.normal(size=row.shape)), jnp.zeros(col.shape))

    def f(eps):
        p = jax.tree.map(lambda a, b: a + eps * b, paths, direction)
        fac = branch.factor(sch, jax.lax.stop_gradient(p))
        return branch.linear_solve(sch, p, fac, jnp.asarray(x))

    f_jit = jax.jit(f)  # one compile each instead of hundreds of eagerly dispatched small ops
    central = (f_jit(1e-6) - f_jit(-1e-6)) / 2e-6
    np.testing.assert_allclose(jax.jit(jax.jacfwd(f))(0.0), central, atol=1e-6 * np.abs(central).max())
    weights = rng.normal(size=(n, 3))
    g = jax.jit(jax.grad(lambda e: jnp.sum(weights * f(e))))(0.0)
    np.testing.assert_allclose(g, np.sum(weights * np.asarray(central)), rtol=1e-6)
