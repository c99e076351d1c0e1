"""Adam on the free DOFs, stopped by the shared velocity residual."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.objective.objective import Objective
from energysim.solvers.arguments import require_integer, require_real
from energysim.solvers.base import Solver, SolverResult


@dataclass(frozen=True)
class Adam(Solver):
    """`torch.optim.Adam` on positions, halving the learning rate when the energy stops falling.

    First-order: cheap per iteration, but many iterations for a tight residual; a baseline. Each
    update is cut back to the largest fraction every term's `max_step` allows, so obstacles are
    never crossed.

    Args:
        tol: velocity-residual tolerance in m/s.
        max_iter: most Adam iterations.
        strict: raise instead of warning when `tol` is not reached.
        lr: initial learning rate, in m (Adam's steps are about `lr` per coordinate).
        patience: iterations without a new lowest energy before the rate is halved.
    """

    max_iter: int = 5000
    lr: float = 1e-3
    patience: int = 10

    def __post_init__(self) -> None:
        super().__post_init__()
        require_real(self.name, "lr", self.lr, unit="m", above=0.0)
        require_integer(self.name, "patience", self.patience, minimum=0)

    def minimize(self, objective: Objective, x0: Tensor) -> SolverResult:
        self.prepare(objective)
        free = objective.free[:, None].to(x0.dtype)
        x = x0.detach().clone().requires_grad_(True)
        optimizer = torch.optim.Adam([x], lr=self.lr)
        scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(
            optimizer, factor=0.5, patience=self.patience, threshold=0.0
        )
        best = x.detach().clone()
        best_energy = None
        residual = None
        iterations = 0
        for _ in range(self.max_iter):
            energy, gradient = objective.energy_and_gradient(x.detach())
            residual = objective.residual(gradient)
            total = float(energy.sum())
            if best_energy is None or total < best_energy:
                best_energy, best, best_residual = total, x.detach().clone(), residual
            if (residual < self.tol).all():
                break
            iterations += 1
            x.grad = gradient * free
            before = x.detach().clone()
            optimizer.step()
            with torch.no_grad():
                # Adam knows nothing of obstacles: cut its step back to what every term allows
                motion = x - before
                fraction = objective.max_step(before, motion)
                if bool((fraction < 1).any()):
                    x.copy_(before + fraction[:, None, None] * motion)
            scheduler.step(total)
        else:
            energy, gradient = objective.energy_and_gradient(x.detach())
            residual = objective.residual(gradient)
            if float(energy.sum()) > best_energy:
                x, residual = best, best_residual
        return self.finish(objective, x.detach(), residual, iterations, 0)
