"""Hookean springs between pairs of vertices."""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.energies.base import ElementEnergy, as_parameter, check_per_element, check_positive
from energysim.mesh import SimplexMesh
from energysim.mesh.indices import as_indices


def spring_energy(length: Tensor, stiffness: Tensor, rest_length: Tensor) -> Tensor:
    """½ k (ℓ − ℓ₀)², in J, broadcasting over springs."""
    return 0.5 * stiffness * (length - rest_length) ** 2


def spring_length(element_positions: Tensor, rest_length: Tensor) -> tuple[Tensor, Tensor]:
    """Edge vectors `[..., s, d]` and lengths `[..., s]`.

    A tiny floor under the squared length keeps a collapsed spring's gradient finite.
    """
    delta = element_positions[..., 1, :] - element_positions[..., 0, :]
    floor = 1e-30 * (1.0 + rest_length.detach()) ** 2
    return delta, torch.sqrt((delta * delta).sum(dim=-1) + floor)


def spring_hessian_blocks(delta: Tensor, length: Tensor, stiffness: Tensor, rest_length: Tensor) -> Tensor:
    """Exact Hessian of ½k(ℓ − ℓ₀)² per spring, shape `[..., s, 2d, 2d]`, in N/m.

    A closed form for speed (tests check it against autograd): with n the unit edge vector, the
    vertex block is K = k [n nᵀ + (1 − ℓ₀/ℓ)(I − n nᵀ)] and the spring's is [[K, −K], [−K, K]].
    """
    dim = delta.shape[-1]
    direction = delta / length[..., None]
    outer = direction[..., :, None] * direction[..., None, :]
    eye = torch.eye(dim, dtype=delta.dtype, device=delta.device)
    stiffness = torch.as_tensor(stiffness, dtype=delta.dtype).expand(length.shape)
    tangential = (1.0 - rest_length / length)[..., None, None]
    block = stiffness[..., None, None] * (outer + tangential * (eye - outer))
    return torch.cat([torch.cat([block, -block], dim=-1), torch.cat([-block, block], dim=-1)], dim=-2)


class Springs(ElementEnergy):
    """Hookean springs: Σ_s ½ k_s (|x_j − x_i| − ℓ₀_s)².

    Args:
        edges: vertex pairs, shape `[s, 2]`; None takes every edge of the mesh.
        stiffness: k in N/m, a scalar or shape `[s]`.
        rest_length: ℓ₀ in m, a scalar or shape `[s]`; None measures it on the rest mesh.
    """

    has_gradient_kernel = True
    has_hessian_kernel = True
    is_translation_invariant = True

    def __init__(
        self,
        edges: Tensor | None = None,
        stiffness: float | Tensor = 1.0,
        rest_length: float | Tensor | None = None,
    ) -> None:
        super().__init__()
        self._edges = None if edges is None else as_indices(edges, "edges")
        self.register_buffer("stiffness", as_parameter(stiffness, "stiffness"))
        self._rest_length = None if rest_length is None else as_parameter(rest_length, "rest_length")

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        edges = mesh.edges() if self._edges is None else self._edges
        if edges.ndim != 2 or edges.shape[1] != 2 or edges.shape[0] == 0:
            raise ValueError(f"edges must have shape [s, 2] with s > 0, got {tuple(edges.shape)}")
        out_of_range = ((edges < 0) | (edges >= mesh.num_vertices)).any(dim=1)
        if out_of_range.any():
            index = torch.nonzero(out_of_range).reshape(-1)[:10].tolist()
            raise ValueError(f"springs {index} name vertices outside [0, {mesh.num_vertices})")
        count = edges.shape[0]
        check_per_element(self.stiffness, count, "stiffness", "spring")
        check_positive(self.stiffness, "stiffness", "N/m")
        if self._rest_length is None:
            rest_length = (mesh.vertices[edges[:, 1]] - mesh.vertices[edges[:, 0]]).norm(dim=-1)
        else:
            rest_length = self._rest_length
            check_per_element(rest_length, count, "rest_length", "spring")
        bad = ~(torch.isfinite(rest_length) & (rest_length >= 0))
        if bad.any():
            index = torch.nonzero(bad.reshape(-1)).reshape(-1)[:10].tolist()
            raise ValueError(f"rest lengths must be finite and >= 0; offending springs {index}")
        self.register_buffer("element_vertices", edges.contiguous())
        self.register_buffer("rest_length", rest_length)

    def target_length(self, action: Tensor | None) -> Tensor:
        """The length each spring is at rest at under `action`, in m: ℓ₀ here (actuators change it)."""
        return self.rest_length

    def element_energy(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        _, length = spring_length(element_positions, self.rest_length)
        return spring_energy(length, self.stiffness, self.target_length(action))

    def element_energy_and_gradient(
        self, element_positions: Tensor, action: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """Energies `[B, s]` in J and ∂E/∂x of both ends, k(ℓ − ℓ₀) (∓n), `[B, s, 2, d]` in N."""
        delta, length = spring_length(element_positions, self.rest_length)
        target = self.target_length(action)
        tension = self.stiffness * (length - target) / length
        pull = tension[..., None] * delta
        return spring_energy(length, self.stiffness, target), torch.stack([-pull, pull], dim=-2)

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Exact per-spring Hessian blocks `[B, s, 2d, 2d]` (closed form; see `spring_hessian_blocks`)."""
        delta, length = spring_length(element_positions, self.rest_length)
        return spring_hessian_blocks(delta, length, self.stiffness, self.target_length(action))
