"""The line search every optimizer shares: one step along a direction, judged by the energy where its
rounding allows and by the directional derivatives where it does not, with the rounding noise of E
measured where it matters."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from energysim.objective.objective import Objective
from energysim.solvers.energy_rounding import NOISE_SAMPLES, noise_allowance, rounding_allowance, ulps_of


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
        unjudged: entries taken whole because neither the energy nor its slope along the step could
            judge it `[B]`.
        allowance: the rounding of E the search allowed for `[B]`, in J: 64 ulps of |E|, or the
            measured noise (`energy_rounding.rounding_allowance`) where it was measured.
        noise: `NOISE_ALLOWANCE` × the noise of E (`energy_noise`) `[B]`, in J, where this search
            measured it or was given it; NaN for entries it was not measured for, None where it
            was measured for none. A solver passes it to its next searches (`line_step`'s
            `noise`), which then measure only the entries still without one.
        hints: the curvature hints of the iteration from the search's start to `x` where the trial gave
            them (`LineTrial.hints`) and every entry took it, or those that refused it searched again
            on an objective of their own (`restrict`; their hints from that search); None otherwise.
    """

    step: Tensor
    x: Tensor
    energy: Tensor
    gradient: Tensor
    residual: Tensor
    unjudged: Tensor
    allowance: Tensor
    noise: Tensor | None = None
    hints: tuple[Tensor, ...] | None = None


# A predicted decrease above this fraction of |E| is far above any rounding noise measured relative
# to |E| (the worst, a stiff rotated body, is ~1e-10 |E|). That bound fails where E itself nearly
# vanishes at the minimum while its terms do not: an unloaded body at rest, whose elastic energy is
# a sum of terms of size μV that cancel to 0. On the 3×3×3 box of E = 1e5 Pa restored from a random
# scramble, |E| is 4e-13 J where the residual is 2.8e-8 m/s, its noise 4e-12 J, and the Newton
# step's predicted decrease 1e-14 J: far below the noise, and above 1e-6 |E|. So the noise is also
# measured wherever the directional derivatives accept the trial that the energy refuses (a
# disagreement that rounding explains); only a trial that both refuse fails on its merits unmeasured
# (measuring costs `NOISE_SAMPLES` energy evaluations).
NOISE_RELEVANT_DECREASE = 1e-6


def _noise_may_matter(energy: Tensor, slope: Tensor, step: Tensor, slope_accepts: Tensor) -> Tensor:
    return (-slope * step <= NOISE_RELEVANT_DECREASE * energy.abs()) | slope_accepts


def _slope_decrease(slope: Tensor, trial_slope: Tensor, constant: float) -> Tensor:
    # Armijo on the trapezoidal estimate ½t(φ'(0) + φ'(t)) of the energy change, exact for a
    # quadratic φ. Directional derivatives carry none of the energy's cancellation: it is how a
    # step is judged when the energy change is below the energy's noise.
    return 0.5 * (slope + trial_slope) <= constant * slope


def _armijo(
    energy: Tensor,
    slope: Tensor,
    rounding: Tensor,
    constant: float,
    trial: Tensor,
    step: Tensor,
    trial_slope: Tensor,
) -> tuple[Tensor, Tensor]:
    # Armijo's test, and where it passes only thanks to the allowance for rounding (E did not fall
    # as it must). Where the predicted decrease is above the rounding, the energy judges the step,
    # and a trial within the allowance passes only where E still falls at it: the rounding must not
    # let through a step past the minimum along the direction (twice the way to it leaves E where
    # it was, and a solve that takes such steps makes no progress). (`_sufficient_decrease` without
    # and with the allowance, sharing their operations.)
    bound = energy + constant * step * slope
    finite = torch.isfinite(trial)
    strict = finite & (trial <= bound)
    within = finite & (trial <= bound + rounding) & ~strict
    by_energy = -slope * step > rounding
    return strict | (within & (~by_energy | (trial_slope <= 0))), within


def _overshot(
    slope: Tensor,
    trial_slope: Tensor,
    unjudged: Tensor,
    slope_decrease: Tensor,
    decrease: Tensor,
    within: Tensor,
) -> Tensor:
    # the entries whose trial went past the minimum along the direction: refused by the trapezoid
    # where the energy cannot judge, or passed by the energy on the allowance alone
    beyond = ~unjudged & ~decrease & within
    return ((unjudged & ~slope_decrease) | beyond) & (slope < 0) & (trial_slope > slope)


