"""Stable neo-Hookean elasticity on linear simplices (tets in 3D, plane-strain triangles in 2D)."""

from __future__ import annotations

import torch
from torch import Tensor

from energysim.energies.base import as_parameter, check_per_element, check_positive
from energysim.energies.derived import DensityEnergy
from energysim.fem.hessian_entries import stable_neo_hookean_hessian_entries
from energysim.fem.kernels import (
    element_major_energy_and_gradient,
    stable_neo_hookean_density_and_stress,
    stable_neo_hookean_density_and_stress_entries,
    stable_neo_hookean_stress_entries,
    stable_neo_hookean_stress_hessian,
)
from energysim.fem.kinematics import corner_forces_entries, deformation_gradient, deformation_gradient_entries
from energysim.fem.materials import lame_parameters, stable_neo_hookean_density
from energysim.linalg.small_matmul import small_matmul
from energysim.mesh import SimplexMesh


class NeoHookean(DensityEnergy):
    """Σ_e V_e ψ(F_e) with ψ the stable neo-Hookean density (see `energysim.fem.materials`).

    The density is the definition; the gradient, the Hessian blocks and the batch-last forces are
    the hand-written kernels of `energysim.fem.kernels`, which replace the derived forms where they
    are measured faster.

    Args:
        youngs_modulus: E in Pa, a scalar or one per element (shape `[m]`); may require grad.
        poissons_ratio: ν, in (−1, 0.5), a scalar or shape `[m]`; may require grad.
    """

    has_batch_last_kernel = True

    def __init__(self, youngs_modulus: float | Tensor = 1e5, poissons_ratio: float | Tensor = 0.3) -> None:
        super().__init__()
        youngs_modulus = as_parameter(youngs_modulus, "youngs_modulus")
        poissons_ratio = as_parameter(poissons_ratio, "poissons_ratio")
        check_positive(youngs_modulus, "youngs_modulus", "Pa")
        bad = ~(torch.isfinite(poissons_ratio) & (poissons_ratio > -1.0) & (poissons_ratio < 0.5))
        if bad.any():
            index = torch.nonzero(bad.reshape(-1)).reshape(-1)[:10].tolist()
            raise ValueError(
                "poissons_ratio must lie in (-1, 0.5): at 0.5 and above λ is infinite or negative; "
                f"offending entries {index}"
            )
        self.register_buffer("youngs_modulus", youngs_modulus)
        self.register_buffer("poissons_ratio", poissons_ratio)

    def bind(self, mesh: SimplexMesh, vertex_mass: Tensor) -> None:
        for name in ("youngs_modulus", "poissons_ratio"):
            check_per_element(getattr(self, name), mesh.num_elements, name, "element")
        super().bind(mesh, vertex_mass)
        # element-major copies for the compiled kernels: elements last
        self.register_buffer("element_vertices_t", mesh.elements.T.contiguous(), persistent=False)
        shape_gradient_t = self.shape_gradient.permute(1, 2, 0).contiguous()
        self.register_buffer("shape_gradient_t", shape_gradient_t, persistent=False)

    def lame(self) -> tuple[Tensor, Tensor]:
        """(μ, λ) in Pa, scalars or shape `[m]`."""
        return lame_parameters(self.youngs_modulus, self.poissons_ratio)

    def density(self, F: Tensor) -> Tensor:
        """ψ(F) in J/m³, `stable_neo_hookean_density` with this term's Lamé parameters."""
        return stable_neo_hookean_density(F, *self.lame())

    def element_energy_and_gradient(
        self, element_positions: Tensor, action: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """V ψ(F) `[B, m]` in J and V P ∇N_b `[B, m, d+1, d]` in N, from one set of invariants."""
        F = deformation_gradient(element_positions, self.rest_edge_inverse)
        density, stress = stable_neo_hookean_density_and_stress(F, *self.lame())
        stress = stress * self.rest_volume[:, None, None]
        return self.rest_volume * density, small_matmul(self.shape_gradient, stress.transpose(-1, -2))

    def forward(self, x: Tensor, action: Tensor | None = None) -> Tensor:
        if torch.compiler.is_compiling() and x.device.type == "cpu":
            return self.value_and_gradient(x, action)[0]  # element-major; the compiler drops ∇E
        return super().forward(x, action)

    def value_and_gradient(self, x: Tensor, action: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """E(x) `[B]` and ∇E(x) `[B, n, d]`; while `torch.compile` traces CPU tensors, element-major
        (`energysim.fem.kernels.element_major_energy_and_gradient`)."""
        if not (torch.compiler.is_compiling() and x.device.type == "cpu"):
            return super().value_and_gradient(x, action)
        return element_major_energy_and_gradient(
            x, self.element_vertices_t, self.shape_gradient_t, self.rest_volume, *self.lame()
        )

    def batch_last_forces(self, corners: list[list[Tensor]], action: Tensor | None) -> list[list[Tensor]]:
        """∂E/∂x entry by entry with the batch innermost (see `ElementEnergy.batch_last_forces`): the
        whole element kernel is scalar arithmetic vectorised over the batch."""
        F = deformation_gradient_entries(corners, self.shape_gradient_t)
        mu, lam = (value[:, None] if value.ndim else value for value in self.lame())
        P = stable_neo_hookean_stress_entries(F, mu, lam)
        return corner_forces_entries(P, self.shape_gradient_t, self.rest_volume)

    def batch_last_energy_and_forces(
        self, corners: list[list[Tensor]], action: Tensor | None
    ) -> tuple[Tensor, list[list[Tensor]]]:
        """V ψ(F) `[m, B]` and ∂E/∂x entry by entry, batch innermost (see
        `ElementEnergy.batch_last_energy_and_forces`), as scalar arithmetic."""
        F = deformation_gradient_entries(corners, self.shape_gradient_t)
        mu, lam = (value[:, None] if value.ndim else value for value in self.lame())
        density, P = stable_neo_hookean_density_and_stress_entries(F, mu, lam)
        forces = corner_forces_entries(P, self.shape_gradient_t, self.rest_volume)
        return self.rest_volume[:, None] * density, forces

    def batch_last_hessian_entries(self, corners: list[list[Tensor]], action: Tensor | None) -> list[Tensor]:
        """The upper entries of every element's Hessian block, batch innermost (see
        `ElementEnergy.batch_last_hessian_entries`), as scalar arithmetic
        (`energysim.fem.hessian_entries.stable_neo_hookean_hessian_entries`)."""
        mu, lam = (value[:, None] if value.ndim else value for value in self.lame())
        return stable_neo_hookean_hessian_entries(corners, self.shape_gradient_t, self.rest_volume, mu, lam)

    def element_hessian(self, element_positions: Tensor, action: Tensor | None) -> Tensor:
        """Exact per-element Hessian blocks V Sᵀ ∂²ψ/∂F² S, shape `[B, m, (d+1)d, (d+1)d]`, in N/m.
        Compiled, its two products fuse into the generated loops (`small_matmul`)."""
        F = deformation_gradient(element_positions, self.rest_edge_inverse)
        stiffness = stable_neo_hookean_stress_hessian(F, *self.lame())
        return small_matmul(
            self.weighted_strain_map_t,
            small_matmul(stiffness, self.weighted_strain_map, fuse_on_cpu=True),
            fuse_on_cpu=True,
        )
