"""What a creature's controller sees: centre of mass, marker vertices, orientation, activations.

Pure, batched functions of positions `[B, n, d]` and velocities; nothing here steps a scene. The
observation leaves out the horizontal position of the centre of mass (the ground is the same
everywhere, so a policy should not depend on it) but keeps its height: the ground breaks vertical
translation invariance, and a jumper in the air must know it is not standing.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def farthest_point_markers(points: Tensor, candidates: Tensor, count: int) -> Tensor:
    """`count` well-spread vertices among `candidates` by farthest-point sampling, deterministically.

    The first marker is the candidate farthest from the candidates' centroid; each next one is the
    candidate farthest from the markers chosen so far. Ties go to the lowest index, so the choice
    depends only on the mesh.

    Args:
        points: vertex positions, shape `[n, d]`, in m.
        candidates: indices of the vertices to choose from (e.g. the surface vertices), shape `[k]`.
        count: how many markers, 1 ≤ count ≤ k.

    Returns:
        vertex indices, shape `[count]`, int64, in the order chosen.
    """
    candidates = torch.as_tensor(candidates, dtype=torch.int64).reshape(-1)
    if not 1 <= count <= candidates.numel():
        raise ValueError(f"count must lie in [1, {candidates.numel()}] (the candidates), got {count}")
    where = points[candidates]
    first = int(torch.argmax((where - where.mean(dim=0)).norm(dim=-1)))
    chosen = [first]
    nearest = (where - where[first]).norm(dim=-1)
    for _ in range(count - 1):
        # argmax returns the first maximum: the lowest candidate position wins a tie
        following = int(torch.argmax(nearest))
        chosen.append(following)
        nearest = torch.minimum(nearest, (where - where[following]).norm(dim=-1))
    return candidates[torch.tensor(chosen, dtype=torch.int64)]


def centre_of_mass(x: Tensor, vertex_mass: Tensor) -> Tensor:
    """Mass-weighted mean of `x` (positions or velocities) `[B, n, d]`, shape `[B, d]`."""
    weight = vertex_mass / vertex_mass.sum()
    return (weight[:, None] * x).sum(dim=-2)


def best_fit_rotation(x: Tensor, rest: Tensor, vertex_mass: Tensor) -> Tensor:
    """The proper rotation R `[B, d, d]` that best maps the rest shape onto `x` (mass-weighted Kabsch).

    R minimises Σ_i m_i ‖R (X_i − X̄) − (x_i − x̄)‖² over rotations (det R = +1), X the rest positions
    `[n, d]` and x `[B, n, d]`, bars the centres of mass: the orientation of the body's best-fit
    rigid frame, well defined however the body deforms (unless it collapses to a line).
    """
    weight = vertex_mass / vertex_mass.sum()
    rest_centred = rest - (weight[:, None] * rest).sum(dim=0)
    centred = x - centre_of_mass(x, vertex_mass)[:, None, :]
    covariance = torch.einsum("n,ni,bnj->bij", weight, rest_centred, centred)
    u, _, vh = torch.linalg.svd(covariance)
    # flip the least significant axis where the optimal orthogonal map would be a reflection
    sign = torch.sign(torch.linalg.det(vh.mT @ u.mT))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    flip = torch.ones(x.shape[0], x.shape[-1], dtype=x.dtype, device=x.device)
    flip[:, -1] = sign
    return vh.mT @ (flip[:, :, None] * u.mT)


def orientation_features(rotation: Tensor) -> Tensor:
    """A continuous encoding of rotations `[B, d, d]`: the first d − 1 columns, shape `[B, d(d − 1)]`.

    In 3D these are the 6 numbers of Zhou et al. (2019), "On the continuity of rotation
    representations in neural networks": unlike Euler angles or quaternions (q and −q) they have no
    jumps, and the last column is their cross product. In 2D the first column is (cos θ, sin θ).
    """
    d = rotation.shape[-1]
    return rotation[..., :, : d - 1].mT.reshape(rotation.shape[0], -1)


@dataclass(frozen=True)
class ObservationLayout:
    """Where each quantity sits in an observation vector (d: dimension, K: markers, a: actuators).

    Attributes:
        com_height: centre-of-mass height above the ground, 1 entry, in m.
        com_velocity: centre-of-mass velocity, d entries, in m/s.
        marker_positions: K marker positions relative to the centre of mass, K·d entries (marker-major),
            in m, world axes.
        marker_velocities: their velocities relative to the centre-of-mass velocity, K·d entries, in m/s.
        orientation: `orientation_features` of the best-fit rotation, d(d − 1) entries.
        activation: the activations the muscles hold, a entries: the last action (clipped to
            [−1, 1]), or its filtered value with `activation_time_constant`.
    """

    com_height: slice
    com_velocity: slice
    marker_positions: slice
    marker_velocities: slice
    orientation: slice
    activation: slice

    @classmethod
    def build(cls, dim: int, num_markers: int, num_actuators: int) -> ObservationLayout:
        """Consecutive slices in the order of the attributes."""
        sizes = {
            "com_height": 1,
            "com_velocity": dim,
            "marker_positions": num_markers * dim,
            "marker_velocities": num_markers * dim,
            "orientation": dim * (dim - 1),
            "activation": num_actuators,
        }
        slices, start = {}, 0
        for name, size in sizes.items():
            slices[name] = slice(start, start + size)
            start += size
        return cls(**slices)

    @property
    def size(self) -> int:
        """Length of the observation vector."""
        return self.activation.stop


def observe(
    x: Tensor,
    v: Tensor,
    activation: Tensor,
    rest: Tensor,
    vertex_mass: Tensor,
    markers: Tensor,
    up: Tensor,
    ground_offset: float,
) -> Tensor:
    """The observation vectors, shape `[B, layout.size]`, in the order of `ObservationLayout`.

    Args:
        x, v: positions (m) and velocities (m/s), shape `[B, n, d]`.
        activation: the activations the muscles hold, shape `[B, a]`.
        rest: rest positions, shape `[n, d]`, in m.
        vertex_mass: shape `[n]`, in kg.
        markers: marker vertex indices, shape `[K]`.
        up: the ground's unit normal, shape `[d]`.
        ground_offset: the ground plane's offset along `up`, in m.
    """
    com = centre_of_mass(x, vertex_mass)
    com_velocity = centre_of_mass(v, vertex_mass)
    height = (com * up).sum(dim=-1, keepdim=True) - ground_offset
    relative_positions = (x[:, markers] - com[:, None, :]).flatten(1)
    relative_velocities = (v[:, markers] - com_velocity[:, None, :]).flatten(1)
    orientation = orientation_features(best_fit_rotation(x, rest, vertex_mass))
    parts = (height, com_velocity, relative_positions, relative_velocities, orientation, activation.to(x))
    return torch.cat(parts, dim=-1)


__all__ = [
    "ObservationLayout",
    "best_fit_rotation",
    "centre_of_mass",
    "farthest_point_markers",
    "observe",
    "orientation_features",
]
