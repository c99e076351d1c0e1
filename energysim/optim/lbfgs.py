"""L-BFGS with a strong-Wolfe line search, in mass-scaled coordinates."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.objective import Objective
from energysim.optim.base import Solver, SolverResult


@dataclass(frozen=True)
class LBFGS(Solver):
    """`torch.optim.LBFGS` (strong Wolfe) on y, with x = x0 + (h/m) y per vertex.

    In these coordinates ∇_y E = h M⁻¹ ∇_x E, the velocity residual itself, so L-BFGS's own
    gradient test is exactly the shared stopping rule, and heavy and light vertices are
    equally well scaled.

    Args:
        tol: velocity-residual tolerance in m/s.
        max_iter: most L-BFGS iterations.
        strict: raise instead of warning when `tol` is not reached.
        history_size: number of curvature pairs kept.
    """

    max_iter: int = 500
    history_size: int = 20

    def minimize(self, objective: Objective, x0: Tensor) -> SolverResult:
        x0 = x0.detach()
        scale = (objective.residual_scale * objective.free.to(x0.dtype))[:, None]
        y = torch.zeros_like(x0, requires_grad=True)
        optimizer = torch.optim.LBFGS(
            [y],
            lr=1.0,
            max_iter=self.max_iter,
            max_eval=self.max_iter * 5 // 4 + 25,
            tolerance_grad=self.tol,
            tolerance_change=0.0,
            history_size=self.history_size,
            line_search_fn="strong_wolfe",
        )

        def closure() -> Tensor:
            energy, gradient = objective.energy_and_gradient(x0 + scale * y.detach())
            y.grad = gradient * scale
            return energy.sum()

        optimizer.step(closure)
        iterations = optimizer.state[optimizer._params[0]].get("n_iter", 0)
        x = x0 + scale * y.detach()
        _, gradient = objective.energy_and_gradient(x)
        return self.finish(objective, x, objective.residual(gradient), iterations, 0)
