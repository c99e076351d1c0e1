"""Static obstacles as energies: an IPC log barrier on each vertex's signed distance to a shape.

E = κ Σ_i a_i b(d_i), d_i the signed distance of vertex i to the obstacle and a_i the surface
area it stands for (so κ b′ is a pressure and the contact force does not change when the mesh is
refined). The barrier is infinite at contact, and `max_step` caps every line search at a fraction
of the first time of impact along the step (closed-form continuous collision detection), so no
vertex ever reaches an obstacle, at any speed, with any solver that respects `max_step`.

Friction (Coulomb, smoothed and lagged as in IPC) enters each step as a separate term built from
the state at the step's start: see `lagged_terms` and `energysim.contact.friction`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from energysim.contact.barrier import barrier, barrier_derivatives, default_barrier_stiffness
from energysim.contact.friction import LaggedFriction
from energysim.energies.base import ElementEnergy, EnergyTerm, as_parameter, scatter_vertices
from energysim.mesh import SimplexMesh
from energysim.mesh.indices import as_indices
from energysim.mesh.simplex import format_indices

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


class Obstacle(ElementEnergy):
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

    def element_gradient(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """κ a b′(d) ∇d per vertex, shape `[B, m, 1, d]`, in N (closed form)."""
        distance, gradient, _ = self.distance_derivatives(element_positions[..., 0, :])
        first, _ = barrier_derivatives(distance, self.barrier_distance)
        return ((self.barrier_stiffness * self.contact_area * first)[..., None] * gradient)[..., None, :]

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Exact per-vertex blocks κ a (b″ ∇d ∇dᵀ + b′ ∇²d), shape `[B, m, d, d]`, in N/m."""
        distance, gradient, hessian = self.distance_derivatives(element_positions[..., 0, :])
        first, second = barrier_derivatives(distance, self.barrier_distance)
        outer = gradient[..., :, None] * gradient[..., None, :]
        weight = (self.barrier_stiffness * self.contact_area)[..., None, None]
        return weight * (second[..., None, None] * outer + first[..., None, None] * hessian)

    def _vertex_positions(self, x: Tensor) -> Tensor:
        # every vertex collides by default: then no gather (a copy of x per call)
        return x if self._vertices is None else x[:, self.element_vertices[:, 0]]

    def check_admissible(self, x: Tensor) -> Tensor:
        """Signed distances `[B, m]` at `x`; raises ValueError naming any vertex inside or on the obstacle."""
        distance = self.signed_distance(self._vertex_positions(x))
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
        points = self._vertex_positions(x)
        inside = (self.signed_distance(points) <= 0).any(dim=-1)
        impact = self.time_of_impact(points, self._vertex_positions(dx))
        limit = (CCD_SAFETY * impact.amin(dim=-1)).clamp(max=1.0)
        return torch.where(inside, torch.full_like(limit, torch.nan), limit)

    def contact_velocity(self, x: Tensor, v: Tensor, horizon: float | Tensor) -> Tensor:
        """The velocities `[B, n, d]` after an inelastic contact with Coulomb friction, for an explicit
        step whose next `horizon` seconds move every vertex from `x` with `v` (both `[B, n, d]`).

        Per colliding vertex, with d its signed distance and n = ∇d at `x`: where d + horizon·n·v
        would be negative, the normal velocity rises to −d/horizon, so that the vertex ends the
        horizon on the tangent plane (outside a convex obstacle, which lies behind each of its
        tangent planes). That rise Δ is the normal impulse per unit mass, and friction takes up to
        μΔ off the tangential velocity: all of it where that is enough (sticking), μΔ along it
        otherwise (sliding). This is the closed-form minimiser of ½m‖v′ − v‖² + μmΔ‖v′_t‖ subject
        to d + horizon·n·v′ ≥ 0, the limit of the barrier and IPC's friction as d̂ and ε_v go to 0,
        and per vertex because the mass matrix is diagonal. Other vertices keep `v`.
        """
        points = self._vertex_positions(x)
        velocity = self._vertex_positions(v)
        distance, normal, _ = self.distance_derivatives(points)
        normal_speed = (velocity * normal).sum(dim=-1)
        impulse = (-distance / horizon - normal_speed).clamp_min(0.0)
        tangential = velocity - normal_speed[..., None] * normal
        _, slip = _safe_norm(tangential)
        kept = (1.0 - self.friction.to(v.dtype) * impulse / slip).clamp_min(0.0)
        projected = kept[..., None] * tangential + (normal_speed + impulse)[..., None] * normal
        if self._vertices is None:
            return projected
        return v.index_copy(1, self.element_vertices[:, 0], projected)

    def normal_force(self, x: Tensor) -> Tensor:
        """Magnitude of the barrier's force on each colliding vertex, shape `[B, m]`, in N."""
        return self._normal_force(self.signed_distance(self._vertex_positions(x)))

    def _normal_force(self, distance: Tensor) -> Tensor:
        first, _ = barrier_derivatives(distance, self.barrier_distance)
        return -self.barrier_stiffness * self.contact_area * first

    def contact_force(self, x: Tensor) -> Tensor:
        """The force the obstacle exerts on every vertex, shape `[B, n, d]`, in N (−∇ of the barrier)."""
        return -scatter_vertices(
            self.element_gradient(x[:, self.element_vertices], None), self.element_vertices, x.shape[1]
        )

    def lagged_terms(self, x_prev: Tensor, dt: float) -> list[EnergyTerm]:
        """This step's friction term, from the state at its start; none if μ = 0 or nothing touches."""
        if not (self.friction.requires_grad or bool(self.friction > 0)):
            return []
        points = self._vertex_positions(x_prev)
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


