"""Every hand-written kernel of `energysim.fem.kernels` equals the form derived from its pure
density by `torch.func` (autograd), to 1e-10 relative, in 2D and 3D, at inverted and flat F too."""

from __future__ import annotations

import pytest
import torch
from torch.func import grad, hessian, vmap

from energysim.energies.derived import density_stiffness, density_stress
from energysim.energies.fibre_muscles import fibre_muscle_density
from energysim.fem.kernels import (
    element_major_energy_and_gradient,
    fibre_energy_and_forces_entries,
    fibre_energy_and_gradient,
    fibre_forces_entries,
    fibre_hessian_blocks,
    lagged_viscosity_hessian_blocks,
    stable_neo_hookean_density_and_stress,
    stable_neo_hookean_density_and_stress_entries,
    stable_neo_hookean_stress_entries,
    stable_neo_hookean_stress_hessian,
    viscous_stress,
    viscous_stress_entries,
)
from energysim.fem.kinematics import deformation_gradient, shape_gradients, simplex_rest_frame
from energysim.fem.materials import stable_neo_hookean_density

RELATIVE = 1e-10
COUNT = 40


def close(got: torch.Tensor, expected: torch.Tensor) -> bool:
    scale = float(expected.abs().max())
    return float((got - expected).abs().max()) <= RELATIVE * scale


def deformations(dim: int, seed: int) -> torch.Tensor:
    """Random F near and far from I, with an inverted (J < 0) and a flat (J = 0) one."""
    generator = torch.Generator().manual_seed(seed)
    F = torch.eye(dim, dtype=torch.float64) + 0.6 * torch.randn(COUNT, dim, dim, generator=generator)
    F[0] = -F[0] if dim == 3 else F[0] @ torch.diag(torch.tensor([-1.0, 1.0], dtype=torch.float64))
    F[1, :, 0] = F[1, :, 1]  # flat: two equal columns
    F[2] = torch.eye(dim, dtype=torch.float64)
    return F


