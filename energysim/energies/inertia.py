"""The implicit-Euler kinetic term."""

from __future__ import annotations

from torch import Tensor

from energysim.energies.base import EnergyTerm


class Inertia(EnergyTerm):
    """½h⁻² ‖x − x̂‖²_M with x̂ = x_n + h v_n, the inertia of one implicit-Euler step.

    Built per step by the step objective, not added to scenes.

    Args:
        vertex_mass: lumped masses, shape `[n]`, in kg.
        dt: time step h in s.
        predicted_positions: x̂, shape `[B, n, d]`, in m.
    """

    def __init__(self, vertex_mass: Tensor, dt: float, predicted_positions: Tensor) -> None:
        super().__init__()
        self.vertex_mass = vertex_mass
        self.dt = dt
        self.predicted_positions = predicted_positions

    def forward(self, x: Tensor, action: Tensor | None = None) -> Tensor:
        offset = x - self.predicted_positions
        return 0.5 / self.dt**2 * (self.vertex_mass[:, None] * offset * offset).sum(dim=(-1, -2))

    def hessian_diagonal(self) -> Tensor:
        """The (constant, diagonal) Hessian M/h², per vertex, shape `[n]`, in kg/s²."""
        return self.vertex_mass / self.dt**2
