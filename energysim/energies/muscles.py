"""Actuation as energy: springs whose rest length the action shortens."""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.energies.base import ElementEnergy, as_parameter, check_per_element, check_positive
from energysim.energies.springs import spring_energy, spring_hessian_blocks, spring_length
from energysim.mesh import SimplexMesh


class ActuatedSprings(ElementEnergy):
    """Springs whose rest length is ℓ₀ (1 − c·a), a = the action of the spring's actuator.

    Each spring belongs to one actuator; `action[:, j]` drives actuator j and is clamped to
    [−1, 1], so the rest length stays within ℓ₀ (1 ± c): a contraction c < 1 keeps it positive.

    Args:
        edges: vertex pairs, shape `[s, 2]`.
        actuators: the actuator of each spring, shape `[s]`, integers in [0, a).
        stiffness: k in N/m, a scalar or shape `[s]`.
        max_contraction: c, the fraction of the rest length an action of 1 takes off, in (0, 1).
        rest_length: ℓ₀ in m, a scalar or shape `[s]`; None measures it on the rest mesh.
    """

    def __init__(
        self,
        edges: Tensor,
        actuators: Tensor,
        stiffness: float | Tensor = 1.0,
        max_contraction: float = 0.3,
        rest_length: float | Tensor | None = None,
    ) -> None:
        super().__init__()
        if not 0 < max_contraction < 1:
            raise ValueError(f"max_contraction must lie in (0, 1), got {max_contraction}")
        self._edges = torch.as_tensor(edges, dtype=torch.int64)
        self.register_buffer("actuators", torch.as_tensor(actuators, dtype=torch.int64))
        self.register_buffer("stiffness", as_parameter(stiffness, "stiffness"))
        self._rest_length = None if rest_length is None else as_parameter(rest_length, "rest_length")
        self.max_contraction = max_contraction

    @property
    def num_actuators(self) -> int:
        """How many entries of the action this term reads."""
        return int(self.actuators.max()) + 1

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        edges = self._edges
        if edges.ndim != 2 or edges.shape[1] != 2 or edges.shape[0] == 0:
            raise ValueError(f"edges must have shape [s, 2] with s > 0, got {tuple(edges.shape)}")
        out_of_range = ((edges < 0) | (edges >= mesh.num_vertices)).any(dim=1)
        if out_of_range.any():
            index = torch.nonzero(out_of_range).reshape(-1)[:10].tolist()
            raise ValueError(f"springs {index} name vertices outside [0, {mesh.num_vertices})")
        if tuple(self.actuators.shape) != (edges.shape[0],) or bool((self.actuators < 0).any()):
            raise ValueError(f"actuators must be non-negative integers of shape [{edges.shape[0]}]")
        check_per_element(self.stiffness, edges.shape[0], "stiffness", "spring")
        check_positive(self.stiffness, "stiffness", "N/m")
        if self._rest_length is None:
            rest_length = (mesh.vertices[edges[:, 1]] - mesh.vertices[edges[:, 0]]).norm(dim=-1)
        else:
            rest_length = self._rest_length
            check_per_element(rest_length, edges.shape[0], "rest_length", "spring")
            check_positive(rest_length, "rest_length", "m")
        self.register_buffer("element_vertices", edges.contiguous())
        self.register_buffer("rest_length", rest_length)

    def actuated_rest_length(self, action: Tensor | None) -> Tensor:
        """ℓ₀ (1 − c·clamp(a, −1, 1)) per spring, shape `[B, s]` (or `[s]` without an action), in m."""
        if action is None:
            return self.rest_length
        if action.shape[-1] < self.num_actuators:
            raise ValueError(
                f"action has {action.shape[-1]} entries; these springs need {self.num_actuators}"
            )
        activation = action[:, self.actuators].clamp(-1.0, 1.0)
        return self.rest_length * (1.0 - self.max_contraction * activation)

    def element_energy(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        _, length = spring_length(element_positions, self.rest_length)
        return spring_energy(length, self.stiffness, self.actuated_rest_length(action))

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Exact per-spring Hessian blocks `[B, s, 2d, 2d]` (closed form; see `spring_hessian_blocks`)."""
        delta, length = spring_length(element_positions, self.rest_length)
        return spring_hessian_blocks(delta, length, self.stiffness, self.actuated_rest_length(action))
