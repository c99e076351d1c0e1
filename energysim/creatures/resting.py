"""A creature's start on the ground: the scene's one `Ground` term, and a state moved along its
normal so that the body touches the barrier from the first step instead of falling onto it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.contact import Ground
from energysim.model.scene import Scene


def scene_ground(scene: Scene) -> Ground:
    """The scene's one `Ground` term; ValueError when it has none or several."""
    grounds = [term for term in scene.terms if isinstance(term, Ground)]
    if len(grounds) != 1:
        raise ValueError(f"expected one Ground term in the scene, found {len(grounds)}")
    return grounds[0]


def resting_state(
    scene: Scene, positions: Tensor | None = None, velocities: Tensor | None = None
) -> Tensor:
    """A state that starts in contact with the ground, outside it: `positions` moved along the ground's
    normal until the lowest vertex is half the barrier distance d̂ above it.

    With the rest positions (lowest vertex on the ground) that is the rest shape lifted by d̂/2: inside
    the barrier's reach, so the creature rests on the ground from the first step instead of falling
    onto it.

    Args:
        scene: a scene with one `Ground` term (e.g. from `Creature.scene`).
        positions: shape `[n, d]` or `[B, n, d]`, in m; default the rest positions.
        velocities: same shape, in m/s; default zero.

    Returns:
        the state, shape `[2·n·d]` (or `[B, 2·n·d]` for batched positions).
    """
    ground = scene_ground(scene)
    x = scene.rest_positions if positions is None else torch.as_tensor(positions).to(scene.rest_positions)
    n, d = scene.num_vertices, scene.dim
    if tuple(x.shape[-2:]) != (n, d) or x.ndim not in (2, 3):
        raise ValueError(f"positions must have shape [{n}, {d}] or [B, {n}, {d}], got {list(x.shape)}")
    v = torch.zeros_like(x) if velocities is None else torch.as_tensor(velocities).to(x)
    if v.shape != x.shape:
        raise ValueError(f"velocities must have the shape of positions {list(x.shape)}, got {list(v.shape)}")
    lowest = ground.signed_distance(x).amin(dim=-1)
    lift = 0.5 * ground.barrier_distance - lowest
    x = x + lift[..., None, None] * ground.normal.to(x)
    return torch.cat([x.flatten(-2), v.flatten(-2)], dim=-1)


__all__ = ["resting_state", "scene_ground"]
