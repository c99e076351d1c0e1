"""The implicit-Euler kinetic term."""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.energies.base import VertexDiagonalEnergy


class Inertia(VertexDiagonalEnergy):
    """½h⁻² ‖x − x̂‖²_M with x̂ = x_n + h v_n, the inertia of one implicit-Euler step.

    Built per step by the step objective, not added to scenes. With an `anchor` a, the energy
    is evaluated as ½h⁻² Σ m (|x − a|² + 2 (x − a)·(a − x̂)), which differs by a constant only
    but whose rounding error scales with x − a, not with a − x̂: near convergence the line
    search must resolve energy changes far smaller than the energy itself.

    Args:
        vertex_mass: lumped masses, shape `[n]`, in kg.
        dt: time step h in s.
        predicted_positions: x̂, shape `[B, n, d]`, in m.
        anchor: a, shape `[B, n, d]` (the solver's starting point), or None.
    """

    has_gradient_kernel = True

    def __init__(
        self, vertex_mass: Tensor, dt: float, predicted_positions: Tensor, anchor: Tensor | None = None
    ) -> None:
        super().__init__()
        # only M/h² is kept (not M and h, whose later change would then change nothing), as a
        # tensor, which compiled evaluations read as data. They would bake a float h into
        # the graph and compile anew for each h (two per TR-BDF2 step size); past torch.compile's
        # limit of 8 graphs per function the evaluations fell back to eager, and a TR-BDF2 run at
        # h = 1/48 s after runs at other steps took 0.89 instead of 0.45 s per simulated second.
        self.mass_per_dt_squared = vertex_mass / dt**2
        self.predicted_positions = predicted_positions
        self.anchor = anchor

    def forward(self, x: Tensor, action: Tensor | None = None) -> Tensor:
        weight = 0.5 * self.mass_per_dt_squared[:, None]
        if self.anchor is None:
            offset = x - self.predicted_positions
            return (weight * offset * offset).sum(dim=(-1, -2))
        displacement = x - self.anchor
        lead = self.anchor - self.predicted_positions
        return (weight * displacement * (displacement + 2.0 * lead)).sum(dim=(-1, -2))

    def value_and_gradient(self, x: Tensor, action: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """E and ∇E = M (x − x̂)/h², in closed form."""
        with torch.no_grad():
            gradient = self.mass_per_dt_squared[:, None] * (x - self.predicted_positions)
            return self.forward(x), gradient

    def rows(self, entries: Tensor) -> Inertia:
        """The inertia of the batch entries `entries` alone (see `EnergyTerm.rows`)."""
        anchor = None if self.anchor is None else self.anchor[entries]
        return self._with(predicted_positions=self.predicted_positions[entries], anchor=anchor)

    def hessian_diagonal(self) -> Tensor:
        """The (constant, diagonal) Hessian M/h², per vertex, shape `[n]`, in kg/s²."""
        return self.mass_per_dt_squared