def project_contacts(
    obstacles: Sequence[Obstacle], free: Tensor, x: Tensor, v: Tensor, horizon: float | Tensor
) -> Tensor:
    """`v` `[B, n, d]` after each obstacle's `contact_velocity` in turn, zero on pinned vertices."""
    for obstacle in obstacles:
        v = obstacle.contact_velocity(x, v, horizon)
    return v * free[:, None].to(v.dtype)


def _unit_vector(value: Sequence[float] | Tensor, name: str) -> Tensor:
    vector = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
    if vector.numel() not in (2, 3) or not torch.isfinite(vector).all() or float(vector.norm()) == 0:
        raise ValueError(
            f"{name} must be a finite non-zero vector of 2 or 3 components, got {vector.tolist()}"
        )
    return vector / vector.norm()


def _point(value: Sequence[float] | Tensor, name: str) -> Tensor:
    point = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
    if point.numel() not in (2, 3) or not torch.isfinite(point).all():
        raise ValueError(f"{name} must be a finite point of 2 or 3 components, got {point.tolist()}")
    return point


class HalfSpace(Obstacle):
    """The solid region n·x < n·p below a plane through `point` with outward unit `normal`.

    Args:
        point: a point on the plane, d components, m.
        normal: the direction of free space, d components (normalised here).
        **options: friction and barrier settings, see `Obstacle`.
    """

    def __init__(self, point: Sequence[float] | Tensor, normal: Sequence[float] | Tensor, **options) -> None:  # noqa: ANN003
        super().__init__(**options)
        normal = _unit_vector(normal, "normal")
        point = _point(point, "point")
        if point.numel() != normal.numel():
            raise ValueError(f"point has {point.numel()} components but normal has {normal.numel()}")
        self.dim = normal.numel()
        self.register_buffer("normal", normal)
        self.register_buffer("offset", (normal * point).sum())

    def __repr__(self) -> str:
        return f"{type(self).__name__}(normal={self.normal.tolist()}, offset={float(self.offset):.4g} m)"

    def signed_distance(self, points: Tensor) -> Tensor:
        return (points * self.normal).sum(dim=-1) - self.offset

    def distance_derivatives(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        distance = self.signed_distance(points)
        gradient = self.normal.to(points.dtype).expand_as(points)
        return distance, gradient, points.new_zeros(*points.shape, points.shape[-1])

    def time_of_impact(self, points: Tensor, motion: Tensor) -> Tensor:
        rate = (motion * self.normal).sum(dim=-1)
        approaching = rate < 0
        distance = self.signed_distance(points)
        safe_rate = torch.where(approaching, rate, -torch.ones_like(rate))
        return torch.where(approaching, distance / -safe_rate, torch.full_like(rate, math.inf))


class Ground(HalfSpace):
    """The ground: the half-space below the plane n·x = `height`.

    Args:
        height: the plane's offset along `normal`, in m.
        normal: the up direction, default (0, 1, 0) (y up); use (0, 1) in 2D. A tilted normal
            makes a slope.
        friction: Coulomb coefficient μ.
        **options: barrier settings, see `Obstacle`.
    """

    def __init__(
        self,
        height: float = 0.0,
        normal: Sequence[float] | Tensor = (0.0, 1.0, 0.0),
        friction: float | Tensor = 0.0,
        **options,  # noqa: ANN003
    ) -> None:
        unit = _unit_vector(normal, "normal")
        super().__init__(point=height * unit, normal=unit, friction=friction, **options)


def _safe_norm(vectors: Tensor) -> tuple[Tensor, Tensor]:
    """‖v‖ over the last axis and a divisor that is never 0 (where ‖v‖ = 0 it is 1)."""
    square = (vectors * vectors).sum(dim=-1)
    positive = square > 0
    length = torch.sqrt(torch.where(positive, square, torch.ones_like(square)))
    return torch.where(positive, length, torch.zeros_like(length)), length


class SphereObstacle(Obstacle):
    """A solid ball (a disc in 2D).

    Args:
        center: d components, m.
        radius: m, > 0.
        **options: friction and barrier settings, see `Obstacle`.
    """

    def __init__(self, center: Sequence[float] | Tensor, radius: float, **options) -> None:  # noqa: ANN003
        super().__init__(**options)
        center = _point(center, "center")
        if not (math.isfinite(radius) and radius > 0):
            raise ValueError(f"radius must be finite and > 0 m, got {radius}")
        self.dim = center.numel()
        self.register_buffer("center", center)
        self.radius = float(radius)

    def __repr__(self) -> str:
        return f"SphereObstacle(center={self.center.tolist()}, radius={self.radius:.4g} m)"

    def signed_distance(self, points: Tensor) -> Tensor:
        length, _ = _safe_norm(points - self.center)
        return length - self.radius

    def distance_derivatives(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        offset = points - self.center
        length, divisor = _safe_norm(offset)
        unit = offset / divisor[..., None]
        eye = torch.eye(points.shape[-1], dtype=points.dtype, device=points.device)
        hessian = (eye - unit[..., :, None] * unit[..., None, :]) / divisor[..., None, None]
        return length - self.radius, unit, hessian

    def time_of_impact(self, points: Tensor, motion: Tensor) -> Tensor:
        # smallest t > 0 with ‖r + t v‖ = R: a t² + 2 b t + c = 0, c > 0 outside; it exists when
        # b < 0 (approaching) and b² ≥ a c; c / (−b + √(b² − a c)) is that root without cancellation
        offset = points - self.center
        a = (motion * motion).sum(dim=-1)
        b = (offset * motion).sum(dim=-1)
        c = (offset * offset).sum(dim=-1) - self.radius**2
        discriminant = b * b - a * c
        hits = (b < 0) & (discriminant >= 0)
        root = c / (-b + torch.sqrt(discriminant.clamp_min(0.0))).where(hits, torch.ones_like(b))
        return torch.where(hits, root, torch.full_like(b, math.inf))


class BoxObstacle(Obstacle):
    """A solid axis-aligned box (a rectangle in 2D).

    Args:
        lower, upper: opposite corners, d components each, m; upper > lower on every axis.
        **options: friction and barrier settings, see `Obstacle`.
    """

    def __init__(
        self,
        lower: Sequence[float] | Tensor,
        upper: Sequence[float] | Tensor,
        **options,  # noqa: ANN003
    ) -> None:
        super().__init__(**options)
        lower, upper = _point(lower, "lower"), _point(upper, "upper")
        if lower.numel() != upper.numel() or not bool((upper > lower).all()):
            raise ValueError(
                f"need upper > lower on every axis, got lower={lower.tolist()}, upper={upper.tolist()}"
            )
        self.dim = lower.numel()
        self.register_buffer("lower", lower)
        self.register_buffer("upper", upper)

    def __repr__(self) -> str:
        return f"BoxObstacle(lower={self.lower.tolist()}, upper={self.upper.tolist()})"

    def _excess(self, points: Tensor) -> tuple[Tensor, Tensor]:
        center = 0.5 * (self.lower + self.upper)
        offset = points - center
        return offset, offset.abs() - 0.5 * (self.upper - self.lower)

    def signed_distance(self, points: Tensor) -> Tensor:
        _, excess = self._excess(points)
        outside, _ = _safe_norm(excess.clamp_min(0.0))
        inside = excess.amax(dim=-1).clamp(max=0.0)
        return outside + inside

    def distance_derivatives(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        # outside the box d = ‖max(q, 0)‖ with q = |x − c| − half: the distance to the nearest face,
        # edge or corner; its Hessian lives on the axes where the point is beyond a face
        offset, excess = self._excess(points)
        beyond = excess.clamp_min(0.0)
        length, divisor = _safe_norm(beyond)
        sign = torch.where(offset < 0, -torch.ones_like(offset), torch.ones_like(offset))
        unit = beyond / divisor[..., None]
        gradient = sign * unit
        mask = (excess > 0).to(points.dtype)
        projector = torch.diag_embed(mask) - unit[..., :, None] * unit[..., None, :]
        hessian = sign[..., :, None] * projector * sign[..., None, :] / divisor[..., None, None]
        inside = excess.amax(dim=-1).clamp(max=0.0)
        return length + inside, gradient, hessian

    def time_of_impact(self, points: Tensor, motion: Tensor) -> Tensor:
        # slab test: the segment enters the box at the latest of the per-axis entry times, if that
        # comes before the earliest exit time
        moving = motion != 0
        safe = torch.where(moving, motion, torch.ones_like(motion))
        to_lower = (self.lower - points) / safe
        to_upper = (self.upper - points) / safe
        within = (points >= self.lower) & (points <= self.upper)
        far = torch.full_like(points, math.inf)
        entry = torch.where(moving, torch.minimum(to_lower, to_upper), torch.where(within, -far, far))
        leave = torch.where(moving, torch.maximum(to_lower, to_upper), torch.where(within, far, -far))
        enter_at = entry.amax(dim=-1)
        hits = (enter_at <= leave.amin(dim=-1)) & (enter_at >= 0)
        return torch.where(hits, enter_at, torch.full_like(enter_at, math.inf))
