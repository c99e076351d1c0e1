"""Internal viscosity (Kelvin–Voigt): a Rayleigh dissipation of the Green strain rate.

    D(x, v) = Σ_e V_e η ‖Ė_e‖²,   Ė = sym(Fᵀ Ḟ),   Ḟ = Σ_b v_b ⊗ ∇N_b,

so the viscous stress is P = ∂D/∂Ḟ / V = 2η F Ė: Newtonian at small strain (σ = 2η ε̇) and zero for
every rigid motion (FᵀḞ is then skew), so it damps deformation, never a translation or a spin.
The forces are −∂D/∂v and they take power 2D out of the body.

An explicit step (`energysim.integrators.explicit`) takes the force in each kick, at the kick's velocity. An
implicit step minimises an energy of positions only; there the term adds h·D(x_n, (x − x_n)/h)
with F lagged at the step's start, `LaggedViscosity`, whose gradient is the viscous force at the
step's end velocity (backward Euler, as the rest of the step).

Why a body needs it: leapfrog conserves energy, and the elastic waves that muscles and impacts
start never die, where real tissue damps them within a few periods. Undamped, the worm's 2 s gait
went 9.2, 11.3, 12.3 and 14.0 cm at 32, 64, 128 and 256 substeps: a chaotic ringing body, whose
walk no step size resolves.
"""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.energies.base import (
    DissipativeEnergy,
    ElementEnergy,
    EnergyTerm,
    as_parameter,
    check_positive,
    scatter_vertices,
)
from energysim.fem.hessian_entries import lagged_viscosity_hessian_entries
from energysim.fem.kernels import (
    lagged_viscosity_energy_and_stress_entries,
    lagged_viscosity_hessian_blocks,
    viscous_stress,
    viscous_stress_entries,
)
from energysim.fem.kinematics import (
    corner_forces_entries,
    deformation_gradient,
    deformation_gradient_entries,
    shape_gradients,
    simplex_rest_frame,
)
from energysim.linalg.batch_innermost import batch_innermost
from energysim.linalg.small_matmul import small_matmul
from energysim.mesh import SimplexMesh


def strain_rate(F: Tensor, rate: Tensor) -> Tensor:
    """Ė = sym(Fᵀ Ḟ), the rate of the Green strain, shape `[..., d, d]`, in 1/s."""
    product = small_matmul(F.transpose(-1, -2), rate)
    return 0.5 * (product + product.transpose(-1, -2))


