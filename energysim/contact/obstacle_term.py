"""The obstacle term: an IPC log barrier on each vertex's signed distance to a static shape.

E = κ Σ_i a_i b(d_i), d_i the signed distance of vertex i to the obstacle and a_i the surface
area it stands for (so κ b′ is a pressure and the contact force does not change when the mesh is
refined). The barrier is infinite at contact, and `max_step` caps every line search at a fraction
of the first time of impact along the step (closed-form continuous collision detection), so no
vertex ever reaches an obstacle, at any speed, with any solver that respects `max_step`.

The shapes (signed distance, its derivatives, time of impact) are in `energysim.contact.obstacles`;
friction (Coulomb, smoothed and lagged as in IPC) enters each step as a separate term built from
the state at the step's start (`lagged_terms`, `energysim.contact.friction`); explicit steps use
the contact projection of `energysim.contact.projection` instead of the barrier.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from energysim.contact.barrier import barrier, barrier_derivatives, default_barrier_stiffness
from energysim.contact.friction import LaggedFriction
from energysim.contact.projection import contact_velocity
from energysim.energies.base import (
    ElementEnergy,
    EnergyTerm,
    StepLimitingEnergy,
    as_parameter,
    scatter_vertices,
)
from energysim.mesh import SimplexMesh
from energysim.mesh.indices import as_indices
from energysim.mesh.validation import format_indices

# the fraction of the time of impact a line search may start from (ipc-toolkit's default)
CCD_SAFETY = 0.8
# d̂ as a fraction of the body's bounding-box diagonal (IPC's default)
BARRIER_DISTANCE_FRACTION = 1e-3
STANDARD_GRAVITY = 9.81


def contact_areas(mesh: SimplexMesh) -> Tensor:
    """The boundary area each vertex stands for, shape `[n]`, in m² (in 2D: m, per metre of depth).

    A third of each boundary triangle's area (half of each boundary segment's length) goes to its
    corners. Interior vertices, which touch an obstacle only if an element inverts through the
    surface, get the mean area of the boundary vertices, so they are kept out too.
    """
    facets = mesh.surface()
    corners = mesh.vertices[facets]
    if mesh.dim == 3:
        size = 0.5 * torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(
            dim=-1
        )
    else:
        size = (corners[:, 1] - corners[:, 0]).norm(dim=-1)
    share = (size / mesh.dim).repeat_interleave(mesh.dim)
    area = torch.zeros(mesh.num_vertices, dtype=mesh.vertices.dtype).index_add_(0, facets.reshape(-1), share)
    boundary = area > 0
    return torch.where(boundary, area, area[boundary].mean())


class Obstacle(ElementEnergy, StepLimitingEnergy):
    """Base of static obstacles: the barrier term, its CCD step limit, contact forces and friction.

    A subclass defines the shape: `signed_distance`, `distance_derivatives` and `time_of_impact`.
    Every element of this term is one vertex (`element_vertices` has shape `[m, 1]`).

    Args:
        friction: Coulomb coefficient μ ≥ 0 (a tensor may require grad); 0: frictionless.
        barrier_distance: d̂ in m, the distance below which the barrier acts; default 1e-3 × the
            body's bounding-box diagonal.
        barrier_stiffness: κ in Pa/m; default such that the body's mean weight per boundary area
            (its mass × 9.81 m/s² over its boundary area) rests at d̂/2.
        friction_smoothing: ε_v in m/s, the slip velocity below which friction ramps down (static
            friction creeps at a fraction of it).
        vertices: which vertices collide, default all.
    """

    has_gradient_kernel = True
    has_hessian_kernel = True
    has_lagged_terms = True

    def __init__(
        self,
        friction: float | Tensor = 0.0,
        barrier_distance: float | None = None,
        barrier_stiffness: float | None = None,
        friction_smoothing: float = 1e-3,
        vertices: Sequence[int] | Tensor | None = None,
    ) -> None:
        super().__init__()
        friction = as_parameter(friction, "friction")
        if friction.ndim != 0 or not (torch.isfinite(friction) and friction >= 0):
            raise ValueError(f"friction must be a finite scalar >= 0, got {friction.tolist()}")
        for name, value in (("barrier_distance", barrier_distance), ("barrier_stiffness", barrier_stiffness)):
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        if not (math.isfinite(friction_smoothing) and friction_smoothing > 0):
            raise ValueError(f"friction_smoothing must be finite and > 0 m/s, got {friction_smoothing}")
        self.register_buffer("friction", friction)
        self._barrier_distance = barrier_distance
        self._barrier_stiffness = barrier_stiffness
        self.friction_smoothing = float(friction_smoothing)
        self._vertices = (
            None if vertices is None else as_indices(vertices, "vertices").reshape(-1)
        )

    # --- the shape -------------------------------------------------------------------------

    dim: int

    def signed_distance(self, points: Tensor) -> Tensor:  # pragma: no cover - abstract
        """Signed distance of `points` (`[..., d]`, m) to the surface, `[...]`, in m; > 0 outside."""
        raise NotImplementedError

    def distance_derivatives(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # pragma: no cover
        """Signed distance `[...]`, its gradient `[..., d]` and Hessian `[..., d, d]` (1/m), closed form."""
        raise NotImplementedError

    def time_of_impact(self, points: Tensor, motion: Tensor) -> Tensor:  # pragma: no cover - abstract
        """The first t > 0 at which `points + t·motion` reaches the surface, `[...]`; +∞ if never."""
        raise NotImplementedError

    # --- the term ----------------------------------------------------------------------------

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        if mesh.dim != self.dim:
            raise ValueError(f"{type(self).__name__} is {self.dim}D but the mesh is {mesh.dim}D")
        vertices = torch.arange(mesh.num_vertices) if self._vertices is None else self._vertices
        if vertices.numel() == 0 or ((vertices < 0) | (vertices >= mesh.num_vertices)).any():
            raise ValueError(f"vertices must be a non-empty subset of [0, {mesh.num_vertices})")
        areas = contact_areas(mesh)
        low, high = mesh.bounding_box()
        self.barrier_distance = self._barrier_distance or BARRIER_DISTANCE_FRACTION * float(
            (high - low).norm()
        )
        if self._barrier_stiffness is None:
            boundary_area = float(areas[mesh.surface_vertices()].sum())
            pressure = float(vertex_mass.sum()) * STANDARD_GRAVITY / boundary_area
            stiffness = default_barrier_stiffness(pressure, self.barrier_distance)
        else:
            stiffness = self._barrier_stiffness
        self.register_buffer("element_vertices", vertices[:, None].contiguous())
        self.register_buffer("contact_area", areas[vertices])
        self.register_buffer("barrier_stiffness", torch.tensor(stiffness, dtype=torch.float64))

    def element_energy(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        distance = self.signed_distance(element_positions[..., 0, :])
        return self.barrier_stiffness * self.contact_area * barrier(distance, self.barrier_distance)

    def element_energy_and_gradient(
        self, element_positions: Tensor, action: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """κ a b(d) per vertex `[B, m]` in J and κ a b′(d) ∇d `[B, m, 1, d]` in N (closed form)."""
        distance, gradient, _ = self.distance_derivatives(element_positions[..., 0, :])
        first, _ = barrier_derivatives(distance, self.barrier_distance)
        weight = self.barrier_stiffness * self.contact_area
        energy = weight * barrier(distance, self.barrier_distance)
        return energy, ((weight * first)[..., None] * gradient)[..., None, :]

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Exact per-vertex blocks κ a (b″ ∇d ∇dᵀ + b′ ∇²d), shape `[B, m, d, d]`, in N/m."""
        distance, gradient, hessian = self.distance_derivatives(element_positions[..., 0, :])
        first, second = barrier_derivatives(distance, self.barrier_distance)
        outer = gradient[..., :, None] * gradient[..., None, :]
        weight = (self.barrier_stiffness * self.contact_area)[..., None, None]
        return weight * (second[..., None, None] * outer + first[..., None, None] * hessian)

    def distance_derivative_entries(
        self, points: list[Tensor]
    ) -> tuple[Tensor, list[Tensor], list[list[Tensor]] | None]:
        """`distance_derivatives` of the points whose coordinates are `points[i]` `[m, B]` (the
        batch-last kernels' layout): the distance `[m, B]`, the gradient's components `[i]` and the
        Hessian's `[i][k]`, or None where it vanishes. This default stacks the coordinates; a shape
        with closed forms per coordinate overrides it (`HalfSpace`)."""
        distance, gradient, hessian = self.distance_derivatives(torch.stack(points, dim=-1))
        dim = len(points)
        columns = [[hessian[..., i, k] for k in range(dim)] for i in range(dim)]
        return distance, [gradient[..., i] for i in range(dim)], columns

    def batch_last_energy_and_forces(
        self, corners: list[list[Tensor]], action: Tensor | None
    ) -> tuple[Tensor, list[list[Tensor]]]:
        """κ a b(d) per vertex `[m, B]` and κ a b′(d) ∇d entry by entry, batch innermost (see
        `ElementEnergy.batch_last_energy_and_forces`)."""
        distance, gradient, _ = self.distance_derivative_entries([row[0] for row in corners])
        first, _ = barrier_derivatives(distance, self.barrier_distance)
        weight = (self.barrier_stiffness * self.contact_area)[:, None]
        pressure = weight * first
        return weight * barrier(distance, self.barrier_distance), [[pressure * g] for g in gradient]

    def batch_last_hessian_entries(self, corners: list[list[Tensor]], action: Tensor | None) -> list[Tensor]:
        """`element_hessian`'s upper entries κ a (b″ ∂_i d ∂_k d + b′ ∂_ik d) `[m, B]`, batch
        innermost (see `ElementEnergy.batch_last_hessian_entries`)."""
        distance, gradient, hessian = self.distance_derivative_entries([row[0] for row in corners])
        first, second = barrier_derivatives(distance, self.barrier_distance)
        weight = (self.barrier_stiffness * self.contact_area)[:, None]
        curvature, pressure = weight * second, weight * first
        dim = len(corners)
        entries = []
        for i in range(dim):
            for k in range(i, dim):
                value = curvature * gradient[i] * gradient[k]
                entries.append(value if hessian is None else value + pressure * hessian[i][k])
        return entries

    @property
    def collides_all_vertices(self) -> bool:
        """Whether every vertex of the mesh collides (the default): `element_vertices` is then 0..n−1."""
        return self._vertices is None

    def vertex_positions(self, x: Tensor) -> Tensor:
        """The colliding vertices' rows of `x` `[B, n, d]`: `[B, m, d]` (no copy when all collide)."""
        return x if self._vertices is None else x[:, self.element_vertices[:, 0]]

    def check_admissible(self, x: Tensor) -> Tensor:
        """Signed distances `[B, m]` at `x`; raises ValueError naming any vertex inside or on the obstacle."""
        distance = self.signed_distance(self.vertex_positions(x))
        inside = (distance <= 0).any(dim=0)
        if inside.any():
            index = self.element_vertices[inside, 0]
            raise ValueError(
                f"the state is not admissible: vertices {format_indices(index)} are inside or on {self!r} "
                f"(signed distance down to {float(distance.min()):.3g} m); every step must start outside"
            )
        return distance

    def max_step(self, x: Tensor, dx: Tensor) -> Tensor:
        """The CCD-safe step fraction `[B]`: `CCD_SAFETY` × the first time of impact, at most 1.

        Raises:
            ValueError: a vertex is already inside or on the obstacle at `x`.
        """
        limit = self.step_limit(x, dx)
        if not bool(torch.isfinite(limit).all()):
            self.check_admissible(x)  # raises, naming the vertices, where x is the cause
        return limit

    def step_limit(self, x: Tensor, dx: Tensor) -> Tensor:
        """`max_step` without the check: NaN where a vertex is inside or on the obstacle at `x`."""
        points = self.vertex_positions(x)
        inside = (self.signed_distance(points) <= 0).any(dim=-1)
        impact = self.time_of_impact(points, self.vertex_positions(dx))
        limit = (CCD_SAFETY * impact.amin(dim=-1)).clamp(max=1.0)
        return torch.where(inside, torch.full_like(limit, torch.nan), limit)

    def contact_velocity(self, x: Tensor, v: Tensor, horizon: float | Tensor) -> Tensor:
        """The velocities `[B, n, d]` after an inelastic contact with Coulomb friction, for an explicit
        step whose next `horizon` seconds move every vertex from `x` with `v` (both `[B, n, d]`);
        see `energysim.contact.projection.contact_velocity`."""
        return contact_velocity(self, x, v, horizon)

    def normal_force(self, x: Tensor) -> Tensor:
        """Magnitude of the barrier's force on each colliding vertex, shape `[B, m]`, in N."""
        return self._normal_force(self.signed_distance(self.vertex_positions(x)))

    def _normal_force(self, distance: Tensor) -> Tensor:
        first, _ = barrier_derivatives(distance, self.barrier_distance)
        return -self.barrier_stiffness * self.contact_area * first

    def contact_force(self, x: Tensor) -> Tensor:
        """The force the obstacle exerts on every vertex, shape `[B, n, d]`, in N (−∇ of the barrier)."""
        _, gradient = self.element_energy_and_gradient(x[:, self.element_vertices], None)
        return -scatter_vertices(gradient, self.element_vertices, x.shape[1])

    def lagged_terms(self, x_prev: Tensor, dt: float) -> list[EnergyTerm]:
        """This step's friction term, from the state at its start; none if μ = 0 or nothing touches."""
        if not (self.friction.requires_grad or bool(self.friction > 0)):
            return []
        points = self.vertex_positions(x_prev)
        distance, gradient, _ = self.distance_derivatives(points)
        if not bool((distance < self.barrier_distance).any()):
            return []
        return [
            LaggedFriction(
                self.element_vertices,
                points,
                gradient,
                self._normal_force(distance),
                self.friction,
                self.friction_smoothing * dt,
            )
        ]