def _first_verdict(
    step: Tensor, slope: Tensor, trial_energy: Tensor, trial_slope: Tensor, energy: Tensor, constant: float
) -> tuple[Tensor, ...]:
    # `line_step`'s first judgement of its trial, evaluated within the trial's compiled call
    # (`Objective.trial`'s `judge`): whether it settles the search (every entry takes the trial as
    # it is: none refuses it, none needs the noise measured, none overshot), `LineStep.unjudged`
    # for that case, and what the search goes on from where it does not: the allowance, the
    # entries the energy cannot judge, the trapezoid's and Armijo's verdicts, and the doubtful ones
    rounding = ulps_of(energy)
    unjudged = -slope * step <= rounding
    slope_decrease = _slope_decrease(slope, trial_slope, constant)
    decrease, within = _armijo(energy, slope, rounding, constant, trial_energy, step, trial_slope)
    doubtful = ~decrease & _noise_may_matter(energy, slope, step, slope_decrease)
    overshot = _overshot(slope, trial_slope, unjudged, slope_decrease, decrease, within)
    settled = ~(doubtful | overshot).any() & (unjudged | decrease).all()
    taken_unjudged = unjudged & ~(decrease & slope_decrease)
    return settled, taken_unjudged, rounding, unjudged, slope_decrease, decrease, within, doubtful


