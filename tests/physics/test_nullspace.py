"""The null-space solver's pieces against dense linear algebra on a random branching tree."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.model.topology import of_tree
from neuromotor.physics.solvers import nullspace
from neuromotor.rotations import quat_normalize, quat_to_matrix

PARENT = (-1, 0, 1, 2, 0, 4, 4, 1, 7, 8)  # branching, depth 4


def _random_tree(seed):
    rng = np.random.default_rng(seed)
    n = len(PARENT)
    rot = np.asarray(quat_to_matrix(quat_normalize(jnp.asarray(rng.normal(size=(n, 4))))))
    mass = rng.uniform(0.5, 8.0, n)
    body = rng.normal(size=(n, 3, 3))
    inertia_body = body @ np.swapaxes(body, 1, 2) * 0.01 + 0.01 * np.eye(3)
    inertia = rot @ inertia_body @ np.swapaxes(rot, 1, 2)
    r_parent, r_child = rng.normal(size=(2, n - 1, 3)) * 0.2
    r0 = rng.normal(size=3) * 0.1
    return rng, n, mass, inertia, r_parent, r_child, r0


def _dense_j(n, r_parent, r_child, r0, driven, free_root):
    """Rows of J as system.full_constraints lays them out: root (6), ball joints, driven."""
    def skew(a):
        return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])

    rows = []
    if not free_root:
        root = np.zeros((6, 6 * n))
        root[0:3, 0:3], root[0:3, 3:6], root[3:6, 3:6] = np.eye(3), -skew(r0), np.eye(3)
        rows.append(root)
    for c in range(1, n):
        p = PARENT[c]
        blk = np.zeros((3, 6 * n))
        blk[:, 6 * p:6 * p + 3], blk[:, 6 * p + 3:6 * p + 6] = np.eye(3), -skew(r_parent[c - 1])
        blk[:, 6 * c:6 * c + 3], blk[:, 6 * c + 3:6 * c + 6] = -np.eye(3), skew(r_child[c - 1])
        rows.append(blk)
    for d in driven:
        blk = np.zeros((3, 6 * n))
        blk[:, 6 * d + 3:6 * d + 6], blk[:, 6 * PARENT[d] + 3:6 * PARENT[d] + 6] = np.eye(3), -np.eye(3)
        rows.append(blk)
    return np.concatenate(rows, 0)


def _dense_m(mass, inertia):
    n = len(mass)
    m = np.zeros((6 * n, 6 * n))
    for b in range(n):
        m[6 * b:6 * b + 3, 6 * b:6 * b + 3] = mass[b] * np.eye(3)
        m[6 * b + 3:6 * b + 6, 6 * b + 3:6 * b + 6] = inertia[b]
    return m


def _basis(st, geo, n):
    """S as a dense matrix, column by column through apply_basis."""
    eye = np.eye(3 * (n + 1))
    return np.stack([np.asarray(nullspace.apply_basis(st, geo, jnp.asarray(e))).reshape(-1) for e in eye], 1)


@pytest.mark.parametrize("driven, free_root", [((), False), ((3, 6), False), ((), True)])
def test_basis_spans_the_null_space_and_reduced_matrices_are_exact(driven, free_root):
    rng, n, mass, inertia, r_parent, r_child, r0 = _random_tree(1)
    st = nullspace.structure(of_tree(PARENT), driven, free_root)
    geo = nullspace.geometry(st, jnp.asarray(r_parent), jnp.asarray(r_child), jnp.asarray(r0))
    s = _basis(st, geo, n)
    j = _dense_j(n, r_parent, r_child, r0, (), True)  # ball-joint rows only
    assert np.abs(j @ s).max() < 1e-14  # J S = 0 ...
    assert np.linalg.matrix_rank(s) == 3 * (n + 1) == 6 * n - j.shape[0]  # ... and S spans null(J)
    m = _dense_m(mass, inertia)
    np.testing.assert_allclose(nullspace.reduced_inertia(st, geo, jnp.asarray(mass), jnp.asarray(inertia)),
                               s.T @ m @ s, atol=1e-12 * np.abs(s.T @ m @ s).max())
    # An angular block-tree matrix G (not symmetric, as feedback stiffness in general is).
    g_diag, g_up, g_down = rng.normal(size=(n, 3, 3)), rng.normal(size=(n - 1, 3, 3)), rng.normal(size=(n - 1, 3, 3))
    g = np.zeros((6 * n, 6 * n))
    for b in range(n):
        g[6 * b + 3:6 * b + 6, 6 * b + 3:6 * b + 6] = g_diag[b]
    for c in range(1, n):
        p = PARENT[c]
        g[6 * c + 3:6 * c + 6, 6 * p + 3:6 * p + 6] = g_up[c - 1]
        g[6 * p + 3:6 * p + 6, 6 * c + 3:6 * c + 6] = g_down[c - 1]
    np.testing.assert_allclose(nullspace.reduced_stiffness(st, *map(jnp.asarray, (g_diag, g_up, g_down))),
                               s.T @ g @ s, atol=1e-12 * np.abs(s.T @ g @ s).max())
    # S^T f and the multipliers: J^T lam = f is recovered exactly when f is in the range of J^T.
    f = rng.normal(size=(n, 6))
    np.testing.assert_allclose(nullspace.project_forces(st, geo, jnp.asarray(f)), s.T @ f.reshape(-1), atol=1e-12)
    jf = _dense_j(n, r_parent, r_child, r0, driven, free_root)
    lam = rng.normal(size=jf.shape[0])
    got = nullspace.multipliers(st, geo, jnp.asarray((jf.T @ lam).reshape(n, 6)))
    np.testing.assert_allclose(got, lam, atol=1e-12)


@pytest.mark.parametrize("driven, free_root", [((), False), ((3, 6), False), ((), True)])
def test_kkt_solve_and_projection_match_dense_saddle_point_solves(driven, free_root):
    rng, n, mass, inertia, r_parent, r_child, r0 = _random_tree(2)
    st = nullspace.structure(of_tree(PARENT), driven, free_root)
    geo = nullspace.geometry(st, jnp.asarray(r_parent), jnp.asarray(r_child), jnp.asarray(r0))
    m = _dense_m(mass, inertia)
    j = _dense_j(n, r_parent, r_child, r0, driven, free_root)
    nc = j.shape[0]
    g_diag = 0.3 * rng.normal(size=(n, 3, 3))
    zero = np.zeros((n - 1, 3, 3))
    a = m.copy()
    for b in range(n):
        a[6 * b + 3:6 * b + 6, 6 * b + 3:6 * b + 6] -= g_diag[b]
    r = rng.normal(size=(n, 6))
    b = np.zeros(nc)
    b[: 6 if not free_root else 0] = rng.normal(size=6 if not free_root else 0)
    b[nc - 3 * len(driven):] = rng.normal(size=3 * len(driven))
    kkt = np.block([[a, -j.T], [j, np.zeros((nc, nc))]])
    x = np.linalg.solve(kkt, np.concatenate([r.reshape(-1), b]))
    solve = jax.jit(lambda *args: nullspace.solve_kkt(st, geo, *args))
    v = solve(jnp.asarray(mass), jnp.asarray(inertia), jnp.asarray(g_diag), jnp.asarray(zero), jnp.asarray(zero),
              jnp.asarray(r), jnp.asarray(b))
    np.testing.assert_allclose(np.asarray(v).reshape(-1), x[:6 * n], atol=1e-12 * np.abs(x).max())
    np.testing.assert_allclose(nullspace.multipliers(st, geo, jnp.asarray((a @ x[:6 * n]).reshape(n, 6) - r)),
                               x[6 * n:], atol=1e-11 * np.abs(x).max())
    # Post-stabilization step: dx = M^-1 J^T (J M^-1 J^T)^-1 (-C).
    c = rng.normal(size=nc) * 1e-3
    minv = np.linalg.inv(m)
    dx = minv @ j.T @ np.linalg.solve(j @ minv @ j.T, -c)
    for tree in (False, True):  # dense Cholesky, and the tree factorization where it applies
        got = nullspace.projection_step(st, geo, jnp.asarray(mass), jnp.asarray(inertia), jnp.asarray(c), tree)
        np.testing.assert_allclose(np.asarray(got).reshape(-1), dx, atol=1e-12 * np.abs(dx).max())
    if st.by_tree:  # Eq. 2 by the tree-factored H (BranchSolver's path)
        args = [jnp.asarray(x) for x in (mass, inertia, g_diag, zero, zero)]
        red = nullspace.reduce_tree(st, geo, *args)
        v = nullspace.solve_reduced(st, geo, red, jnp.asarray(r), jnp.asarray(b))
        np.testing.assert_allclose(np.asarray(v).reshape(-1), x[:6 * n], atol=1e-12 * np.abs(x).max())


@pytest.mark.parametrize("unrolled", [False, True])
@pytest.mark.parametrize("driven, free_root", [((), False), ((3, 6), False), ((), True)])
def test_contact_responses_in_joint_space_equal_the_dense_saddle_point_solve(driven, free_root, unrolled):
    """The contact rows projected in closed form (``(Jc S)``, no tree sum per row), the responses
    ``X = A^-1 [Jc^T; 0]`` lifted from joint space and the Delassus matrix ``W = Jc X`` equal the
    dense saddle-point solve and the solver interface's default (the vmapped solve of every row),
    with a stiffness that is not symmetric (couplings up and down the tree)."""
    from neuromotor.physics.solvers.base import KKTSolver, one_body_rows
    from neuromotor.physics.solvers.nullspace import BranchSolver, NullSpaceKKT, NullSpaceSolver

    rng, n, mass, inertia, r_parent, r_child, r0 = _random_tree(3)
    topo = of_tree(PARENT)
    st = nullspace.structure(topo, driven, free_root, unrolled)
    geo = nullspace.geometry(st, jnp.asarray(r_parent), jnp.asarray(r_child), jnp.asarray(r0))
    g_diag, (g_up, g_down) = 0.2 * rng.normal(size=(n, 3, 3)), 0.1 * rng.normal(size=(2, n - 1, 3, 3))
    args = [jnp.asarray(x) for x in (mass, inertia, g_diag, g_up, g_down)]
    red = nullspace.reduce_tree(st, geo, *args) if st.by_tree else None
    den = None if st.by_tree else nullspace.reduce_dense(st, geo, *args)
    system = NullSpaceKKT(st, topo, geo, *args, jnp.asarray(r_parent), jnp.asarray(r_child), red, den)
    k = 5
    body = jnp.asarray(rng.integers(0, n, size=k), jnp.int32)
    rows = jnp.asarray(rng.normal(size=(k, 3, 6)))
    jc = np.asarray(one_body_rows(n, body, rows)).reshape(3 * k, 6 * n)
    # S^T of each one-body row in closed form, against the tree sums of project_forces.
    proj = nullspace.project_body_rows(st, geo, body, rows)
    want = jax.vmap(lambda f: nullspace.project_forces(st, geo, f))(jnp.asarray(jc.reshape(-1, n, 6)))
    np.testing.assert_allclose(proj, want, rtol=0, atol=1e-13 * np.abs(want).max())
    # The dense saddle-point system: A = M - G with G's angular blocks on the tree.
    a = _dense_m(mass, inertia)
    for bb in range(n):
        a[6 * bb + 3:6 * bb + 6, 6 * bb + 3:6 * bb + 6] -= g_diag[bb]
    for c in range(1, n):
        p = PARENT[c]
        a[6 * c + 3:6 * c + 6, 6 * p + 3:6 * p + 6] -= g_up[c - 1]
        a[6 * p + 3:6 * p + 6, 6 * c + 3:6 * c + 6] -= g_down[c - 1]
    j = _dense_j(n, r_parent, r_child, r0, driven, free_root)
    nc = j.shape[0]
    kkt = np.block([[a, -j.T], [j, np.zeros((nc, nc))]])
    x_dense = np.linalg.solve(kkt, np.concatenate([jc.T, np.zeros((nc, 3 * k))]))[: 6 * n]
    solver = BranchSolver() if unrolled else NullSpaceSolver()
    b = jnp.asarray(rng.normal(size=nc))  # the responses do not depend on b
    for cr, lift in ((solver.contact_responses(system, n, body, rows, b), solver.lift),
                     (KKTSolver.contact_responses(solver, system, n, body, rows, b), lambda s, x: x)):
        x = np.asarray(lift(system, cr.x))
        np.testing.assert_allclose(x, x_dense, rtol=0, atol=1e-11 * np.abs(x_dense).max())
        np.testing.assert_allclose(cr.w, jc @ x_dense, rtol=0, atol=1e-11 * np.abs(jc @ x_dense).max())
