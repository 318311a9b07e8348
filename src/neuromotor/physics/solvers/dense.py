"""Eq. 2 by one dense LU of the whole (6B + nc) saddle-point matrix: the reference path.

K and D come from one dense ``jax.jacfwd`` over all bodies (``stiffness.stiff_jacobians``), so
this path shares neither the tree sparsity nor the per-joint Jacobians of the fast solvers; tests
check that all three give the same step to round-off. Post-stabilization solves
``(J M^-1 J^T) mu = -C`` densely.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from neuromotor.physics.solvers.base import KKTSolver, relative_residual
from neuromotor.physics.system import apply_inverse_mass, full_constraints, mass_matrix


class DenseKKT(eqx.Module):
    """``[[A, -J^T], [J, 0]]`` of Eq. 2."""

    lhs: Float[Array, "N N"]


class DenseSolver(KKTSolver):
    """One dense LU of Eq. 2; one dense solve of ``J M^-1 J^T`` per Newton step."""

    tree_blocks = False

    def assemble(self, model, cfg, rot, inertia, stiff, h):
        jac = full_constraints(model, cfg.driven, rot, cfg.free_root)
        nc = jac.shape[0]
        a11 = mass_matrix(model, rot) - h * stiff.dmat - h * h * stiff.kmat
        return DenseKKT(jnp.block([[a11, -jac.T], [jac, jnp.zeros((nc, nc), rot.dtype)]]))

    def solve(self, system, r, b):
        sol = jnp.linalg.solve(system.lhs, jnp.concatenate([r.reshape(-1), b]))
        return sol[: r.size].reshape(r.shape), sol

    def multipliers(self, system, r, b, v, sol):
        rhs = jnp.concatenate([r.reshape(-1), b])
        residual = relative_residual(system.lhs @ sol - rhs, jnp.linalg.norm(rhs))
        return sol[r.size :], residual

    def projection_step(self, model, cfg, rot, c):
        jac = full_constraints(model, cfg.driven, rot, cfg.free_root)
        minv_jt = apply_inverse_mass(model, rot, jac).T  # (6B, nc)
        mu = jnp.linalg.solve(jac @ minv_jt, -c)
        return (minv_jt @ mu).reshape(model.n_bodies, 6)
