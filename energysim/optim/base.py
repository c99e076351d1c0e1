"""What every optimizer shares: the result record, failure reporting, and the line search."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.objective import Objective


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

    def summary(self) -> str:
        """One line with every figure, for logs and warnings."""
        return (
            f"{self.solver}: {'converged' if self.converged else 'NOT converged'} in {self.iterations} "
            f"iterations, velocity residual {self.residual:.3e} m/s (tol {self.tol:.1e}), "
            f"{self.grad_evals} gradient evals, {self.hvp_evals} HVPs, {self.energy_evals} energy evals"
        )


@dataclass(frozen=True)
class Solver:
    """Base of the optimizers. Every solver stops on the same measure, the velocity residual.

    Args:
        tol: stop when ‖h M⁻¹ ∇E‖∞ < tol, in m/s.
        max_iter: most outer iterations.
        strict: raise `ConvergenceError` when `tol` is not reached, instead of warning.
    """

    tol: float = 1e-5
    max_iter: int = 100
    strict: bool = False

    def __post_init__(self) -> None:
        if not (self.tol > 0):
            raise ValueError(f"tol must be > 0 m/s, got {self.tol}")
        if self.max_iter < 1:
            raise ValueError(f"max_iter must be >= 1, got {self.max_iter}")

    @property
    def name(self) -> str:
        return type(self).__name__

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
        self, objective: Objective, x: Tensor, residual: Tensor, iterations: int, hvps: int
    ) -> SolverResult:
        """Build the result; raise on non-finite iterates; warn or raise when not converged."""
        worst = float(residual.max()) if residual.numel() else 0.0
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
        )
        if not torch.isfinite(x).all() or not torch.isfinite(residual).all():
            raise ConvergenceError("non-finite positions or residual: " + result.summary())
        return self._report(result)


def _rounding(x: Tensor, energy: Tensor) -> Tensor:
    # a decrease within a few ulps of |E| counts as no increase
    return 64 * torch.finfo(x.dtype).eps * energy.abs()


def _sufficient_decrease(
    energy: Tensor, trial: Tensor, step: Tensor, slope: Tensor, rounding: Tensor, constant: float
) -> Tensor:
    return torch.isfinite(trial) & (trial <= energy + constant * step * slope + rounding)


@dataclass(frozen=True)
class LineStep:
    """Where a line search along one direction ended, per batch entry.

    Attributes:
        step: the accepted fractions of the direction `[B]` (0 where none was accepted).
        x: the new positions `[B, n, d]`, in m.
        energy: E there `[B]`, in J.
        gradient: ∇E there `[B, n, d]`, in N.
        residual: the velocity residual there `[B]`, in m/s.
        unjudged: entries taken whole because the energy could not judge the step `[B]`.
    """

    step: Tensor
    x: Tensor
    energy: Tensor
    gradient: Tensor
    residual: Tensor
    unjudged: Tensor


def line_step(
    objective: Objective,
    x: Tensor,
    energy: Tensor,
    gradient: Tensor,
    direction: Tensor,
    *,
    sufficient_decrease: float = 1e-4,
) -> LineStep:
    """One line-search step from `x` along `direction`, with the energy and gradient where it ends.

    Starts from the largest fraction every term allows (`objective.max_step`). That first trial is
    evaluated with its gradient, which the solver needs next anyway: when every entry accepts it (the
    common case near a minimum), the search costs no energy evaluation of its own. Otherwise it
    backtracks (`backtracking_line_search`) and evaluates the gradient where it stopped.
    """
    initial = objective.max_step(x, direction)
    slope = (gradient * direction).sum(dim=(-1, -2))
    rounding = _rounding(x, energy)
    unjudged = -slope * initial <= rounding
    trial_x = x + initial[:, None, None] * direction
    trial_energy, trial_gradient = objective.energy_and_gradient(trial_x)
    decrease = _sufficient_decrease(energy, trial_energy, initial, slope, rounding, sufficient_decrease)
    accepted = unjudged | decrease
    if bool(accepted.all()):
        return LineStep(
            initial, trial_x, trial_energy, trial_gradient, objective.residual(trial_gradient), unjudged
        )
    step, _, unjudged = backtracking_line_search(
        objective, x, energy, gradient, direction, initial, sufficient_decrease=sufficient_decrease
    )
    x_new = x + step[:, None, None] * direction
    new_energy, new_gradient = objective.energy_and_gradient(x_new)
    return LineStep(step, x_new, new_energy, new_gradient, objective.residual(new_gradient), unjudged)


def backtracking_line_search(
    objective: Objective,
    x: Tensor,
    energy: Tensor,
    gradient: Tensor,
    direction: Tensor,
    initial_step: Tensor,
    *,
    sufficient_decrease: float = 1e-4,
    max_halvings: int = 40,
) -> tuple[Tensor, Tensor, Tensor]:
    """Armijo backtracking, per batch entry, from the largest admissible step.

    Near convergence the energy change falls below the energy's rounding error, so a decrease
    within a few ulps of |E| counts as no increase; and where even the full step's predicted
    decrease is below that level, the energy cannot judge the step at all: it is taken whole and
    flagged, so that the caller can judge it by the gradient instead.

    Args:
        x, gradient, direction: shape `[B, n, d]`; energy, initial_step: shape `[B]`.

    Returns:
        step fractions `[B]` (0 where no step was accepted), the energies there `[B]`, and which
        entries were taken unjudged `[B]`.
    """
    slope = (gradient * direction).sum(dim=(-1, -2))
    step = initial_step.clone()
    rounding = _rounding(x, energy)
    unjudged = -slope * initial_step <= rounding
    accepted = unjudged.clone()
    new_energy = energy.clone()
    for _ in range(max_halvings):
        trial = objective.energy(x + step[:, None, None] * direction)
        ok = _sufficient_decrease(energy, trial, step, slope, rounding, sufficient_decrease) & ~accepted
        new_energy = torch.where(ok, trial, new_energy)
        accepted = accepted | ok
        if accepted.all():
            break
        step = torch.where(accepted, step, 0.5 * step)
    step = torch.where(accepted, step, torch.zeros_like(step))
    return step, new_energy, unjudged