def line_step(
    objective: Objective,
    x: Tensor,
    energy: Tensor,
    gradient: Tensor,
    direction: Tensor,
    *,
    sufficient_decrease: float = 1e-4,
    noise: Tensor | None = None,
    restrict: Callable[[Tensor], Objective] | None = None,
) -> LineStep:
    """One line-search step from `x` along `direction`, with the energy and gradient where it ends.

    Starts from the largest fraction every term allows (`objective.trial`, one compiled call where the
    objective compiles). That first trial is evaluated with its gradient, which the solver needs next
    anyway: when every entry accepts it (the common case near a minimum), the search costs no energy
    evaluation of its own. Otherwise the energy's rounding noise is measured (`energy_noise`) and the
    trial judged again with that allowance. Where even the trial's predicted decrease is below the
    noise, the energy cannot judge the step, and the directional derivatives at both ends do instead
    (the trapezoidal estimate of the change, exact for a quadratic, which the energy is on that scale);
    a step that overshoots by that estimate is replaced by the minimiser of the quadratic. Where the
    energy does judge, a trial that passes Armijo's test only thanks to the allowance must still go
    downhill where it lands (φ'(t) ≤ 0), and one past the minimum along the direction is replaced by
    that minimiser too: in float32, steps twice the way to the minimum pass on the allowance, leave
    E where it was, and stall Newton far above its tolerance. A step neither can judge is taken
    whole and flagged `unjudged`. Where some entry still refuses its trial, the search backtracks
    (`backtracking_line_search`) and evaluates the gradient where it stopped.

    `restrict`: builds the objective of some of the batch's rows alone (their indices `[k]`). Where
    it is given and at most half of the entries refuse their trial, only those search again, on their
    own objective; the others keep their trial's energy and gradient. Their search is this one,
    along the direction shortened to the step that the quadratic through E(0), φ'(0) and E(t) puts
    forward (`_interpolated_step`): its first trial is that step, evaluated with the gradient, the
    curvature hints and the verdict in one call, and where it is refused too, it backtracks on those
    rows. The noise is then measured for the entries whose trial it may decide alone, too. Without
    `restrict` every backtracking energy, the final gradient and the noise are evaluated on the whole
    batch: on 64 randomly driven worms, one or two refusing entries made that a fifth of a step.

    `noise`: the allowance for the noise of E (`LineStep.noise`) that an earlier search of the same
    solve measured, used instead of measuring again. The noise is that of the energy's terms at
    this body's scale, which one solve's iterates share; with random actions, 64 worms measured it
    in a third of their Newton iterations, four energy evaluations each.
    """
    measured_noise = [noise]

    def alone(rows: Tensor) -> bool:
        # whether `rows` are evaluated on an objective of their own: possible, and it saves work
        return restrict is not None and 2 * rows.numel() <= x.shape[0]

    def noise_floor(needed: Tensor) -> Tensor:
        # the allowance, with the noise of E measured for the `needed` entries that lack it
        known = measured_noise[0]
        if known is None:
            known = torch.full_like(energy, torch.nan)
        rows = torch.nonzero(needed & torch.isnan(known)).reshape(-1)
        if rows.numel():
            if not alone(rows):
                known = torch.where(torch.isnan(known), noise_allowance(objective, x, energy), known)
            else:
                # every sample of every row in one evaluation: the objective of the rows repeated
                replicated = restrict(rows.repeat(NOISE_SAMPLES))
                allowance = noise_allowance(objective, x[rows], energy[rows], replicated)
                known = known.index_copy(0, rows, allowance)
            measured_noise[0] = known
        return rounding_allowance(objective, x, energy, known)

    first = objective.trial(x, direction, gradient, _first_verdict, (energy, sufficient_decrease))
    initial, trial_x, trial_energy, trial_gradient = first.step, first.x, first.energy, first.gradient
    slope, trial_slope, trial_residual = first.slope, first.trial_slope, first.residual
    hints = first.hints
    settled, taken_unjudged, rounding, unjudged, slope_decrease, decrease, within, doubtful = first.verdict
    if bool(settled):  # every entry takes its first trial: the common case near a minimum
        found = (trial_energy, trial_gradient, trial_residual)
        return LineStep(initial, trial_x, *found, taken_unjudged, rounding, measured_noise[0], hints)
    measured = False

    def armijo(trial: Tensor, step: Tensor, trial_slope: Tensor) -> tuple[Tensor, Tensor]:
        return _armijo(energy, slope, rounding, sufficient_decrease, trial, step, trial_slope)

    if bool(doubtful.any()):
        # the trial may have failed on rounding alone; only now is the noise worth its evaluations
        rounding, measured = noise_floor(doubtful), True
        unjudged = -slope * initial <= rounding
        decrease, within = armijo(trial_energy, initial, trial_slope)
    overshot = _overshot(slope, trial_slope, unjudged, slope_decrease, decrease, within)
    if bool(overshot.any()):
        # the minimiser of the quadratic through φ'(0) and φ'(t): below t/2 where the trapezoid
        # refused t, below t where φ'(t) > 0, so inside the admissible segment
        curvature = torch.where(overshot, trial_slope - slope, torch.ones_like(slope))
        initial = torch.where(overshot, -initial * slope / curvature, initial)
        trial_x, hints = x + initial[:, None, None] * direction, None
        trial_energy, trial_gradient = objective.energy_and_gradient(trial_x)
        trial_slope = (trial_gradient * direction).sum(dim=(-1, -2))
        trial_residual = objective.residual(trial_gradient)
        slope_decrease = _slope_decrease(slope, trial_slope, sufficient_decrease)
        decrease, _ = armijo(trial_energy, initial, trial_slope)
        if not measured and not bool(decrease.all()):
            rounding = noise_floor(~decrease)
            unjudged = -slope * initial <= rounding
            decrease, _ = armijo(trial_energy, initial, trial_slope)
    # the energy cannot tell these from no change: their derivatives can
    judged = unjudged & decrease & slope_decrease
    if bool((unjudged | decrease).all()):
        found = (trial_energy, trial_gradient, trial_residual)
        return LineStep(initial, trial_x, *found, unjudged & ~judged, rounding, measured_noise[0], hints)
    refusing = torch.nonzero(~(unjudged | decrease)).reshape(-1)
    part = restrict(refusing) if alone(refusing) else None
    if part is not None:
        # the refusing rows search again on their own objective, from the step that the quadratic
        # through E(0), φ'(0) and E(t) puts forward: one trial (energy, gradient, hints and verdict in
        # one call where the objective compiles) along the direction scaled to that step, which
        # lies within the admissible segment, so that its first trial is the step itself
        shorter = _interpolated_step(
            initial[refusing], energy[refusing], trial_energy[refusing], slope[refusing]
        )
        known = measured_noise[0]
        own = line_step(
            part,
            x[refusing],
            energy[refusing],
            gradient[refusing],
            shorter[:, None, None] * direction[refusing],
            sufficient_decrease=sufficient_decrease,
            noise=None if known is None else known[refusing],
        )
        if own.noise is not None:
            known = torch.full_like(energy, torch.nan) if known is None else known
            measured_noise[0] = known.index_copy(0, refusing, own.noise)
        if hints is not None:
            # the trial's hints stand for the rows that took it; the others' iteration ended elsewhere
            mine = own.hints if own.hints is not None else part.curvature_hints(x[refusing], own.x)
            hints = tuple(hint.index_copy(0, refusing, row) for hint, row in zip(hints, mine, strict=True))
        return LineStep(
            initial.index_copy(0, refusing, shorter * own.step),
            trial_x.index_copy(0, refusing, own.x),
            trial_energy.index_copy(0, refusing, own.energy),
            trial_gradient.index_copy(0, refusing, own.gradient),
            trial_residual.index_copy(0, refusing, own.residual),
            (unjudged & ~judged).index_copy(0, refusing, own.unjudged),
            rounding.index_copy(0, refusing, own.allowance),
            measured_noise[0],
            hints,
        )
    step, _, unjudged = backtracking_line_search(
        objective,
        x,
        energy,
        gradient,
        direction,
        initial,
        sufficient_decrease=sufficient_decrease,
        rounding=rounding,
        initial_energy=trial_energy,
        initial_refused=~decrease,
    )
    x_new = x + step[:, None, None] * direction
    new_energy, new_gradient = objective.energy_and_gradient(x_new)
    found = (new_energy, new_gradient, objective.residual(new_gradient))
    return LineStep(step, x_new, *found, unjudged & ~judged, rounding, measured_noise[0])


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
    rounding: Tensor | None = None,
    initial_energy: Tensor | None = None,
    initial_refused: Tensor | bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Armijo backtracking, per batch entry, from the largest admissible step.

    Each refused step t is replaced by the minimiser of the quadratic through E(0), the slope at 0
    and E(t), kept within [t/10, t/2] (halving where that quadratic has no minimum, or E(t) is not
    finite): where a direction is far too long, as an indefinite Hessian's shifted one can be, one
    interpolation lands near the acceptable step that several halvings would reach (docs/solvers.md
    weighs it). The first trial's energy comes from the caller where it has it (`initial_energy`).

    Near convergence the energy change falls below the energy's rounding error, so a rise within
    that error counts as no increase; and where even the full step's predicted decrease is below
    it, the energy cannot judge the step at all: it is taken whole and flagged, so that the caller
    can judge it by the gradient instead. The error is the larger of 64 ulps of |E| and the noise
    of E measured near `x` (`energy_noise`), which is far larger for stiff rotated bodies.

    Args:
        x, gradient, direction: shape `[B, n, d]`; energy, initial_step: shape `[B]`.
        rounding: that allowance `[B]` in J, if the caller has measured it already.
        max_halvings: at most this many reductions of the step (each at least halves it).
        initial_energy: E at `initial_step` `[B]`, if the caller has evaluated it already.
        initial_refused: entries `[B]` (or all, True) whose first trial the caller has refused
            already, on a test this energy-only search cannot make (`line_step`'s derivatives).

    Returns:
        step fractions `[B]` (0 where no step was accepted), the energies there `[B]`, and which
        entries were taken unjudged `[B]`.
    """
    slope = (gradient * direction).sum(dim=(-1, -2))
    step = initial_step.clone()
    if rounding is None:
        rounding = rounding_allowance(objective, x, energy)
    unjudged = -slope * initial_step <= rounding
    accepted = unjudged.clone()
    new_energy = energy.clone()
    trial = initial_energy
    refused = torch.as_tensor(initial_refused, device=x.device) & ~unjudged
    for _ in range(max_halvings):
        if trial is None:
            trial = objective.energy(x + step[:, None, None] * direction)
        ok = _sufficient_decrease(energy, trial, step, slope, rounding, sufficient_decrease)
        ok, refused = ok & ~accepted & ~refused, torch.zeros_like(accepted)
        new_energy = torch.where(ok, trial, new_energy)
        accepted = accepted | ok
        if accepted.all():
            break
        step = torch.where(accepted, step, _interpolated_step(step, energy, trial, slope))
        trial = None
    step = torch.where(accepted, step, torch.zeros_like(step))
    return step, new_energy, unjudged


def _interpolated_step(step: Tensor, energy: Tensor, trial: Tensor, slope: Tensor) -> Tensor:
    # the minimiser −s t²/(2(E(t) − E(0) − s t)) of the quadratic through E(0), E'(0) = s and E(t),
    # safeguarded to [t/10, t/2] (Nocedal & Wright, section 3.5); t/2 without a positive curvature
    excess = trial - energy - slope * step
    convex = torch.isfinite(trial) & (excess > 0)
    minimiser = -slope * step * step / (2.0 * torch.where(convex, excess, torch.ones_like(excess)))
    interpolated = torch.minimum(torch.maximum(minimiser, 0.1 * step), 0.5 * step)
    return torch.where(convex, interpolated, 0.5 * step)
