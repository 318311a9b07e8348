"""The contact step's fast kernels against their plain definitions (issue 38, the free-standing
step's cost): the selection by ranks against ``lax.top_k``, the closed-form polygon projection
against the nearest point over every edge, and the factored LU solve against ``jnp.linalg.solve``
(values, forward and reverse derivatives, the transposed solve). The Delassus matrix from the
contacts' own bodies: tests/physics/test_nullspace.py."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.physics.contact import project_polygon
from neuromotor.physics.contact.ground import smallest
from neuromotor.physics.solvers.nullspace import lu_factor, lu_solve


@pytest.mark.parametrize("shape,k", [((19, 40), 8), ((152,), 16), ((5, 7), 7), ((3, 10), 1)])
def test_smallest_is_top_k_of_the_negated_keys(shape, k):
    rng = np.random.default_rng(7)
    for trial in range(40):
        x = rng.normal(size=shape)
        if trial % 2:
            x = np.round(x, 1) + 0.0  # ties (lower index first); no signed zeros
        if trial % 3 == 0:
            x[..., :2] = 1e6  # padding vertices
        want = np.asarray(jax.lax.top_k(-jnp.asarray(x), k)[1])
        got = np.asarray(smallest(jnp.asarray(x), k))
        np.testing.assert_array_equal(got, want)


def _nearest_on_polygon(p, scale, sides):
    """Brute force: the nearest of the clamped projections on every edge, or p when inside."""
    ang = 2 * np.pi * np.arange(sides) / sides
    verts = scale * np.stack([np.cos(ang), np.sin(ang)], -1)
    normals = np.stack([np.cos(ang + np.pi / sides), np.sin(ang + np.pi / sides)], -1)
    if np.max(normals @ p) <= scale * np.cos(np.pi / sides):
        return p
    best, dist = None, np.inf
    for j in range(sides):
        a, b = verts[j], verts[(j + 1) % sides]
        t = np.clip(np.dot(p - a, b - a) / max(np.dot(b - a, b - a), 1e-300), 0, 1)
        c = a + t * (b - a)
        if np.sum((c - p) ** 2) < dist:
            best, dist = c, np.sum((c - p) ** 2)
    return best


@pytest.mark.parametrize("sides", [4, 5, 8, 16])
def test_polygon_projection_is_the_nearest_point(sides):
    rng = np.random.default_rng(sides)
    proj = jax.jit(lambda p, s: project_polygon(p, s, sides))
    for _ in range(300):
        p = rng.normal(size=2) * rng.choice([0.1, 1.0, 5.0])
        scale = rng.choice([0.0, 0.3, 1.0, 2.5])
        np.testing.assert_allclose(np.asarray(proj(jnp.asarray(p), scale)), _nearest_on_polygon(p, scale, sides), atol=1e-12)
    # on a vertex's direction and on an edge's normal, exactly
    for p in ([3.0, 0.0], [0.0, 0.0], [np.cos(np.pi / sides) * 2, np.sin(np.pi / sides) * 2]):
        np.testing.assert_allclose(np.asarray(proj(jnp.asarray(p), 1.0)), _nearest_on_polygon(np.asarray(p), 1.0, sides), atol=1e-12)


def test_factored_lu_solve_equals_linalg_solve_with_derivatives():
    rng = np.random.default_rng(3)
    a = jnp.asarray(rng.normal(size=(9, 9)) + 3 * np.eye(9))
    b = jnp.asarray(rng.normal(size=9))
    np.testing.assert_allclose(lu_solve(lu_factor(a), b), jnp.linalg.solve(a, b), rtol=1e-13, atol=1e-13)
    ours = lambda a, b: jnp.sum(jnp.sin(lu_solve(lu_factor(a), b)))
    ref = lambda a, b: jnp.sum(jnp.sin(jnp.linalg.solve(a, b)))
    for diff in (jax.grad, jax.jacfwd):  # reverse mode uses the transposed solve
        for x, y in zip(diff(ours, (0, 1))(a, b), diff(ref, (0, 1))(a, b)):
            np.testing.assert_allclose(x, y, rtol=1e-11, atol=1e-12)
    many = jax.vmap(lambda c: lu_solve(lu_factor(a), c))(jnp.eye(9))
    np.testing.assert_allclose(many.T, jnp.linalg.inv(a), rtol=1e-12, atol=1e-12)
