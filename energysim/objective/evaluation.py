"""The evaluations of a step objective, as pure functions of its terms: one definition each.

`Objective` calls them eagerly; `energysim.objective.compiled` compiles these same functions with
`torch.compile` (wrapped, never copied), so a compiled evaluation computes what the eager one does.
The step limits they return are unchecked (NaN where a state is not admissible, no data-dependent
branch); the caller checks them (`Objective.max_step`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from energysim.energies.base import EnergyTerm
from energysim.objective import batch_last
from energysim.objective.derivatives import energy_and_gradient as autograd_energy_and_gradient


def shifted(term: EnergyTerm, x: Tensor, anchor: Tensor | None) -> Tensor:
    """Where `term` is evaluated: linear terms (gravity) at x − anchor, which keeps their rounding
    proportional to the displacement (`Objective.anchor`), the others at `x` `[B, n, d]`."""
    return x - anchor if term.is_linear and anchor is not None else x


def total_energy(
    terms: Sequence[EnergyTerm], anchor: Tensor | None, action: Tensor | None, x: Tensor
) -> Tensor:
    """Σ_i E_i(x), shape `[B]`, in J."""
    batched = batch_last.evaluates_batch_last(terms, x)
    total = x.new_zeros(x.shape[0])
    if batched:
        # the gradient goes unused, and the compiler drops it
        total = total + batch_last.element_energy_and_gradient([terms[i] for i in batched], action, x)[0]
    for index, term in enumerate(terms):
        if index not in batched:
            total = total + term(shifted(term, x, anchor), action)
    return total


def term_energies(terms: Sequence[EnergyTerm], action: Tensor | None, x: Tensor) -> Tensor:
    """Every term's E_i(x) at `x` itself (no anchor), `[len(terms), B]`, in J."""
    return torch.stack([term(x, action) for term in terms])


def energy_and_gradient(
    terms: Sequence[EnergyTerm], anchor: Tensor | None, action: Tensor | None, free: Tensor, x: Tensor
) -> tuple[Tensor, Tensor]:
    """E(x) `[B]` in J and ∇E(x) `[B, n, d]` in N, zero on fixed vertices (`free` `[n]` bool).

    Terms that declare `has_gradient_kernel` give theirs in closed form; the rest share one
    backward pass (never traced by the compiled functions, which take only terms with kernels).
    """
    batched = batch_last.evaluates_batch_last(terms, x)
    total = x.new_zeros(x.shape[0])
    gradient = torch.zeros_like(x)
    if batched:
        total, gradient = batch_last.element_energy_and_gradient([terms[i] for i in batched], action, x)
    others = []
    for index, term in enumerate(terms):
        if index in batched:
            continue
        if term.has_gradient_kernel:
            value, term_gradient = term.value_and_gradient(shifted(term, x, anchor), action)
            total = total + value
            gradient = gradient + term_gradient
        else:
            others.append(term)
    if others:
        value, rest = autograd_energy_and_gradient(lambda y: total_energy(others, anchor, action, y), x)
        total = total + value
        gradient = gradient + rest
    return total, gradient * free[:, None].to(gradient.dtype)


def step_limit(terms: Sequence[EnergyTerm], x: Tensor, direction: Tensor) -> Tensor:
    """The largest fraction of `direction` every term allows from `x`, `[B]`, at most 1, unchecked
    (`EnergyTerm.step_limit`): NaN where `x` is not admissible."""
    limit = x.new_ones(x.shape[0])
    for term in terms:
        term_limit = term.step_limit(x, direction)
        if term_limit is not None:
            limit = torch.minimum(limit, term_limit)
    return limit


def trial(
    terms: Sequence[EnergyTerm],
    anchor: Tensor | None,
    action: Tensor | None,
    free: Tensor,
    residual_scale: Tensor,
    x: Tensor,
    direction: Tensor,
    gradient: Tensor,
    judge: Callable[..., tuple[Tensor, ...]],
    judged_with: tuple,
) -> tuple[object, ...]:
    """A line search's first trial from `x` along `direction` (`gradient` = ∇E(x)): the unchecked
    step limit `[B]`, where it lands `[B, n, d]`, E `[B]` and ∇E `[B, n, d]` there, the slopes of E
    along `direction` at both ends `[B]`, the velocity residual there `[B]`, where the element
    terms are evaluated batch-last, the curvature hints of an iteration from `x` to there
    (`batch_last.curvature_hints`; None otherwise), and the search's verdict on the trial,
    `judge(limit, slope, E there, slope there, *judged_with)` (`LineTrial`)."""
    limit = step_limit(terms, x, direction)
    trial_x = x + limit[:, None, None] * direction
    energy, trial_gradient = energy_and_gradient(terms, anchor, action, free, trial_x)
    slope = (gradient * direction).sum(dim=(-1, -2))
    trial_slope = (trial_gradient * direction).sum(dim=(-1, -2))
    residual = (trial_gradient * residual_scale[:, None]).abs().amax(dim=(-1, -2))
    batched = batch_last.evaluates_batch_last(terms, x)
    hints = batch_last.curvature_hints(terms, x, trial_x) if batched else None
    verdict = judge(limit, slope, energy, trial_slope, *judged_with)
    return limit, trial_x, energy, trial_gradient, slope, trial_slope, residual, hints, verdict


def cut_targets(
    terms: Sequence[EnergyTerm], origin: Tensor, targets: Sequence[Tensor]
) -> tuple[Tensor, Tensor]:
    """Each target moved back towards `origin` to its unchecked step limit, `[k, B, n, d]`, and the
    limits, `[k, B]`."""
    cuts, limits = [], []
    for target in targets:
        motion = target - origin
        limit = step_limit(terms, origin, motion)
        cuts.append(origin + limit[:, None, None] * motion)
        limits.append(limit)
    return torch.stack(cuts), torch.stack(limits)


def cut_back(
    terms: Sequence[EnergyTerm],
    anchor: Tensor | None,
    action: Tensor | None,
    origin: Tensor,
    targets: Sequence[Tensor],
) -> tuple[Tensor, Tensor, Tensor]:
    """Each target moved back towards `origin` to its unchecked step limit, `[k, B, n, d]`; E at
    `origin` and at every cut, `[k + 1, B]`; and the limits, `[k, B]` (`cut_targets`)."""
    cuts, limits = cut_targets(terms, origin, targets)
    energies = [total_energy(terms, anchor, action, point) for point in (origin, *cuts.unbind(0))]
    return cuts, torch.stack(energies), limits
