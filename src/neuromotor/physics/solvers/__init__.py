"""Solvers of Eq. 2 and of post-stabilization, one per module, behind one interface
(:class:`~neuromotor.physics.solvers.base.KKTSolver`), picked by :class:`Solver`."""

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


__all__ = ["KKTSolver", "SOLVERS", "Solver", "get"]
