"""Optimizers for the step objective. All share one contract and one stopping rule.

`solver.minimize(objective, x0) -> SolverResult`, stopping when the velocity residual
‖h M⁻¹ ∇E‖∞ falls below `tol` (m/s).
"""

from energysim.optim.adam import Adam
from energysim.optim.base import ConvergenceError, ConvergenceWarning, Solver, SolverResult
from energysim.optim.lbfgs import LBFGS
from energysim.optim.newton_cg import NewtonCG

__all__ = ["LBFGS", "Adam", "ConvergenceError", "ConvergenceWarning", "NewtonCG", "Solver", "SolverResult"]
