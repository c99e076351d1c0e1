"""Static obstacle shapes: signed distance, its derivatives, and the time of impact (CCD).

Each shape is an `Obstacle` (`energysim.contact.obstacle_term`: the barrier term, its step limit and
friction) that defines `signed_distance`, `distance_derivatives` and `time_of_impact` in closed form.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from energysim.contact.obstacle_term import (
    BARRIER_DISTANCE_FRACTION,
    CCD_SAFETY,
    STANDARD_GRAVITY,
    Obstacle,
    contact_areas,
)
from energysim.contact.projection import project_contacts, safe_norm

__all__ = [
    "BARRIER_DISTANCE_FRACTION",
    "CCD_SAFETY",
    "STANDARD_GRAVITY",
    "BoxObstacle",
    "Ground",
    "HalfSpace",
    "Obstacle",
    "SphereObstacle",
    "contact_areas",
    "project_contacts",
]


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

    def distance_derivative_entries(self, points: list[Tensor]) -> tuple[Tensor, list[Tensor], None]:
        """The distance n·p − n·p₀, its constant gradient n and zero Hessian, per coordinate (see
        `Obstacle.distance_derivative_entries`)."""
        normal = self.normal.to(points[0].dtype)
        distance = sum(points[i] * normal[i] for i in range(len(points))) - self.offset
        return distance, [normal[i].expand_as(points[0]) for i in range(len(points))], None

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
        length, _ = safe_norm(points - self.center)
        return length - self.radius

    def distance_derivatives(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        offset = points - self.center
        length, divisor = safe_norm(offset)
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
        outside, _ = safe_norm(excess.clamp_min(0.0))
        inside = excess.amax(dim=-1).clamp(max=0.0)
        return outside + inside

    def distance_derivatives(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        # outside the box d = ‖max(q, 0)‖ with q = |x − c| − half: the distance to the nearest face,
        # edge or corner; its Hessian lives on the axes where the point is beyond a face
        offset, excess = self._excess(points)
        beyond = excess.clamp_min(0.0)
        length, divisor = safe_norm(beyond)
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
