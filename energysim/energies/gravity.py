"""Uniform gravity."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from energysim.energies.base import EnergyTerm
from energysim.mesh import SimplexMesh


class Gravity(EnergyTerm):
    """−Σ_i m_i g·x_i, the potential of a uniform gravity field.

    Args:
        acceleration: g, a vector of d components, in m/s² (e.g. `(0, -9.81, 0)`); may be a tensor
            that requires grad.
    """

    is_linear = True
    has_gradient_kernel = True

    def __init__(self, acceleration: Sequence[float] | Tensor) -> None:
        super().__init__()
        acceleration = torch.as_tensor(acceleration, dtype=torch.float64)
        if acceleration.ndim != 1 or not torch.isfinite(acceleration).all():
            raise ValueError(f"gravity must be a finite vector, got {acceleration.tolist()}")
        self.register_buffer("acceleration", acceleration)
        self.register_buffer("vertex_mass", torch.zeros(0, dtype=torch.float64))

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        if self.acceleration.shape[0] != mesh.dim:
            raise ValueError(
                f"gravity has {self.acceleration.shape[0]} components but the mesh is {mesh.dim}D"
            )
        self.vertex_mass = vertex_mass

    def forward(self, x: Tensor, action: Tensor | None = None) -> Tensor:
        return -(self.vertex_mass[:, None] * x * self.acceleration).sum(dim=(-1, -2))

    def value_and_gradient(self, x: Tensor, action: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """E and ∇E = −m g, in closed form."""
        with torch.no_grad():
            gradient = -(self.vertex_mass[:, None] * self.acceleration).expand_as(x)
            return self.forward(x), gradient
