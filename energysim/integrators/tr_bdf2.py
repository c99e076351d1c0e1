"""TR-BDF2 where it is safe: its two stages, and the energy check that falls back to implicit Euler
where the trapezoidal stage overshoots (a scrambled or flattened body)."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable

import torch
from torch import Tensor

from energysim.integrators.common import ENERGY_ROUNDING, state_energies, touching
from energysim.model.scene import Scene
from energysim.solvers import SolverResult
from energysim.solvers.base import ConvergenceError, ConvergenceWarning


def combined(first: SolverResult, second: SolverResult) -> SolverResult:
    """One report for a step made of two solves: counts add up, the worse residual stands (per
    entry too, where both report them)."""
    both = first.residuals is not None and second.residuals is not None
    return dataclasses.replace(
        second,
        iterations=first.iterations + second.iterations,
        grad_evals=first.grad_evals + second.grad_evals,
        hvp_evals=first.hvp_evals + second.hvp_evals,
        energy_evals=first.energy_evals + second.energy_evals,
        residual=max(first.residual, second.residual),
        converged=first.converged and second.converged,
        stalled=first.stalled or second.stalled,
        residuals=torch.maximum(first.residuals, second.residuals) if both else None,
        entry_iterations=(
            first.entry_iterations + second.entry_iterations
            if first.entry_iterations is not None and second.entry_iterations is not None
            else None
        ),
    )


# The most energy a TR-BDF2 step may gain, as a fraction of the kinetic plus deformation energy.
# On a nonlinear body the scheme is not exactly energy-stable, and its truncation error moves a
# little energy either way: the swinging cantilever gains at most 0.2 % of it in a step at h = 1/24 s.
# The trapezoidal overshoot on a flattened body gains 20–500 %.
ENERGY_GAIN_LIMIT = 1e-2


def gains_energy(
    scene: Scene,
    before: tuple[Tensor, Tensor],
    after: tuple[Tensor, Tensor],
    action: Tensor | None,
    residual: float,
    compiled: bool = False,
) -> Tensor:
    """Which entries end the step with clearly more energy than they started with, `[B]` bool.

    With the action held over the step the scene is conservative (friction only dissipates): an
    exact implicit-Euler step never gains energy, nor does TR-BDF2 on a linear system (its
    amplification matrix is normal with spectral radius ≤ 1). Allowed: the work of the solve's
    residual, |vᵀMρ| ≤ ρ Σ m|v|, rounding, and `ENERGY_GAIN_LIMIT` of the energy of motion and
    deformation for TR-BDF2's own truncation error on a nonlinear body. More than that is the
    trapezoidal stage overshooting on a stiff, strongly nonlinear state (a scrambled or flattened
    body)."""
    (x0, v0), (x1, v1) = before, after
    energy_before, motion_before, scale_before = state_energies(scene, x0, v0, action, compiled)
    energy_after, motion_after, scale_after = state_energies(scene, x1, v1, action, compiled)
    work = residual * (scene.vertex_mass[:, None] * v1.detach().abs()).sum(dim=(-1, -2))
    allowance = (
        work
        + ENERGY_ROUNDING * torch.maximum(scale_before, scale_after)
        + ENERGY_GAIN_LIMIT * torch.maximum(motion_before, motion_after)
    )
    # written so that a NaN energy (an overflowing stage) counts as a gain, not as safe
    return ~(energy_after <= energy_before + allowance)


def second_order_where_safe(
    scene: Scene,
    x_prev: Tensor,
    v_prev: Tensor,
    action: Tensor | None,
    implicit_euler: Callable[[Tensor, Tensor, Tensor | None], tuple[Tensor, Tensor, SolverResult]],
    tr_bdf2: Callable[[Tensor, Tensor, Tensor | None], tuple[Tensor, Tensor, Tensor, SolverResult]],
    *,
    compiled: bool = False,
) -> tuple[Tensor, Tensor, SolverResult]:
    """TR-BDF2 for the batch entries where it is safe, implicit Euler for the others (`compiled`:
    the energy check evaluates the terms through a compiled function).

    Implicit Euler takes over an entry that
    - touches an obstacle at the step's start or after either stage: a second-order step rebuilds
      the velocity from the kink an impact leaves in the positions (v_{n+1} = (3x_{n+1} − 4x_½ +
      x_n)/h) and turns the impact into a bounce, while contact and friction are first order anyway;
    - would end the step with more energy than it started with (`gains_energy`): the trapezoidal
      stage takes the force at the step's start at face value, which on a scrambled, flattened or
      inverted body is huge and overshoots (a flattened box went from 290 J to 539 J in one step);
    - or whose TR-BDF2 solves did not converge (they are then all redone, and only the implicit-Euler
      solve reports).
    """

    def entries(rows: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        return x_prev[rows], v_prev[rows], None if action is None else action[rows]

    euler = touching(scene, x_prev, action)
    pieces: list[tuple[Tensor, Tensor, Tensor]] = []
    reports: list[SolverResult] = []
    rows = torch.nonzero(~euler).reshape(-1)
    if rows.numel():
        x0, v0, act = entries(rows)
        try:
            with warnings.catch_warnings():
                # an attempt that does not converge is discarded and redone, not reported
                warnings.simplefilter("ignore", ConvergenceWarning)
                x_next, v_next, x_half, report = tr_bdf2(x0, v0, act)
        except ConvergenceError:
            euler[rows] = True
        else:
            if report.converged:
                unsafe = touching(scene, x_half, act) | touching(scene, x_next, act)
                unsafe |= gains_energy(scene, (x0, v0), (x_next, v_next), act, report.residual, compiled)
            else:
                unsafe = torch.ones_like(rows, dtype=torch.bool)
            euler[rows[unsafe]] = True
            kept = ~unsafe
            pieces.append((rows[kept], x_next[kept], v_next[kept]))
            reports.append(report)
    rows = torch.nonzero(euler).reshape(-1)
    if rows.numel():
        x_next, v_next, report = implicit_euler(*entries(rows))
        pieces.append((rows, x_next, v_next))
        reports.append(report)
    if len(pieces) == 1 and pieces[0][0].numel() == x_prev.shape[0]:
        return pieces[0][1], pieces[0][2], reports[0]
    order = torch.argsort(torch.cat([piece[0] for piece in pieces]))
    x_next = torch.cat([piece[1] for piece in pieces])[order]
    v_next = torch.cat([piece[2] for piece in pieces])[order]
    stats = reports[0] if len(reports) == 1 else combined(*reports)
    return x_next, v_next, dataclasses.replace(stats, x=x_next.detach())