class Viscosity(DissipativeEnergy):
    """Kelvin–Voigt viscosity η on every element of the mesh: no stored energy, a dissipation.

    Its energy is zero (so implicit solvers and energy checks see nothing of it): it acts through
    `dissipation_gradient` in explicit steps and `lagged_terms` in implicit ones.

    Args:
        viscosity: η in Pa·s, > 0, a scalar. A mode of angular frequency ω and modulus M is damped
            at ratio about ηω/M: the worm's gait (ω ≈ 10 /s) keeps its motion, its stiffest
            element modes (ω ≈ 3,000 /s) ring down within periods.
    """

    has_batch_last_kernel = True

    def __init__(self, viscosity: float | Tensor) -> None:
        super().__init__()
        viscosity = as_parameter(viscosity, "viscosity")
        if viscosity.ndim != 0:
            raise ValueError(f"viscosity must be a scalar in Pa·s, got shape {tuple(viscosity.shape)}")
        check_positive(viscosity.reshape(1), "viscosity", "Pa·s")
        self.register_buffer("viscosity", viscosity)

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        rest_edge_inverse, rest_volume = simplex_rest_frame(mesh.vertices, mesh.elements)
        self.register_buffer("element_vertices", mesh.elements)
        self.register_buffer("rest_edge_inverse", rest_edge_inverse)
        self.register_buffer("rest_volume", rest_volume)
        self.register_buffer("shape_gradient", shape_gradients(rest_edge_inverse), persistent=False)
        self.register_buffer(
            "shape_gradient_t", self.shape_gradient.permute(1, 2, 0).contiguous(), persistent=False
        )

    def _deformation_and_rate(self, x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        F = deformation_gradient(x[:, self.element_vertices], self.rest_edge_inverse)
        rate = deformation_gradient(v[:, self.element_vertices], self.rest_edge_inverse)
        return F, rate

    def dissipation(self, x: Tensor, v: Tensor) -> Tensor:
        """D(x, v) `[B]` in W (half the power the viscous forces take), at positions and velocities
        `[B, n, d]`."""
        F, rate = self._deformation_and_rate(x, v)
        return (self.viscosity * self.rest_volume * strain_rate(F, rate).square().sum(dim=(-1, -2))).sum(-1)

    def dissipation_gradient(self, x: Tensor, v: Tensor) -> Tensor:
        """∂D/∂v `[B, n, d]` in N: minus the viscous forces (closed form, checked against autograd)."""
        F, rate = self._deformation_and_rate(x, v)
        stress = viscous_stress(F, rate, self.viscosity) * self.rest_volume[:, None, None]
        corner = small_matmul(self.shape_gradient, stress.transpose(-1, -2))  # [B, m, k, d]: V P ∇N_b
        return scatter_vertices(corner, self.element_vertices, x.shape[1])

    def batch_last_dissipation_gradient(
        self, corners: list[list[Tensor]], velocities: list[list[Tensor]]
    ) -> list[list[Tensor]]:
        """∂D/∂v entry by entry with the batch innermost (see `ElementEnergy.batch_last_forces`):
        `corners[i][b]` and `velocities[i][b]` `[m, B]`; returns ∂D/∂v_bi `[m, B]` in N."""
        F = deformation_gradient_entries(corners, self.shape_gradient_t)
        rate = deformation_gradient_entries(velocities, self.shape_gradient_t)
        stress = viscous_stress_entries(F, rate, self.viscosity)
        return corner_forces_entries(stress, self.shape_gradient_t, self.rest_volume)

    def lagged_terms(self, x_prev: Tensor, dt: float) -> list[EnergyTerm]:
        """This step's `LaggedViscosity`, with F at the step's start `x_prev` `[B, n, d]`."""
        # F = Σ_b x_b ⊗ ∇N_b, eagerly at every step: one batched product per element over the corners
        # gathered with the batch innermost, (F_ij)ᵀ per entry `[m, j, i, B]`, whose view `[B, m, i, j]`
        # is F and whose batch-last copy (`LaggedViscosity.start_gradient_t`) reads rows of B numbers;
        # an `einsum` over the `[B, m, k, d]` corners cost several times more (docs/envs.md)
        elements, corners, dim = self.shape_gradient.shape
        batch = x_prev.shape[0]
        positions = x_prev.permute(1, 2, 0).contiguous()[self.element_vertices]  # [m, k, d, B]
        columns = positions.reshape(elements, corners, dim * batch)
        transposed = torch.bmm(self.shape_gradient.transpose(1, 2), columns)
        return [LaggedViscosity(self, transposed.reshape(elements, dim, dim, batch).permute(3, 0, 2, 1), dt)]


class LaggedViscosity(ElementEnergy):
    """One implicit step's viscosity: h·D(x_n, (x − x_n)/h) with F lagged at x_n,

        Φ(x) = Σ_e (η V_e / h) ‖sym(F_nᵀ (F(x) − F_n))‖²,

    a convex quadratic in x whose gradient is the viscous force at the step's end velocity. Built
    by `Viscosity.lagged_terms`; not added to scenes.

    Args:
        viscosity: the scene's term (its elements, rest shape and η).
        start_gradient: F_n, shape `[B, m, d, d]`.
        dt: the step h in s.
    """

    has_constant_hessian = True
    has_gradient_kernel = True
    has_hessian_kernel = True
    is_translation_invariant = True

    def __init__(self, viscosity: Viscosity, start_gradient: Tensor, dt: float) -> None:
        super().__init__()
        self.element_vertices = viscosity.element_vertices
        self.rest_edge_inverse = viscosity.rest_edge_inverse
        self.shape_gradient = viscosity.shape_gradient
        self.shape_gradient_t = viscosity.shape_gradient_t
        self.start_gradient = start_gradient
        # F_n batch innermost, `[d, d, m, B]`, for the batch-last kernels: read strided from
        # `start_gradient`, the constant Hessian entries took longer than the neo-Hookean ones
        self.start_gradient_t = batch_innermost(start_gradient, 2, 3, 1, 0)
        # η V / h per element, a tensor: compiled evaluations then need no new graph for a new h
        step = torch.as_tensor(dt, dtype=start_gradient.dtype, device=start_gradient.device)
        self.weight = viscosity.viscosity * viscosity.rest_volume / step

    def rows(self, entries: Tensor) -> LaggedViscosity:
        """This step's viscosity for the batch entries `entries` alone (see `EnergyTerm.rows`)."""
        start_gradient = self.start_gradient[entries]
        return self._with(
            start_gradient=start_gradient, start_gradient_t=batch_innermost(start_gradient, 2, 3, 1, 0)
        )

    def _strain(self, element_positions: Tensor) -> Tensor:
        change = deformation_gradient(element_positions, self.rest_edge_inverse) - self.start_gradient
        return strain_rate(self.start_gradient, change)

    def element_energy(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        return self.weight * self._strain(element_positions).square().sum(dim=(-1, -2))

    def element_energy_and_gradient(
        self, element_positions: Tensor, action: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """`element_energy` `[B, m]` in J and 2ηV/h · F_n S ∇N_b per corner `[B, m, k, d]` in N."""
        strain = self._strain(element_positions)
        stress = 2.0 * self.weight[:, None, None] * small_matmul(self.start_gradient, strain)
        energy = self.weight * strain.square().sum(dim=(-1, -2))
        return energy, small_matmul(self.shape_gradient, stress.transpose(-1, -2))

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Constant blocks (ηV/h)[(F_nF_nᵀ)_kl ∇N_b·∇N_c + (F_n∇N_c)_k (F_n∇N_b)_l], shape
        `[B, m, (d+1)d, (d+1)d]`, in N/m (closed form, checked against autograd)."""
        return lagged_viscosity_hessian_blocks(self.start_gradient, self.shape_gradient, self.weight)

    def batch_last_energy_and_forces(
        self, corners: list[list[Tensor]], action: Tensor | None
    ) -> tuple[Tensor, list[list[Tensor]]]:
        """`element_energy` `[m, B]` and its corner gradients entry by entry, batch innermost (see
        `ElementEnergy.batch_last_energy_and_forces`;
        `energysim.fem.kernels.lagged_viscosity_energy_and_stress_entries`)."""
        F = deformation_gradient_entries(corners, self.shape_gradient_t)
        weight = self.weight[:, None]
        energy, stress = lagged_viscosity_energy_and_stress_entries(F, self.start_gradient_t, weight)
        return energy, corner_forces_entries(stress, self.shape_gradient_t, self.weight)

    def batch_last_hessian_entries(self, corners: list[list[Tensor]], action: Tensor | None) -> list[Tensor]:
        """The upper entries of the constant blocks, batch innermost (see
        `ElementEnergy.batch_last_hessian_entries`;
        `energysim.fem.hessian_entries.lagged_viscosity_hessian_entries`)."""
        return lagged_viscosity_hessian_entries(self.start_gradient_t, self.shape_gradient_t, self.weight)
