"""Contact for explicit steps: velocities projected onto what a static obstacle allows.

The limit of the barrier and IPC's friction as d̂ and ε_v go to 0, in closed form per vertex: an
inelastic contact with Coulomb friction, applied after every kick of `energysim.integrators.explicit`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from torch import Tensor

if TYPE_CHECKING:  # the obstacle term calls this module; it is only a type here
    from energysim.contact.obstacle_term import Obstacle


def contact_velocity(obstacle: Obstacle, x: Tensor, v: Tensor, horizon: float | Tensor) -> Tensor:
    """The velocities `[B, n, d]` after an inelastic contact with Coulomb friction against `obstacle`,
    for an explicit step whose next `horizon` seconds move every vertex from `x` with `v` (both
    `[B, n, d]`).

    Per colliding vertex, with d its signed distance and n = ∇d at `x`: where d + horizon·n·v
    would be negative, the normal velocity rises to −d/horizon, so that the vertex ends the
    horizon on the tangent plane (outside a convex obstacle, which lies behind each of its
    tangent planes). That rise Δ is the normal impulse per unit mass, and friction takes up to
    μΔ off the tangential velocity: all of it where that is enough (sticking), μΔ along it
    otherwise (sliding). This is the closed-form minimiser of ½m‖v′ − v‖² + μmΔ‖v′_t‖ subject
    to d + horizon·n·v′ ≥ 0, the limit of the barrier and IPC's friction as d̂ and ε_v go to 0,
    and per vertex because the mass matrix is diagonal. Other vertices keep `v`.
    """
    points = obstacle.vertex_positions(x)
    velocity = obstacle.vertex_positions(v)
    distance, normal, _ = obstacle.distance_derivatives(points)
    normal_speed = (velocity * normal).sum(dim=-1)
    impulse = (-distance / horizon - normal_speed).clamp_min(0.0)
    tangential = velocity - normal_speed[..., None] * normal
    _, slip = safe_norm(tangential)
    kept = (1.0 - obstacle.friction.to(v.dtype) * impulse / slip).clamp_min(0.0)
    projected = kept[..., None] * tangential + (normal_speed + impulse)[..., None] * normal
    if obstacle.collides_all_vertices:
        return projected
    return v.index_copy(1, obstacle.element_vertices[:, 0], projected)


def project_contacts(
    obstacles: Sequence[Obstacle], free: Tensor, x: Tensor, v: Tensor, horizon: float | Tensor
) -> Tensor:
    """`v` `[B, n, d]` after each obstacle's `contact_velocity` in turn, zero on pinned vertices."""
    for obstacle in obstacles:
        v = obstacle.contact_velocity(x, v, horizon)
    return v * free[:, None].to(v.dtype)


def safe_norm(vectors: Tensor) -> tuple[Tensor, Tensor]:
    """‖v‖ over the last axis and a divisor that is never 0 (where ‖v‖ = 0 it is 1)."""
    square = (vectors * vectors).sum(dim=-1)
    positive = square > 0
    length = torch.sqrt(torch.where(positive, square, torch.ones_like(square)))
    return torch.where(positive, length, torch.zeros_like(length)), length
