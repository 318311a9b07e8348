"""The contact LCP at the velocity level (Section 4 of the paper) by projected Gauss-Seidel.

With the Delassus matrix W and ``w = W P + q`` (contacts ordered (n, t1, t2)) each active
contact must satisfy

    lam_n >= 0,  w_n >= 0,  lam_n w_n = 0                       (non-penetration)
    f_t in mu lam_n Poly_N,   <w_t, f' - f_t> >= 0 for all f' in mu lam_n Poly_N

where Poly_N is the regular N-gon with vertices d_j = (cos 2 pi j/N, sin 2 pi j/N): the
friction pyramid of the Stewart-Trinkle LCP (f_t = sum_j beta_j d_j, beta_j >= 0, slack
gamma = max_j(-d_j . w_t) >= 0 with sum_j beta_j <= mu lam_n complementary to gamma). The
variational form above is its maximal-dissipation statement, which is what projected
Gauss-Seidel (PGS) converges to: per contact, lam_n <- max(0, lam_n - w_n / W_nn), then
f_t <- Proj(f_t - w_t / lambda_max(W_tt)) onto the scaled polygon (exact Euclidean
projection). Fixed sweep count (``lax.fori_loop``): jittable, vmappable and differentiable
almost everywhere. A fixed count is not convergence: :func:`lcp_residual` measures how far an
answer is from solving the LCP, and every contact step records it.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

_TINY = 1e-12


def project_polygon(p: Float[Array, " 2"], scale, sides: int) -> Float[Array, " 2"]:
    """Euclidean projection of p onto scale * Poly_N (regular N-gon, vertices (cos, sin)(2 pi j/N)).

    The edge whose outward normal is nearest to p's direction is the most violated one; outside,
    the projection onto that edge's segment (clamped at its vertices) is the nearest point. In
    closed form, elementwise: a PGS sweep runs it once per contact, and a search over the edges
    would cost a gather per call."""
    sector = 2.0 * math.pi / sides
    # Which edge is piecewise constant in p: no derivative flows through the angle.
    ang = jax.lax.stop_gradient(jnp.arctan2(p[1], p[0]))
    mid = (jnp.floor(ang / sector) + 0.5) * sector
    c, s = jnp.cos(mid), jnp.sin(mid)
    apothem, half = scale * math.cos(math.pi / sides), scale * math.sin(math.pi / sides)
    outside = c * p[0] + s * p[1] > apothem
    along = jnp.clip(c * p[1] - s * p[0], -half, half)
    edge = jnp.stack([apothem * c - along * s, apothem * s + along * c])
    return jnp.where(outside, edge, p)


def _tangent_steps(w_mat: Float[Array, "3K 3K"], k: int) -> Float[Array, " K"]:
    """1 / largest eigenvalue of each contact's 2x2 tangent block: the friction update's step."""
    tt = jnp.stack([w_mat[3 * i + 1 : 3 * i + 3, 3 * i + 1 : 3 * i + 3] for i in range(k)])
    tt = 0.5 * (tt + jnp.swapaxes(tt, -1, -2))
    tr, det = tt[:, 0, 0] + tt[:, 1, 1], tt[:, 0, 0] * tt[:, 1, 1] - tt[:, 0, 1] ** 2
    lam_max = 0.5 * tr + jnp.sqrt(jnp.maximum(0.25 * tr**2 - det, 0.0))
    return 1.0 / jnp.maximum(lam_max, _TINY)


def solve_lcp_pgs(
    w_mat: Float[Array, "3K 3K"],
    q: Float[Array, " 3K"],
    mu: Float[Array, " K"] | float,
    active: Bool[Array, " K"],
    p0: Float[Array, "K 3"],
    sides: int,
    iterations: int,
) -> Float[Array, "K 3"]:
    """Projected Gauss-Seidel for the contact LCP (see the module docstring).

    w = W P + q, contacts ordered (n, t1, t2); ``mu`` one friction coefficient, or one per
    contact (K,). Inactive contacts keep P = 0.
    """
    k = active.shape[0]
    mu = jnp.broadcast_to(mu, (k,))
    mask = active.astype(w_mat.dtype)
    diag_n = jnp.array([w_mat[3 * i, 3 * i] for i in range(k)])
    inv_n = mask / jnp.maximum(diag_n, _TINY)
    step_t = _tangent_steps(w_mat, k)
    # Each contact's rows and constants as separate loop-invariant arrays: slicing them inside
    # the sweep would cost a kernel per contact per sweep (the sweep is launch-bound).
    rows = [w_mat[3 * i : 3 * i + 3] for i in range(k)]
    consts = [
        (q[3 * i : 3 * i + 3], inv_n[i], mask[i], step_t[i], mu[i], w_mat[3 * i + 1 : 3 * i + 3, 3 * i])
        for i in range(k)
    ]

    def sweep(_, p):
        for i in range(k):
            q_i, inv_i, mask_i, step_i, mu_i, w_tn = consts[i]
            w = rows[i] @ p + q_i
            p_i = jax.lax.dynamic_slice(p, (3 * i,), (3,))
            lam = jnp.maximum(0.0, p_i[0] - w[0] * inv_i) * mask_i
            w_t = w[1:] + w_tn * (lam - p_i[0])
            f_t = project_polygon(p_i[1:] - step_i * w_t, mu_i * lam, sides) * mask_i
            p = jax.lax.dynamic_update_slice(p, jnp.concatenate([lam[None], f_t]), (3 * i,))
        return p

    return jax.lax.fori_loop(0, iterations, sweep, (p0 * mask[:, None]).reshape(-1)).reshape(k, 3)


def lcp_residual(
    w_mat: Float[Array, "3K 3K"],
    q: Float[Array, " 3K"],
    mu: Float[Array, " K"] | float,
    active: Bool[Array, " K"],
    p: Float[Array, "K 3"],
    sides: int,
) -> Float[Array, " K"]:
    """Each contact's distance from solving the LCP (module docstring) at impulses ``p``, in
    velocity units (m/s; 0 on inactive contacts): the larger of the normal part
    ``|min(lam_n / W_nn, w_n)|`` and the friction part ``|f_t - Proj(f_t - s w_t)| / s`` (s the
    PGS friction step), the fixed-point residuals of the PGS update scaled to velocities. Zero
    exactly at a solution, whatever W's null space does to the impulses."""
    k = active.shape[0]
    mu = jnp.broadcast_to(mu, (k,))
    w = (w_mat @ p.reshape(-1) + q).reshape(k, 3)
    diag_n = jnp.diagonal(w_mat)[0::3]
    normal = jnp.abs(jnp.minimum(p[:, 0] / jnp.maximum(diag_n, _TINY), w[:, 0]))
    step_t = _tangent_steps(w_mat, k)
    proj = jax.vmap(lambda f, s: project_polygon(f, s, sides))(p[:, 1:] - step_t[:, None] * w[:, 1:], mu * p[:, 0])
    friction = jnp.linalg.norm(p[:, 1:] - proj, axis=-1) / step_t
    return jnp.where(active, jnp.maximum(normal, friction), 0.0)


def solve_gap_projection(w_nn: Float[Array, "K K"], g: Float[Array, " K"], active, iterations: int):
    """mu >= 0, g + W_nn mu >= 0, mu (g + W_nn mu) = 0 by projected Gauss-Seidel (positions)."""
    k = g.shape[0]
    mask = active.astype(g.dtype)
    inv = mask / jnp.maximum(jnp.diag(w_nn), _TINY)
    rows = [(w_nn[i], g[i], inv[i]) for i in range(k)]  # loop-invariant, one array each (see above)

    def sweep(_, m):
        for i in range(k):
            row, g_i, inv_i = rows[i]
            m = jax.lax.dynamic_update_slice(m, jnp.maximum(0.0, m[i] - (row @ m + g_i) * inv_i)[None], (i,))
        return m

    return jax.lax.fori_loop(0, iterations, sweep, jnp.zeros_like(g))
