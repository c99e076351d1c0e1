"""L-BFGS, batched, with the shared backtracking line search (so it respects every term's `max_step`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.energies.base import VertexDiagonalEnergy
from energysim.objective.objective import Objective
from energysim.solvers.arguments import require_integer
from energysim.solvers.base import Solver, SolverResult
from energysim.solvers.line_search import line_step
from energysim.solvers.stagnation import LBFGS_STALL_ITERATIONS, Stagnation


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(dim=(-1, -2))


def _initial_inverse_hessian(objective: Objective, x: Tensor) -> Tensor:
    """A diagonal guess D of H⁻¹ per vertex, `[n, 1]`: h²/m where the inertia term is present (its
    exact inverse Hessian, which dominates at small steps), else h/m (scaled by the first step)."""
    diagonal = None
    for term in objective.terms:
        if isinstance(term, VertexDiagonalEnergy):
            value = term.hessian_diagonal()
            diagonal = value if diagonal is None else diagonal + value
    if diagonal is None:
        return objective.residual_scale[:, None].to(x)
    return 1.0 / diagonal[:, None].to(x)


@dataclass(frozen=True)
class LBFGS(Solver):
    """Limited-memory BFGS with an Armijo backtracking line search, per batch entry.

    The two-loop recursion starts from the diagonal D = h²/m (the inertia term's exact inverse
    Hessian), scaled each iteration by sᵀy / yᵀDy, so the first step is already well scaled and
    heavy and light vertices are treated alike. Each line search starts from the largest step
    every term allows (`max_step`: obstacles), so contact scenes stay intersection-free. Pairs
    with sᵀy ≤ 0 (possible on nonconvex energies without a Wolfe search) are skipped; an entry whose
    line search fails restarts from D, and stops if that fails too.

    Args:
        tol: velocity-residual tolerance in m/s.
        max_iter: most iterations.
        strict: raise instead of warning when `tol` is not reached.
        history_size: number of curvature pairs kept.
    """

    max_iter: int = 500
    history_size: int = 20

    def __post_init__(self) -> None:
        super().__post_init__()
        require_integer(self.name, "history_size", self.history_size, minimum=1)

    def minimize(self, objective: Objective, x0: Tensor) -> SolverResult:
        self.prepare(objective)
        x = x0.detach().clone()
        free = objective.free[:, None].to(x.dtype)
        inverse_diagonal = _initial_inverse_hessian(objective, x) * free
        energy, gradient = objective.energy_and_gradient(x)
        residual = objective.residual(gradient)
        history: list[tuple[Tensor, Tensor, Tensor]] = []  # (s, y, 1/sᵀy or 0 where skipped)
        scale = torch.ones_like(energy)
        restarted = torch.zeros_like(energy, dtype=torch.bool)
        stalled = torch.zeros_like(restarted)
        stagnation = Stagnation.start(x, energy, residual, LBFGS_STALL_ITERATIONS)
        iterations = 0
        noise = None  # the energy's noise, once a line search has measured it (`line_step`)
        taken = torch.zeros_like(residual, dtype=torch.int64)  # iterations per entry
        for _ in range(self.max_iter):
            active = (residual >= self.tol) & ~stalled
            if not active.any():
                break
            iterations += 1
            taken = taken + active
            direction = -self._two_loop(gradient, history, inverse_diagonal, scale) * active[:, None, None]
            downhill = _dot(gradient, direction) < 0
            direction = torch.where(downhill[:, None, None], direction, -inverse_diagonal * gradient)
            search = line_step(objective, x, energy, gradient, direction, noise=noise)
            noise = search.noise
            failed = active & (search.step == 0)
            stalled = stalled | (failed & restarted)
            restarted = failed
            # as in Newton–CG: a step the energy cannot judge stands only if the residual fell
            worse = active & search.unjudged & (search.residual >= residual)
            stalled = stalled | worse
            moved = active & ~failed & ~worse
            s = (search.x - x) * moved[:, None, None]
            y = (search.gradient - gradient) * moved[:, None, None]
            curvature = _dot(s, y)
            usable = moved & (curvature > 1e-12 * _dot(s, s).sqrt() * _dot(y, y).sqrt())
            if usable.any():
                history.append((s, y, torch.where(usable, 1.0 / curvature.where(usable, 1.0), 0.0)))
                weighted = _dot(y, inverse_diagonal * y).clamp_min(torch.finfo(x.dtype).tiny)
                scale = torch.where(usable, curvature / weighted, scale)
                if len(history) > self.history_size:
                    history.pop(0)
            if failed.any():
                # forget the curvature of entries whose step failed: restart from D
                history = [(s_, y_, torch.where(failed, 0.0, rho)) for s_, y_, rho in history]
                scale = torch.where(failed, torch.ones_like(scale), scale)
            keep = ~moved[:, None, None]
            x = torch.where(keep, x, search.x)
            gradient = torch.where(keep, gradient, search.gradient)
            new_energy = torch.where(moved, search.energy, energy)
            residual = torch.where(moved, search.residual, residual)
            stagnation, stuck = stagnation.update(active, energy, x, new_energy, residual, search.allowance)
            energy = new_energy
            stalled = stalled | stuck
        x, residual = stagnation.best_of(x, residual, stalled)
        return self.finish(objective, x, residual, iterations, 0, stalled, taken)

    @staticmethod
    def _two_loop(
        gradient: Tensor,
        history: list[tuple[Tensor, Tensor, Tensor]],
        inverse_diagonal: Tensor,
        scale: Tensor,
    ) -> Tensor:
        """H_k ∇E by the two-loop recursion over the stored pairs, per batch entry."""
        q = gradient.clone()
        alphas = []
        for s, y, rho in reversed(history):
            alpha = rho * _dot(s, q)
            q = q - alpha[:, None, None] * y
            alphas.append(alpha)
        r = scale[:, None, None] * inverse_diagonal * q
        for (s, y, rho), alpha in zip(history, reversed(alphas), strict=True):
            beta = rho * _dot(y, r)
            r = r + (alpha - beta)[:, None, None] * s
        return r
