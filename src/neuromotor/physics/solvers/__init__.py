"""Solvers of Eq. 2 and of post-stabilization behind one interface
(:class:`~neuromotor.physics.solvers.base.KKTSolver`), picked by :class:`Solver`: one per
module, except :class:`BranchSolver`, the null-space solver's batched twin, which lives beside
it in ``nullspace.py`` (it only swaps the factorization for :mod:`.branch`'s)."""

from __future__ import annotations

from neuromotor.physics.solvers.base import KKTSolver, Solver
from neuromotor.physics.solvers.dense import DenseSolver
from neuromotor.physics.solvers.nullspace import BranchSolver, NullSpaceSolver
from neuromotor.physics.solvers.tree import TreeSolver

SOLVERS: dict[Solver, KKTSolver] = {
    Solver.NULLSPACE: NullSpaceSolver(),
    Solver.BRANCH: BranchSolver(),
    Solver.TREE: TreeSolver(),
    Solver.DENSE: DenseSolver(),
}


def get(solver: Solver | str) -> KKTSolver:
    """The solver for an option (a :class:`Solver` or its string)."""
    return SOLVERS[Solver(solver)]


def uses_lapack(solver: Solver | str, driven: tuple[int, ...] = (), free_root: bool = False) -> bool:
    """Whether a step calls LAPACK: the dense solver always; the null-space solvers where the
    root floats or joints are driven (their dense LU and Cholesky fallback); the tree solver never.
    XLA:CPU can deadlock when batched LAPACK calls run on several CPU devices at once, so batches
    of such steps stay on one CPU device (:func:`neuromotor.studies.sweep.runner.batch_mesh`)."""
    solver = Solver(solver)
    if solver is Solver.DENSE:
        return True
    return solver in (Solver.NULLSPACE, Solver.BRANCH) and (bool(free_root) or bool(driven))


__all__ = ["KKTSolver", "SOLVERS", "Solver", "get", "uses_lapack"]
