"""What every optimizer shares: the result record, the solver contract, failure reporting, and
keeping an iterate's tensors in the layout the compiled evaluations were traced with.

The line search is `energysim.solvers.line_search`, the stop for lack of progress
`energysim.solvers.stagnation`."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.objective.objective import Objective
from energysim.solvers.arguments import require_bool, require_integer, require_real


def in_layout_of(like: Tensor, value: Tensor) -> Tensor:
    """`value` in the memory layout of `like` (a copy only where the two differ): the compiled calls
    guard on their inputs' strides, and an iterate's gradient that came back in another layout
    (batch-last from one evaluation, batch-major from another) would compile the next calls anew."""
    if value.stride() == like.stride():
        return value
    return torch.empty_like(like).copy_(value)


class ConvergenceWarning(RuntimeWarning):
    """A solve stopped before the velocity residual reached the solver's tolerance."""


class ConvergenceError(RuntimeError):
    """A solve failed (strict mode, or a non-finite iterate that can never be returned)."""


@dataclass(frozen=True)
class SolverResult:
    """The outcome of one minimisation.

    Attributes:
        x: the minimiser found, shape `[B, n, d]`, in m.
        iterations: outer iterations taken (Newton steps, L-BFGS or Adam iterations).
        grad_evals: energy-and-gradient evaluations.
        hvp_evals: Hessian-vector products (CG iterations for Newton–CG).
        energy_evals: energy-only evaluations (line searches).
        residual: final velocity residual ‖h M⁻¹ ∇E‖∞ in m/s, the worst over the batch.
        converged: whether every batch entry reached `tol`.
        solver: the solver's name.
        tol: the tolerance in m/s.
        stalled: whether some entry that did not reach `tol` was stopped before `max_iter` because
            its iterations no longer made progress beyond the rounding of E and ∇E (`Stagnation`).
        residuals: the final velocity residual of each batch entry `[B]`, in m/s, where the solver
            reports them (None for an unrolled solve).
        entry_iterations: the iterations each batch entry took part in `[B]`, int64, where the
            solver counts them (Newton–CG, L-BFGS): an entry stops costing once it has converged.
    """

    x: Tensor
    iterations: int
    grad_evals: int
    hvp_evals: int
    energy_evals: int
    residual: float
    converged: bool
    solver: str
    tol: float
    stalled: bool = False
    residuals: Tensor | None = None
    entry_iterations: Tensor | None = None

    def summary(self) -> str:
        """One line with every figure, for logs and warnings."""
        line = (
            f"{self.solver}: {'converged' if self.converged else 'NOT converged'} in {self.iterations} "
            f"iterations, velocity residual {self.residual:.3e} m/s (tol {self.tol:.1e}), "
            f"{self.grad_evals} gradient evals, {self.hvp_evals} HVPs, {self.energy_evals} energy evals"
        )
        if self.stalled and not self.converged:
            line += (
                "; stopped early: no step reduced the residual or the energy beyond their rounding "
                "(the residual is at the floor this precision reaches; ask for a larger tol)"
            )
        return line


@dataclass(frozen=True)
class Solver:
    """Base of the optimizers. Every solver stops on the same measure, the velocity residual.

    Args:
        tol: stop when ‖h M⁻¹ ∇E‖∞ < tol, in m/s.
        max_iter: most outer iterations.
        strict: raise `ConvergenceError` when `tol` is not reached, instead of warning.
        compile: evaluate the objective through `torch.compile`d functions (`energysim.objective.compiled`):
            the same numbers at a fraction of the cost for small bodies, after a compilation of
            seconds per scene. Off by default.
    """

    tol: float = 1e-5
    max_iter: int = 100
    strict: bool = False
    compile: bool = False

    def __post_init__(self) -> None:
        require_real(self.name, "tol", self.tol, unit="m/s", above=0.0)
        require_integer(self.name, "max_iter", self.max_iter, minimum=1)
        require_bool(self.name, "strict", self.strict)
        require_bool(self.name, "compile", self.compile)

    @property
    def name(self) -> str:
        return type(self).__name__

    def prepare(self, objective: Objective) -> Objective:
        """`objective`, set to evaluate through compiled functions if this solver's `compile` says so."""
        objective.compiled = objective.compiled or self.compile
        return objective

    def minimize(self, objective: Objective, x0: Tensor) -> SolverResult:  # pragma: no cover - abstract
        """Minimise `objective` from `x0` (shape `[B, n, d]`); fixed vertices keep their `x0` value."""
        raise NotImplementedError

    def finish_unrolled(self, x: Tensor, residual: float, iterations: int) -> SolverResult:
        """The report of an unrolled (recorded) Newton solve; warns or raises like `finish`."""
        result = SolverResult(
            x=x.detach(),
            iterations=iterations,
            grad_evals=iterations + 1,
            hvp_evals=0,
            energy_evals=0,
            residual=residual,
            converged=residual < self.tol,
            solver=f"unrolled Newton (tol of {self.name})",
            tol=self.tol,
        )
        return self._report(result)

    def _report(self, result: SolverResult) -> SolverResult:
        """Warn, or raise when strict, if `result` did not converge; return it."""
        if not result.converged:
            if self.strict:
                raise ConvergenceError(result.summary())
            warnings.warn(result.summary(), ConvergenceWarning, stacklevel=4)
        return result

    def finish(
        self,
        objective: Objective,
        x: Tensor,
        residual: Tensor,
        iterations: int,
        hvps: int,
        stopped: Tensor | None = None,
        entry_iterations: Tensor | None = None,
    ) -> SolverResult:
        """Build the result; raise on non-finite iterates; warn or raise when not converged.
        `stopped`: the entries `[B]` stopped early for lack of progress, if any; `entry_iterations`:
        the iterations each entry took part in `[B]`, if counted."""
        worst = float(residual.max()) if residual.numel() else 0.0
        stalled = stopped is not None and bool((stopped & (residual >= self.tol)).any())
        result = SolverResult(
            x=x.detach(),
            iterations=iterations,
            grad_evals=objective.grad_evals,
            hvp_evals=hvps,
            energy_evals=objective.energy_evals,
            residual=worst,
            converged=bool((residual < self.tol).all()),
            solver=self.name,
            tol=self.tol,
            stalled=stalled,
            residuals=residual.detach(),
            entry_iterations=entry_iterations,
        )
        if not torch.isfinite(x).all() or not torch.isfinite(residual).all():
            raise ConvergenceError("non-finite positions or residual: " + result.summary())
        return self._report(result)