def lame(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    mu = 1e4 + 1e5 * torch.rand(COUNT, generator=generator, dtype=torch.float64)
    return mu, 3.0 * mu


def simplices(dim: int, seed: int) -> tuple[torch.Tensor, ...]:
    """`COUNT` random rest simplices: elements `[m, d+1]`, vertices, Dm⁻¹ `[m, d, d]` and V `[m]`."""
    generator = torch.Generator().manual_seed(seed)
    base = torch.cat([torch.zeros(1, dim, dtype=torch.float64), torch.eye(dim, dtype=torch.float64)])
    rest = base + 0.2 * torch.randn(COUNT, dim + 1, dim, generator=generator, dtype=torch.float64)
    vertices = rest.reshape(-1, dim)
    elements = torch.arange(COUNT * (dim + 1)).reshape(COUNT, dim + 1)
    rest_edge_inverse, volume = simplex_rest_frame(vertices, elements)
    return elements, vertices, rest_edge_inverse, volume


@pytest.mark.parametrize("dim", [2, 3])
def test_neo_hookean_stress_and_density_equal_the_derived_stress(dim):
    F = deformations(dim, dim)
    mu, lam = lame(dim)
    density, stress = stable_neo_hookean_density_and_stress(F, mu, lam)
    derived_stress, derived_density = density_stress(lambda G: stable_neo_hookean_density(G, mu, lam), F)
    assert close(density, derived_density)
    assert close(stress, derived_stress)


@pytest.mark.parametrize("dim", [2, 3])
def test_neo_hookean_stress_hessian_equals_the_derived_stiffness(dim):
    F = deformations(dim, 10 + dim)
    mu, lam = lame(dim)
    closed = stable_neo_hookean_stress_hessian(F, mu, lam)
    derived = density_stiffness(lambda G: stable_neo_hookean_density(G, mu, lam), F)
    assert close(closed, derived)


@pytest.mark.parametrize("dim", [2, 3])
def test_neo_hookean_stress_entries_equal_the_derived_stress(dim):
    F = deformations(dim, 20 + dim)
    mu, lam = lame(dim)
    F_entries = [[F[:, i, j] for j in range(dim)] for i in range(dim)]
    entries = stable_neo_hookean_stress_entries(F_entries, mu, lam)
    got = torch.stack([torch.stack(row, dim=-1) for row in entries], dim=-2)
    derived, derived_density = density_stress(lambda G: stable_neo_hookean_density(G, mu, lam), F)
    assert close(got, derived)
    density, _ = stable_neo_hookean_density_and_stress_entries(F_entries, mu, lam)
    assert close(density, derived_density)


@pytest.mark.parametrize("dim", [2, 3])
def test_element_major_gradient_equals_autograd_of_the_summed_density(dim):
    elements, vertices, rest_edge_inverse, volume = simplices(dim, 30 + dim)
    mu, lam = lame(dim)
    generator = torch.Generator().manual_seed(dim)
    x = vertices + 0.3 * torch.randn(2, *vertices.shape, generator=generator, dtype=torch.float64)
    x[0, elements[0, 0]] = x[0, elements[0, 1]]  # a flat element

    def energy(y: torch.Tensor) -> torch.Tensor:
        F = deformation_gradient(y[:, elements], rest_edge_inverse)
        return (volume * stable_neo_hookean_density(F, mu, lam)).sum(-1)

    grad_n = shape_gradients(rest_edge_inverse)
    value, gradient = element_major_energy_and_gradient(
        x, elements.T.contiguous(), grad_n.permute(1, 2, 0).contiguous(), volume, mu, lam
    )
    expected = vmap(grad(lambda y: energy(y[None])[0]))(x)
    assert close(value, energy(x))
    assert close(gradient, expected)


def fibre_setup(dim: int, seed: int):
    generator = torch.Generator().manual_seed(seed)
    corners = torch.randn(2, COUNT, dim + 1, dim, generator=generator, dtype=torch.float64)
    weights = torch.randn(COUNT, dim + 1, generator=generator, dtype=torch.float64)
    weights = weights - weights.mean(dim=-1, keepdim=True)  # ∇N·m sums to zero over the corners
    stiffness = 1e3 + 1e4 * torch.rand(COUNT, generator=generator, dtype=torch.float64)
    target = 0.7 + 0.6 * torch.rand(2, COUNT, generator=generator, dtype=torch.float64)
    return corners, weights, stiffness, target


def fibre_energy(corners: torch.Tensor, weights, stiffness, target) -> torch.Tensor:
    vector = (weights[..., None] * corners).sum(dim=-2)
    stretch = torch.sqrt((vector * vector).sum(dim=-1) + 1e-30)
    return fibre_muscle_density(stretch, stiffness, target)


@pytest.mark.parametrize("dim", [2, 3])
def test_fibre_gradient_blocks_and_entries_equal_autograd_of_the_density(dim):
    corners, weights, stiffness, target = fibre_setup(dim, 40 + dim)
    vector = (weights[..., None] * corners).sum(dim=-2)
    stretch = torch.sqrt((vector * vector).sum(dim=-1) + 1e-30)
    energy, gradient = fibre_energy_and_gradient(vector, stretch, stiffness, target, weights)
    blocks = fibre_hessian_blocks(vector, stretch, stiffness, target, weights)

    def one(c: torch.Tensor, w: torch.Tensor, k: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return fibre_energy(c, w, k, t)

    per_element = vmap(vmap(grad(one)), in_dims=(0, None, None, 0))
    per_element_hessian = vmap(vmap(hessian(one)), in_dims=(0, None, None, 0))
    size = (dim + 1) * dim
    assert close(energy, fibre_energy(corners, weights, stiffness, target))
    assert close(gradient, per_element(corners, weights, stiffness, target))
    expected_blocks = per_element_hessian(corners, weights, stiffness, target).reshape(2, COUNT, size, size)
    assert close(blocks, expected_blocks)
    corner_entries = [[corners[:, :, b, i].T for b in range(dim + 1)] for i in range(dim)]
    entries = fibre_forces_entries(corner_entries, weights, stiffness[:, None], target.T)
    got = torch.stack([torch.stack(row, dim=-1) for row in entries], dim=-1).permute(1, 0, 2, 3)
    assert close(got, gradient)
    entry_energy, _ = fibre_energy_and_forces_entries(corner_entries, weights, stiffness[:, None], target.T)
    assert close(entry_energy.T, energy)


@pytest.mark.parametrize("dim", [2, 3])
def test_viscous_stress_and_entries_equal_autograd_of_the_dissipation(dim):
    F = deformations(dim, 50 + dim)
    rate = torch.randn(COUNT, dim, dim, generator=torch.Generator().manual_seed(dim), dtype=torch.float64)
    viscosity = torch.tensor(3.0, dtype=torch.float64)

    def dissipation(F: torch.Tensor, rate: torch.Tensor) -> torch.Tensor:
        product = F.transpose(-1, -2) @ rate
        strain_rate = 0.5 * (product + product.transpose(-1, -2))
        return viscosity * strain_rate.square().sum(dim=(-1, -2))

    expected = vmap(grad(dissipation, argnums=1))(F, rate)
    assert close(viscous_stress(F, rate, viscosity), expected)
    entries = viscous_stress_entries(
        [[F[:, i, j] for j in range(dim)] for i in range(dim)],
        [[rate[:, i, j] for j in range(dim)] for i in range(dim)],
        viscosity,
    )
    assert close(torch.stack([torch.stack(row, dim=-1) for row in entries], dim=-2), expected)


@pytest.mark.parametrize("dim", [2, 3])
def test_lagged_viscosity_blocks_equal_autograd_of_its_energy(dim):
    elements, vertices, rest_edge_inverse, volume = simplices(dim, 60 + dim)
    grad_n = shape_gradients(rest_edge_inverse)
    start = deformations(dim, 70 + dim)[None]
    weight = 2.0 * volume

    def energy(corners: torch.Tensor, F_n: torch.Tensor, inverse: torch.Tensor, w: torch.Tensor):
        change = deformation_gradient(corners, inverse) - F_n
        product = F_n.transpose(-1, -2) @ change
        return w * (0.5 * (product + product.transpose(-1, -2))).square().sum()

    corners = vertices[elements]
    size = (dim + 1) * dim
    expected = vmap(hessian(energy))(corners, start[0], rest_edge_inverse, weight)
    expected = expected.reshape(1, COUNT, size, size)
    assert close(lagged_viscosity_hessian_blocks(start, grad_n, weight), expected)
