"""The explicit integrator: position Verlet (leapfrog, drift–kick–drift), for scenes without contact.

    x_½ = x_n + ½h v_n,   v_{n+1} = v_n − h M⁻¹∇E(x_½),   x_{n+1} = x_½ + ½h v_{n+1}

Second order and symplectic: on a stable step the energy oscillates in a band of width O(h²) and
does not drift, so a swinging beam keeps its amplitude. It costs one gradient per step and no solve,
but it is stable only while h ω_max < 2, ω_max the stiffest mode's angular frequency (the Courant
limit: about 3 ms for the 810-tet, 1e5 Pa cantilever, 1/60 s needs a few substeps for anything
stiffer than jelly). Where the limit holds it is the cheapest way to a small error: on that
cantilever its error at h = 3 ms is 2e-4 m, where the implicit steps need h = 1/240 s and tight
solves for the same. Contact is not for it: a barrier's stiffness grows without bound near the
obstacle, so no fixed step is stable there, and the scene's terms are checked for it.

A step of `Scene.dt` takes `Scene.substeps` Verlet steps of dt / substeps. Instability does not
pass silently: an unstable mode grows geometrically, so `step` compares the energy at the start
and end of every step, and raises `InstabilityError` (with an estimate of the stable step) where it
grew by more than a fraction of the energy of motion and deformation, or went non-finite.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from energysim.derivatives import HessianOperator
from energysim.energies.base import EnergyTerm, limits_steps
from energysim.optim.base import ConvergenceError

# The most energy an explicit step may gain: `ENERGY_GAIN_LIMIT` of its energy of motion and
# deformation (kinetic plus the nonlinear terms') at its start, plus `ENERGY_GAIN_FLOOR` of that at
# its end (a step from rest starts with none). A stable step only trades energy between its forms:
# the swinging cantilever near its Courant limit (h = 2.98 ms, 28 substeps a step) gains at most
# 1e-4 of it in a step, a lone mode at ωh = 0.7 swings by 14 % (by 1/(1 − (ωh)²/4) in general, so a
# false alarm needs nearly all the energy in modes past ωh = 1.4). An unstable mode multiplies its
# energy by (ωh)⁴/4 or more every substep: `bench_peers`' tiny beam just past its limit (h = 10.4
# against 10.9 ms) is flagged at the first step that shows it, whose total went from 39.3 to 84.7 J
# (its energy of motion from 38 to 120 J); the step before had gained 0.01 J.
ENERGY_GAIN_LIMIT = 0.5
ENERGY_GAIN_FLOOR = 0.01
POWER_ITERATIONS = 30
# The substeps an `InstabilityError` advises keep h below this fraction of the estimated limit: power
# iteration approaches ω_max from below, and a body stiffens as it deforms (a soft beam falling from
# horizontal, `tests/test_explicit.py`: from 12.3 ms at rest to 10.1 ms bent).
COURANT_SAFETY = 0.75


class InstabilityError(ConvergenceError):
    """An explicit step blew up: its step is past the stable (Courant) limit of the scene."""


def check_terms(terms: Sequence[EnergyTerm]) -> None:
    """Refuse terms an explicit step cannot integrate: contact barriers and friction.

    Raises:
        ValueError: naming the offending terms.
    """
    offending = [
        type(term).__name__
        for term in terms
        if limits_steps(term) or type(term).lagged_terms is not EnergyTerm.lagged_terms
    ]
    if offending:
        raise ValueError(
            f"the explicit integrator has no contact: {', '.join(offending)} need the implicit step, "
            "whose line search keeps every iterate outside the obstacle (a barrier's stiffness grows "
            "without bound near contact, so no fixed explicit step is stable there); use "
            "integrator='implicit_euler' or 'tr_bdf2'"
        )


def leapfrog(
    x: Tensor, v: Tensor, h: float, substeps: int, acceleration: Callable[[Tensor], Tensor]
) -> tuple[Tensor, Tensor]:
    """`substeps` position-Verlet steps of `h` from (x, v), `[B, n, d]` each; `acceleration(x)` is
    −M⁻¹∇E(x), zero on pinned vertices (whose velocity must be zero)."""
    for _ in range(substeps):
        x = x + (0.5 * h) * v
        v = v + h * acceleration(x)
        x = x + (0.5 * h) * v
    return x, v


def stable_step(operator: HessianOperator, vertex_mass: Tensor, free: Tensor, like: Tensor) -> float:
    """The Courant limit 2/ω_max at the operator's point, in s, with ω_max² the largest eigenvalue of
    M⁻¹H over the free DOFs, by power iteration (an estimate from below of ω_max, so the step it
    returns is slightly optimistic); inf where H has no positive curvature."""
    free_f = free[:, None].to(like.dtype)
    inverse_mass = free_f / vertex_mass[:, None]
    generator = torch.Generator(device="cpu").manual_seed(0)
    vector = torch.randn(like.shape, generator=generator, dtype=like.dtype).to(like.device) * free_f
    largest = 0.0
    for _ in range(POWER_ITERATIONS):
        vector = vector / vector.norm().clamp_min(torch.finfo(like.dtype).tiny)
        product = operator.matvec(vector) * free_f
        mass_norm = (vector * vector * vertex_mass[:, None]).sum()
        largest = float((vector * product).sum() / mass_norm)
        vector = product * inverse_mass
    return 2.0 / math.sqrt(largest) if largest > 0 else math.inf
