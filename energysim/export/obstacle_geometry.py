"""Triangulated surfaces of a scene's obstacles, for drawing them beside the body.

Obstacles are implicit (a signed distance), so a picture needs a finite stand-in: the ground or any
half-space becomes a rectangle on its plane, sized to the motion (the range the body's vertices cover
on the plane, plus a quarter of it on every side); spheres and boxes are drawn as they are. In 2D an
obstacle is a region of the plane, drawn filled: a half-space as a rectangle below its line, a circle
as a fan of triangles, a box as two. Obstacles of other shapes are left out, with a warning.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from energysim.contact.obstacles import BoxObstacle, HalfSpace, Obstacle, SphereObstacle

if TYPE_CHECKING:
    from energysim.model.scene import Scene

logger = logging.getLogger(__name__)

# fraction of the motion's extent added around it on a half-space's plane
_MARGIN = 0.25
_SEGMENTS = 32  # around a circle or a sphere's equator


def _tangents(normal: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors that span the plane orthogonal to the unit `normal` `[3]`."""
    helper = torch.zeros_like(normal)
    helper[int(torch.argmin(normal.abs()))] = 1.0
    first = torch.linalg.cross(normal, helper)
    first = first / first.norm()
    return first, torch.linalg.cross(normal, first)


def _span(values: Tensor) -> tuple[float, float]:
    low, high = float(values.min()), float(values.max())
    pad = _MARGIN * (high - low) if high > low else 0.0
    pad = pad or _MARGIN * max(1.0, abs(low))
    return low - pad, high + pad


def _half_space(obstacle: HalfSpace, points: Tensor, dim: int) -> tuple[Tensor, Tensor]:
    normal, offset = obstacle.normal.detach().to(points), float(obstacle.offset)
    if dim == 2:
        tangent = torch.stack([normal[1], -normal[0]])
        lo, hi = _span(points @ tangent)
        depth = hi - lo
        base = offset * normal
        corners = [base + lo * tangent, base + hi * tangent]
        corners += [corners[1] - depth * normal, corners[0] - depth * normal]
    else:
        first, second = _tangents(normal)
        (lo1, hi1), (lo2, hi2) = _span(points @ first), _span(points @ second)
        base = offset * normal
        corners = [base + a * first + b * second for a, b in ((lo1, lo2), (hi1, lo2), (hi1, hi2), (lo1, hi2))]
    # counter-clockwise seen from the outside (along the normal in 3D)
    return torch.stack(corners), torch.tensor([[0, 1, 2], [0, 2, 3]])


def _sphere(obstacle: SphereObstacle, dim: int) -> tuple[Tensor, Tensor]:
    center, radius = obstacle.center.detach().to(torch.float64), obstacle.radius
    if dim == 2:
        angle = torch.arange(_SEGMENTS, dtype=torch.float64) * (2 * math.pi / _SEGMENTS)
        ring = center + radius * torch.stack([angle.cos(), angle.sin()], dim=1)
        k = torch.arange(_SEGMENTS)
        triangles = torch.stack([torch.zeros_like(k), k + 1, (k + 1) % _SEGMENTS + 1], dim=1)
        return torch.cat([center[None], ring]), triangles
    rings, around = _SEGMENTS // 2, _SEGMENTS
    polar = torch.arange(1, rings, dtype=torch.float64) * (math.pi / rings)
    azimuth = torch.arange(around, dtype=torch.float64) * (2 * math.pi / around)
    p, a = torch.meshgrid(polar, azimuth, indexing="ij")
    body = torch.stack([p.sin() * a.cos(), p.cos(), p.sin() * a.sin()], dim=-1).reshape(-1, 3)
    poles = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    points = center + radius * torch.cat([body, poles])
    top, bottom = body.shape[0], body.shape[0] + 1
    triangles = []
    for j in range(around):
        nxt = (j + 1) % around
        triangles.append([top, nxt, j])
        last = (rings - 2) * around
        triangles.append([bottom, last + j, last + nxt])
        for i in range(rings - 2):
            a0, a1 = i * around + j, i * around + nxt
            b0, b1 = a0 + around, a1 + around
            triangles += [[a0, a1, b0], [a1, b1, b0]]
    return points, torch.tensor(triangles)


def _box(obstacle: BoxObstacle, dim: int) -> tuple[Tensor, Tensor]:
    lower, upper = obstacle.lower.detach().to(torch.float64), obstacle.upper.detach().to(torch.float64)
    if dim == 2:
        corners = torch.stack(
            [lower, torch.stack([upper[0], lower[1]]), upper, torch.stack([lower[0], upper[1]])]
        )
        return corners, torch.tensor([[0, 1, 2], [0, 2, 3]])
    bits = torch.tensor([[(k >> axis) & 1 for axis in range(3)] for k in range(8)], dtype=torch.float64)
    corners = lower + bits * (upper - lower)
    faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    triangles = [tri for a, b, c, d in faces for tri in ([a, b, c], [a, c, d])]
    return corners, torch.tensor(triangles)


def obstacle_surfaces(scene: Scene, positions: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
    """All of the scene's obstacles as one triangle mesh; None when it has none.

    Args:
        scene: the model.
        positions: the body's vertices over the frames drawn, `[F, n, d]` in m (they size the
            half-spaces' rectangles).

    Returns:
        `(points [p, d] in m, triangles [t, 3], obstacle [t])`: `obstacle` is the position of each
        triangle's obstacle among the scene's obstacle terms (0, 1, ...).
    """
    obstacles = [term for term in scene.terms if isinstance(term, Obstacle)]
    if not obstacles:
        return None
    flat = positions.detach().reshape(-1, scene.dim).to(torch.float64)
    points, triangles, owner = [], [], []
    count = 0
    for k, obstacle in enumerate(obstacles):
        if isinstance(obstacle, HalfSpace):
            corners, tris = _half_space(obstacle, flat, scene.dim)
        elif isinstance(obstacle, SphereObstacle):
            corners, tris = _sphere(obstacle, scene.dim)
        elif isinstance(obstacle, BoxObstacle):
            corners, tris = _box(obstacle, scene.dim)
        else:
            logger.warning("obstacle %d (%s) has no drawable shape; left out", k, type(obstacle).__name__)
            continue
        points.append(corners.to(torch.float64))
        triangles.append(tris + count)
        owner.append(torch.full((tris.shape[0],), k))
        count += corners.shape[0]
    if not points:
        return None
    return torch.cat(points), torch.cat(triangles), torch.cat(owner)


__all__ = ["obstacle_surfaces"]
