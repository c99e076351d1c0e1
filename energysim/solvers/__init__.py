"""Optimizers for the step objective. All share one contract and one stopping rule.

`solver.minimize(objective, x0) -> SolverResult`, stopping when the velocity residual
‖h M⁻¹ ∇E‖∞ falls below `tol` (m/s).
"""

from energysim.solvers.adam import Adam
from energysim.solvers.base import ConvergenceError, ConvergenceWarning, Solver, SolverResult
from energysim.solvers.lbfgs import LBFGS
from energysim.solvers.newton_cg import NewtonCG

__all__ = ["LBFGS", "Adam", "ConvergenceError", "ConvergenceWarning", "NewtonCG", "Solver", "SolverResult"]
