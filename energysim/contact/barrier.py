"""The IPC log barrier on a distance, and how its scale is chosen.

b(d) = −(d − d̂)² ln(d/d̂) for 0 < d < d̂, 0 for d ≥ d̂ and +∞ for d ≤ 0: C² at d̂, convex and
decreasing on (0, d̂), unbounded as d → 0, so a minimiser of an energy that contains κ·b(d) never
reaches contact (Li et al., "Incremental Potential Contact", 2020).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def barrier(distance: Tensor, barrier_distance: float) -> Tensor:
    """b(d) in m², elementwise; +∞ where d ≤ 0.

    Outside (0, d̂) the logarithm is evaluated at d̂ instead, so that autograd never meets the
    infinite or undefined derivatives of the branch `torch.where` discards.
    """
    active = (distance > 0) & (distance < barrier_distance)
    safe = torch.where(active, distance, torch.full_like(distance, barrier_distance))
    value = -((safe - barrier_distance) ** 2) * torch.log(safe / barrier_distance)
    return torch.where(distance > 0, value, torch.full_like(distance, math.inf))


def barrier_derivatives(distance: Tensor, barrier_distance: float) -> tuple[Tensor, Tensor]:
    """b'(d) (in m, ≤ 0) and b''(d) (dimensionless, ≥ 0), elementwise; both 0 for d ≥ d̂.

    b'(d) = (d̂ − d)(2 ln(d/d̂) − d̂/d + 1),  b''(d) = (d̂/d + 2) d̂/d − 2 ln(d/d̂) − 3.
    Only for d > 0 (an admissible state).
    """
    active = (distance > 0) & (distance < barrier_distance)
    safe = torch.where(active, distance, torch.full_like(distance, barrier_distance))
    ratio = barrier_distance / safe
    log = torch.log(safe / barrier_distance)
    first = (barrier_distance - safe) * (2.0 * log - ratio + 1.0)
    second = (ratio + 2.0) * ratio - 2.0 * log - 3.0
    zero = torch.zeros_like(distance)
    return torch.where(active, first, zero), torch.where(active, second, zero)


# |b'(d̂/2)| / d̂ = (1/2)(2 ln 2 + 1): the slope of the barrier half-way into its range
_HALF_WAY_SLOPE = 0.5 * (2.0 * math.log(2.0) + 1.0)


def default_barrier_stiffness(reference_pressure: float, barrier_distance: float) -> float:
    """κ in Pa/m such that a contact pressure of `reference_pressure` (Pa) rests at d = d̂/2.

    The contact energy is κ Σ_i a_i b(d_i) with a_i the area a vertex stands for, so the pressure
    it exerts at distance d is κ |b'(d)|; a body pressing harder settles closer, never through.
    """
    return reference_pressure / (_HALF_WAY_SLOPE * barrier_distance)
