"""The explicit integrator: position Verlet (leapfrog, drift–kick–drift), with contact as a velocity
projection.

    x_½ = x_n + ½h v_n,   v_{n+1} = v_n − h M⁻¹∇E(x_½),   x_{n+1} = x_½ + ½h v_{n+1}

Second order and symplectic: on a stable step the energy oscillates in a band of width O(h²) and
does not drift, so a swinging beam keeps its amplitude. It costs one gradient per step and no solve,
but it is stable only while h ω_max < 2, ω_max the stiffest mode's angular frequency (the Courant
limit: about 3 ms for the 810-tet, 1e5 Pa cantilever, 1/60 s needs a few substeps for anything
stiffer than jelly). Where the limit holds it is the cheapest way to a small error: on that
cantilever its error at h = 3 ms is 2e-4 m, where the implicit steps need h = 1/240 s and tight
solves for the same.

A barrier's stiffness grows without bound near its obstacle, so no fixed explicit step is stable
with one. Obstacles whose surface normal is defined on the surface (`HalfSpace`, `Ground`,
`SphereObstacle`) act instead after every kick, through `Obstacle.contact_velocity`: an inelastic
contact with Coulomb friction, the barrier's and friction's limit as d̂ and ε_v go to 0, in closed
form per vertex. It keeps every vertex outside (the constraint is on the tangent plane, behind
which a convex obstacle lies), and it only takes energy out. Other contact terms are refused.

A step of `Scene.dt` takes `Scene.substeps` Verlet steps of dt / substeps. Instability does not
pass silently: an unstable mode grows geometrically, so `step` compares the energy at the start
and end of every step, and raises `InstabilityError` (with an estimate of the stable step) where it
grew by more than a fraction of the energy of motion and deformation, where the state or an energy
went non-finite, or where a vertex ended inside an obstacle (`blown_up`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from energysim.contact.obstacles import HalfSpace, Obstacle, SphereObstacle
from energysim.energies.base import EnergyTerm, is_dissipative, limits_steps
from energysim.mesh.validation import format_indices
from energysim.objective.derivatives import HessianOperator
from energysim.solvers.base import ConvergenceError

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
# The obstacles whose normal is defined on their surface, where resting vertices sit: a box's
# distance gradient vanishes on its faces, so its contact has no direction there.
EXPLICIT_OBSTACLES = (HalfSpace, SphereObstacle)
# How far inside an obstacle (a fraction of its d̂) a step may start: the projection puts vertices
# on the surface, where rounding leaves them a few ulps either side.
START_DEPTH_TOLERANCE = 1e-6


class InstabilityError(ConvergenceError):
    """An explicit step blew up: its step is past the stable (Courant) limit of the scene."""


def is_explicit_contact(term: EnergyTerm) -> bool:
    """Whether `term` is an obstacle that explicit steps handle by `Obstacle.contact_velocity`."""
    return isinstance(term, EXPLICIT_OBSTACLES)


def check_terms(terms: Sequence[EnergyTerm]) -> None:
    """Refuse terms an explicit step cannot integrate: contact other than `EXPLICIT_OBSTACLES`.

    Raises:
        ValueError: naming the offending terms.
    """
    offending = [
        type(term).__name__
        for term in terms
        if not (is_explicit_contact(term) or is_dissipative(term))
        and (limits_steps(term) or term.has_lagged_terms)
    ]
    if offending:
        raise ValueError(
            f"the explicit integrator has no contact model for {', '.join(offending)}: it handles "
            "HalfSpace, Ground and SphereObstacle (inelastic contact with Coulomb friction, after every "
            "kick); other contact needs the implicit step, whose line search keeps every iterate "
            "outside the obstacle; use integrator='implicit_euler' or 'tr_bdf2'"
        )


def split_terms(terms: Sequence[EnergyTerm]) -> tuple[list[EnergyTerm], list[Obstacle]]:
    """The terms whose gradients are forces, and the obstacles that act by contact projection."""
    forces = [term for term in terms if not is_explicit_contact(term)]
    obstacles = [term for term in terms if is_explicit_contact(term)]
    return forces, obstacles  # type: ignore[return-value]


def _inside(obstacle: Obstacle, x: Tensor) -> tuple[Tensor, Tensor]:
    # the signed distances `[B, m]` of the obstacle's vertices, in m, and which lie deeper inside
    # than `START_DEPTH_TOLERANCE` × its d̂
    distance = obstacle.signed_distance(x.detach()[:, obstacle.element_vertices[:, 0]])
    return distance, distance < -START_DEPTH_TOLERANCE * obstacle.barrier_distance


def check_start(obstacles: Sequence[Obstacle], x: Tensor) -> None:
    """Raise ValueError naming the vertices that start a step inside an obstacle (deeper than
    `START_DEPTH_TOLERANCE` × its d̂)."""
    for obstacle in obstacles:
        distance, inside = _inside(obstacle, x)
        inside = inside.any(dim=0)
        if bool(inside.any()):
            index = obstacle.element_vertices[inside, 0]
            raise ValueError(
                f"the state is not admissible: vertices {format_indices(index)} are inside {obstacle!r} "
                f"(signed distance down to {float(distance.min()):.3g} m); every step must start outside"
            )


def ends_inside(obstacles: Sequence[Obstacle], x: Tensor) -> Tensor:
    """Which entries of positions `x` `[B, n, d]` have a vertex inside an obstacle (as `check_start`
    measures it), `[B]` bool. The contact projection keeps every vertex of a stable step outside,
    so one that ends inside is the mark of a step that blew up."""
    inside = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    for obstacle in obstacles:
        inside = inside | _inside(obstacle, x)[1].any(dim=1)
    return inside


def blown_up(
    x: Tensor,
    v: Tensor,
    obstacles: Sequence[Obstacle],
    energy_before: Tensor,
    energy_after: Tensor,
    allowance: Tensor,
) -> Tensor:
    """Which entries of a finished explicit step blew up, `[B]` bool.

    An entry passes only where its positions `x` and velocities `v` (`[B, n, d]`, m and m/s) are
    finite, its energies at the start and end (`[B]`, J) and the gain it is allowed (`allowance`
    `[B]`, J) are finite, the energy grew by no more than the allowance, and no vertex ended inside
    an obstacle (`ends_inside`). Finiteness is checked by name, not left to the comparison: a
    velocity past about 1e154 m/s squares to an infinite kinetic energy, and an allowance that
    grows with the end energy then makes inf ≤ inf + inf hold; and a NaN on either side of a
    comparison makes it False, so the gain is tested as "within", never as "exceeds"."""
    finite = (
        torch.isfinite(x).all(dim=(-1, -2))
        & torch.isfinite(v).all(dim=(-1, -2))
        & torch.isfinite(energy_before)
        & torch.isfinite(energy_after)
        & torch.isfinite(allowance)
    )
    within = energy_after <= energy_before + allowance
    return ~(finite & within) | ends_inside(obstacles, x)


def describe_blow_up(obstacles: Sequence[Obstacle], x: Tensor, v: Tensor) -> str:
    """What, besides its energy, marks the blown-up step of one entry (`x`, `v` `[1, n, d]`): its
    non-finite positions or velocities, its largest velocity component, and the vertices left inside an
    obstacle; one sentence for an `InstabilityError`."""
    if not bool(torch.isfinite(x).all()):
        return " Its positions went non-finite."
    if not bool(torch.isfinite(v).all()):
        return " Its velocities went non-finite."
    # the largest component, not the norm: the norm of a velocity past 1e154 m/s overflows
    speed = float(v.detach().abs().max()) if v.numel() else 0.0
    text = f" Its velocities reach {speed:.3g} m/s"
    for obstacle in obstacles:
        distance, inside = _inside(obstacle, x)
        if bool(inside.any()):
            index = obstacle.element_vertices[inside[0], 0]
            text += (
                f"; vertices {format_indices(index)} ended inside {obstacle!r} (signed distance down to "
                f"{float(distance.min()):.3g} m), which contact keeps every stable step out of"
            )
    return text + "."


def leapfrog(
    x: Tensor,
    v: Tensor,
    h: float,
    substeps: int,
    acceleration: Callable[[Tensor], Tensor],
    contact: Callable[[Tensor, Tensor, float], Tensor] | None = None,
    damping: Callable[[Tensor, Tensor], Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    """`substeps` position-Verlet steps of `h` from (x, v), `[B, n, d]` each; `acceleration(x)` is
    −M⁻¹∇E(x), zero on pinned vertices (whose velocity must be zero).

    `damping(x, v)`, if given, is the viscous acceleration −M⁻¹∂D/∂v (`is_dissipative`), taken
    right after the elastic kick at the velocity it left: a splitting, first order in the damping
    as any explicit damping is (compiled batches run the two kicks as two calls, in this order).
    `contact(x, v, horizon)`, if given, then projects the velocities, for the whole step h that
    they drive (the half drift that ends this substep and the one that starts the next), and once
    before the first half drift, so that every position stays outside."""
    if contact is not None:
        v = contact(x, v, 0.5 * h)
    for _ in range(substeps):
        x = x + (0.5 * h) * v
        v = v + h * acceleration(x)
        if damping is not None:
            v = v + h * damping(x, v)
        if contact is not None:
            v = contact(x, v, h)
        x = x + (0.5 * h) * v
    return x, v


def stable_damping_step(
    dissipative: Sequence[EnergyTerm], x: Tensor, vertex_mass: Tensor, free: Tensor
) -> float:
    """The largest step, in s, that the viscous kick of `leapfrog` keeps stable at positions `x`
    `[1, n, d]`: 1/γ_max, with γ_max the largest eigenvalue of M⁻¹C and C = ∂²D/∂v² the viscous
    damping matrix (D is quadratic in v), by power iteration on v ↦ M⁻¹∂D/∂v; inf without damping.

    Why 1/γ and not 2/γ: after the elastic kick, the viscous one scales a mode's velocity by 1 − hγ,
    and with the drifts around it the substep's map keeps its spectral radius at most 1 only while
    hγ ≤ 1, whatever hω (checked for hω from 0.5 to 1.8)."""
    if not dissipative:
        return math.inf
    free_f = free[:, None].to(x.dtype)
    generator = torch.Generator(device="cpu").manual_seed(0)
    vector = torch.randn(x.shape, generator=generator, dtype=x.dtype).to(x.device) * free_f
    largest = 0.0
    with torch.no_grad():
        for _ in range(POWER_ITERATIONS):
            vector = vector / vector.norm().clamp_min(torch.finfo(x.dtype).tiny)
            product = sum(term.dissipation_gradient(x, vector) for term in dissipative) * free_f
            largest = float((vector * product).sum() / (vector * vector * vertex_mass[:, None]).sum())
            vector = product / vertex_mass[:, None]
    return 1.0 / largest if largest > 0 else math.inf


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
