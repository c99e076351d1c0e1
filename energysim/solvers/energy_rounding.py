"""The rounding of a step objective's energy, as a line search allows for it: a few ulps of |E|, or
the noise of E measured where that matters (`energysim.solvers.line_search`)."""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.objective.objective import Objective


def ulps_of(energy: Tensor) -> Tensor:
    """64 ulps of |E| `[B]`, in J: a decrease within them counts as no increase."""
    return 64 * torch.finfo(energy.dtype).eps * energy.abs()


# Perturbed evaluations `energy_noise` takes. With E(x) itself that is 5 values, whose spread is
# 2.3 standard deviations of the noise on average and above 1.0 in 95 % of measurements; the
# difference of two noisy values that a line search compares has √2 of them, and exceeds
# `NOISE_ALLOWANCE` spreads in about 0.2 % of comparisons (2.5 % for 2 spreads).
NOISE_SAMPLES = 4
NOISE_ALLOWANCE = 4.0


def energy_noise(
    objective: Objective,
    x: Tensor,
    energy: Tensor,
    samples: int = NOISE_SAMPLES,
    *,
    replicated: Objective | None = None,
) -> Tensor:
    """The rounding noise of E near `x`, measured: its spread over positions a few ulps away, `[B]`, in J.

    Every free coordinate moves by a fixed pattern of −2 … 2 times eps·|x|, the size of the rounding
    of the positions a line search visits, so the smooth part of E changes by at most 2 eps Σ|∇E||x|:
    the spread is how far E itself can be trusted. It is measured because the estimates from the
    magnitudes of what is summed miss where the cancellation happens. In a stiff rotated element the
    neo-Hookean energy is a sum of terms of size μV|F − I|² that cancel to a far smaller energy, inside
    the element. On the E = 1e8 Pa drop of `scripts/stability_matrix.py`, where Newton–CG stalled at
    2.1e-5 m/s, the step objective is −1.04e-2 J and its noise has a standard deviation of 6e-13 J,
    4000 times 64 ulps of |E| (1.5e-16 J); eps times the sum of the terms' magnitudes (inertia,
    gravity, elasticity, barrier, friction) is 1.8e-17 J, eps Σ|∇E||x| is 1.5e-20 J (the total force
    vanishes at the minimum), and eps Σ|∇E_i||x| over the terms i is 6e-15 J (the elastic forces of a
    stiff body are small, not its energy's terms). A bound from the material's moduli, eps Σ(μ + λ)V
    (1.7e-10 J there), holds for any rotation but is 300 times the noise at this one, and would leave
    to the derivatives every step whose predicted decrease lies below it.

    Args:
        objective: the objective whose `energy` is measured (each sample counts as an evaluation).
        x: positions `[B, n, d]`, in m; energy: E(x) `[B]`, in J, one of the spread's values.
        samples: perturbed evaluations.
        replicated: the objective of `samples` copies of the batch (entries `arange(B).repeat(samples)`),
            or None. Given, the samples are one evaluation of it, not `samples` (a compiled call's
            dispatch and guards are most of its cost for the few entries a search measures).

    Returns:
        the largest minus the smallest finite value of E among them, per batch entry (0 if none is).
    """
    # a fixed pattern from a private generator: measuring must not draw on the global random state
    generator = torch.Generator().manual_seed(0)
    patterns = torch.randint(-2, 3, (samples, *x.shape[1:]), generator=generator).to(x)
    unit = torch.finfo(x.dtype).eps * x.abs() * objective.free[:, None].to(x.dtype)
    points = [x + pattern * unit for pattern in patterns]
    if replicated is None:
        values = [energy] + [objective.energy(point) for point in points]
    else:
        values = [energy, *replicated.energy(torch.cat(points)).reshape(samples, -1).unbind(0)]
    stacked = torch.stack(values)
    finite = torch.isfinite(stacked)
    largest = torch.where(finite, stacked, -torch.inf).amax(dim=0)
    smallest = torch.where(finite, stacked, torch.inf).amin(dim=0)
    return torch.where(largest >= smallest, largest - smallest, torch.zeros_like(energy))


def rounding_allowance(
    objective: Objective, x: Tensor, energy: Tensor, noise: Tensor | None = None
) -> Tensor:
    """The allowance for rounding in an Armijo test from `x`, `[B]`, in J: 64 ulps of |E|, or the
    noise of E with `NOISE_ALLOWANCE` (`noise`, measured by `energy_noise` where None; NaN where an
    entry's is not known), whichever is larger."""
    if noise is None:
        noise = noise_allowance(objective, x, energy)
    return torch.fmax(ulps_of(energy), noise)


def noise_allowance(
    objective: Objective, x: Tensor, energy: Tensor, replicated: Objective | None = None
) -> Tensor:
    """The measured noise of E near `x` (`replicated`: see `energy_noise`) × `NOISE_ALLOWANCE`, `[B]`,
    in J."""
    return NOISE_ALLOWANCE * energy_noise(objective, x, energy, replicated=replicated)
