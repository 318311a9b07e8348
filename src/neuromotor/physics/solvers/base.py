"""The interface every solver of Eq. 2 implements, and the option that picks one.

Eq. 2 is the saddle-point system

    [ A   -J^T ] [ v+  ]   [ r ]        A = M - h D - h^2 K,
    [ J    0   ] [ lam ] = [ b ]        r = M v + h (k - D v),

and each Newton step of post-stabilization is the same shape with A = M, r = 0, b = -C(x). The
step (:func:`neuromotor.physics.dynamics.step`) computes what is common -- controller inputs,
K and D, r and b -- once; a solver only assembles its own form of the matrix and solves it:

* :meth:`KKTSolver.assemble` -- the matrix at the current orientations, in the solver's layout;
* :meth:`KKTSolver.solve` -- v+ for a right-hand side ``(r, b)``. The result is linear in
  ``(r, b)``, so ``jax.vmap`` over extra right-hand sides (responses to unit contact impulses,
  ``A^-1 [Jc^T; 0]``) reuses one factorization;
* :meth:`KKTSolver.multipliers` -- lam and the relative residual of the whole of Eq. 2;
* :meth:`KKTSolver.projection_step` -- the projection of post-stabilization (its first Newton step);
* :meth:`KKTSolver.contact_responses` and :meth:`KKTSolver.lift` -- the responses to unit
  contact impulses and the Delassus matrix (by default the vmapped :meth:`KKTSolver.solve`; a
  solver in reduced coordinates may keep them reduced and lift only the impulses' sums).

To add a solver: subclass :class:`KKTSolver` in a module of this package, add a member to
:class:`Solver` and register the class in ``neuromotor.physics.solvers.SOLVERS``.
"""

from __future__ import annotations

import abc
import enum
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


def relative_residual(res: Float[Array, " m"], rhs_norm: Float[Array, ""]) -> Float[Array, ""]:
    """``|res| / |rhs|``, the floor the smallest normal number of the dtype (a float64 floor such
    as 1e-300 would round to 0 in float32)."""
    return jnp.linalg.norm(res) / jnp.maximum(rhs_norm, jnp.finfo(res.dtype).tiny)


class Solver(str, enum.Enum):
    """Which solver of Eq. 2 a rollout uses (``StepOptions.solver``; the strings are accepted too)."""

    NULLSPACE = "nullspace"  # v = S u over the joint-space basis, H factored along the tree (fastest single run)
    BRANCH = "branch"  # the same with its tree indexing as slices (fastest in vmapped batches)
    TREE = "tree"  # linear-time block elimination along the body tree (Baraff 1996)
    DENSE = "dense"  # one dense LU of the (6B + nc) matrix: the reference path

    def __str__(self) -> str:
        return self.value

    def batched(self) -> Solver:
        """The solver for many trajectories under ``vmap``: the null-space method's batched twin."""
        return Solver.BRANCH if self is Solver.NULLSPACE else self


class ContactResponses(eqx.Module):
    """The character's responses to unit contact impulses (the rows of Jc, each a wrench on one
    body): ``x`` (D, R) in the solver's coordinates, ``X = lift(x)`` in the bodies' velocities
    (6B, R), and the Delassus matrix ``W = Jc X`` (R, R)."""

    x: Float[Array, "D R"]
    w: Float[Array, "R R"]


def one_body_rows(n_bodies: int, body: Int[Array, " K"], rows: Float[Array, "K d 6"]) -> Float[Array, "Kd B 6"]:
    """The rows as whole-character wrenches (zero on every body but their own)."""
    onehot = jax.nn.one_hot(body, n_bodies, dtype=rows.dtype)
    return jnp.einsum("kb,kdj->kdbj", onehot, rows).reshape(-1, n_bodies, 6)


class KKTSolver(abc.ABC):
    """One way to solve Eq. 2 and the post-stabilization projection (stateless)."""

    # True: K and D come as 3x3 blocks on the body tree (``stiffness.StiffBlocks``); False: dense.
    tree_blocks: ClassVar[bool]
    # True: the solver of vmapped batches, and the step's static sums take their batched form
    # (neuromotor.physics.static).
    unrolled: ClassVar[bool] = False

    @abc.abstractmethod
    def assemble(self, model, cfg, rot, inertia, stiff, h: float) -> Any:
        """The matrix of Eq. 2 (``A = M - h D - h^2 K`` and J) in this solver's layout (a pytree)."""

    @abc.abstractmethod
    def solve(self, system, r: Float[Array, "B 6"], b: Float[Array, " nc"]) -> tuple[Float[Array, "B 6"], Any]:
        """``(v, aux)``: v+ of Eq. 2 for the right-hand side ``(r, b)``; ``aux`` is what
        :meth:`multipliers` reuses."""

    @abc.abstractmethod
    def multipliers(self, system, r, b, v, aux) -> tuple[Float[Array, " nc"], Float[Array, ""]]:
        """``(lam, residual)``: the constraint multipliers (rows of ``system.full_constraints``)
        and the relative residual of both block rows of Eq. 2."""

    @abc.abstractmethod
    def projection_step(self, model, cfg, rot, c: Float[Array, " nc"]) -> Float[Array, "B 6"]:
        """dx of least M-norm with ``J dx = -C``: the projection of post-stabilization."""

    def contact_responses(
        self, system, n_bodies: int, body: Int[Array, " K"], rows: Float[Array, "K d 6"], b: Float[Array, " nc"]
    ) -> ContactResponses:
        """Responses to unit impulses along ``rows`` (row (k, j): the wrench ``[force, torque]``
        of a unit impulse on body ``body[k]``, world) with the constraint right-hand side ``b``
        zeroed: ``X = A^-1 [Jc^T; 0]``, one factorization for every row, and ``W = Jc X``."""
        cols = one_body_rows(n_bodies, body, rows)
        x, _ = jax.vmap(lambda col: self.solve(system, col, jnp.zeros_like(b)))(cols)
        x = x.reshape(x.shape[0], -1).T  # (6B, R)
        x_rows = x.reshape(n_bodies, 6, -1)[body]  # (K, 6, R): each row of Jc has its body's 6 entries only
        return ContactResponses(x, jnp.einsum("kdj,kjm->kdm", rows, x_rows).reshape(cols.shape[0], -1))

    def lift(self, system, x: Float[Array, "D R"]) -> Float[Array, "6B R"]:
        """Bodies' velocities ``(6B, R)`` of ``R`` responses in the solver's coordinates (columns)."""
        return x
