"""The batch-last kernels of compiled batches: the Hessian entries (`energysim.fem.hessian_entries`,
`batch_last_hessian_entries`) equal autograd's Hessian of each element energy, and the lagged
viscosity's energy and forces autograd's gradient, to 1e-10 relative, in 2D and 3D, at inverted and
flat elements too; the defaults for other terms equal their element-major kernels."""

from __future__ import annotations

import pytest
import torch
from test_kernels_against_derived import close, deformations, fibre_energy, fibre_setup, lame, simplices
from torch.func import hessian

import energysim as es
from energysim.contact.obstacles import Ground
from energysim.fem.hessian_entries import (
    fibre_hessian_entries,
    lagged_viscosity_hessian_entries,
    stable_neo_hookean_hessian_entries,
    upper_entries,
)
from energysim.fem.kernels import lagged_viscosity_energy_and_stress_entries
from energysim.fem.kinematics import (
    corner_forces_entries,
    deformation_gradient,
    deformation_gradient_entries,
    shape_gradients,
)
from energysim.fem.materials import stable_neo_hookean_density


def corner_entries(corners: torch.Tensor) -> list[list[torch.Tensor]]:
    """`[B, m, k, d]` positions as `[i][b]` `[m, B]`, the batch-last kernels' input."""
    return [[corners[:, :, b, i].T for b in range(corners.shape[2])] for i in range(corners.shape[3])]


def as_upper(blocks: torch.Tensor, corners: int, dim: int) -> torch.Tensor:
    """The upper entries of `[B, m, K, K]` blocks as `[P, m, B]`, the kernels' output stacked."""
    return torch.stack([blocks[:, :, r, c].T for r, c in upper_entries(corners, dim)])


def autograd_blocks(energy, corners: torch.Tensor) -> torch.Tensor:
    """Every element's Hessian block `[B, m, K, K]` of Σ_e energy(corners)_e, by autograd, corners
    `[B, m, k, d]` (each element has corners of its own, so the Hessian is block diagonal)."""
    batch, count, k, dim = corners.shape
    size = k * dim
    blocks = []
    for entry in range(batch):
        full = hessian(lambda c, entry=entry: energy(c, entry).sum())(corners[entry])
        full = full.reshape(count, size, count, size)
        blocks.append(torch.stack([full[e, :, e] for e in range(count)]))
    return torch.stack(blocks)


def test_upper_entries_cover_each_symmetric_pair_once():
    pairs = upper_entries(4, 3)
    assert len(pairs) == 78 and len(set(pairs)) == 78
    assert all(r <= c for r, c in pairs) and pairs[:2] == ((0, 0), (0, 1))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("per_element", [False, True])
def test_neo_hookean_entries_equal_autograd_of_the_element_energy(dim, per_element):
    _, vertices, rest_edge_inverse, volume = simplices(dim, 80 + dim)
    F = deformations(dim, 90 + dim)  # inverted, flat and identity F among them
    mu, lam = lame(dim)
    if not per_element:
        mu, lam = mu[0], lam[0]
    # corners whose F is the chosen one: x_b = F X_b; the second batch entry moved and stretched
    rest = vertices.reshape(-1, dim + 1, dim)
    deformed = rest @ F.transpose(-1, -2)
    corners = torch.stack([deformed, 1.1 * deformed + 0.5])

    def energy(c: torch.Tensor, entry: int) -> torch.Tensor:
        return volume * stable_neo_hookean_density(deformation_gradient(c, rest_edge_inverse), mu, lam)

    column = (lambda value: value[:, None]) if per_element else (lambda value: value)
    grad_n = shape_gradients(rest_edge_inverse).permute(1, 2, 0).contiguous()
    got = stable_neo_hookean_hessian_entries(corner_entries(corners), grad_n, volume, column(mu), column(lam))
    assert close(torch.stack(got), as_upper(autograd_blocks(energy, corners), dim + 1, dim))


@pytest.mark.parametrize("dim", [2, 3])
def test_fibre_entries_equal_autograd_of_the_density(dim):
    corners, weights, stiffness, target = fibre_setup(dim, 100 + dim)
    blocks = autograd_blocks(lambda c, entry: fibre_energy(c, weights, stiffness, target[entry]), corners)
    got = fibre_hessian_entries(corner_entries(corners), weights, stiffness[:, None], target.T)
    assert close(torch.stack(got), as_upper(blocks, dim + 1, dim))


@pytest.mark.parametrize("dim", [2, 3])
def test_lagged_viscosity_entries_equal_autograd_of_its_energy(dim):
    elements, vertices, rest_edge_inverse, volume = simplices(dim, 110 + dim)
    grad_n = shape_gradients(rest_edge_inverse)
    start = deformations(dim, 120 + dim)
    weight = 2.0 * volume

    def energy(corners: torch.Tensor, F_n: torch.Tensor, inverse: torch.Tensor, w: torch.Tensor):
        change = deformation_gradient(corners, inverse) - F_n
        product = F_n.transpose(-1, -2) @ change
        return w * (0.5 * (product + product.transpose(-1, -2))).square().sum(dim=(-1, -2))

    corners = vertices[elements][None]
    blocks = autograd_blocks(lambda c, entry: energy(c, start, rest_edge_inverse, weight), corners)
    start_entries = [[start[:, i, j][:, None] for j in range(dim)] for i in range(dim)]
    got = lagged_viscosity_hessian_entries(start_entries, grad_n.permute(1, 2, 0).contiguous(), weight)
    assert close(torch.stack(got), as_upper(blocks, dim + 1, dim))


@pytest.mark.parametrize("dim", [2, 3])
def test_lagged_viscosity_energy_and_forces_entries_equal_autograd(dim):
    elements, vertices, rest_edge_inverse, volume = simplices(dim, 130 + dim)
    grad_n = shape_gradients(rest_edge_inverse).permute(1, 2, 0).contiguous()
    start = deformations(dim, 140 + dim)
    weight = 2.0 * volume
    generator = torch.Generator().manual_seed(dim)
    noise = torch.randn(2, *elements.shape, dim, generator=generator, dtype=torch.float64)
    corners = vertices[elements][None] + 0.2 * noise

    def energy(c: torch.Tensor) -> torch.Tensor:
        change = deformation_gradient(c, rest_edge_inverse) - start
        product = start.transpose(-1, -2) @ change
        return weight * (0.5 * (product + product.transpose(-1, -2))).square().sum(dim=(-1, -2))

    expected_gradient = torch.func.vmap(torch.func.grad(lambda c: energy(c).sum()))(corners)
    F = deformation_gradient_entries(corner_entries(corners), grad_n)
    start_entries = [[start[:, i, j][:, None] for j in range(dim)] for i in range(dim)]
    value, stress = lagged_viscosity_energy_and_stress_entries(F, start_entries, weight[:, None])
    forces = corner_forces_entries(stress, grad_n, weight)
    assert close(value.T, torch.stack([energy(c) for c in corners]))
    assert close(torch.stack([torch.stack(row) for row in forces]).permute(3, 2, 1, 0), expected_gradient)


def _contact_terms(obstacle) -> tuple[list, torch.Tensor]:
    # `obstacle` under a 2×1×1 box, its step's friction from a start a little above it, and positions
    # `[3, n, 3]` that slide the contact vertices by 0.3, 1 and 3 times ε (ε = ε_v h) in the entries
    scene = es.Scene(es.TetMesh.box(size=(0.2, 0.1, 0.1), cells=(2, 1, 1)), dt=1 / 60)
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.add(obstacle)
    generator = torch.Generator().manual_seed(0)
    lift = 0.003 * torch.rand(3, scene.num_vertices, 3, generator=generator, dtype=torch.float64)
    start = scene.rest_positions[None] + 0.005 + lift
    (friction,) = obstacle.lagged_terms(start, scene.dt)
    slide = float(friction.smoothing) * torch.randn(start.shape, generator=generator, dtype=torch.float64)
    slide[..., 1] = 0.0
    scale = torch.tensor([0.3, 1.0, 3.0], dtype=torch.float64)[:, None, None]
    return [obstacle, friction], start + scale * slide


@pytest.mark.parametrize("shape", ["ground", "sphere"])
def test_contact_entries_equal_autograd_of_the_barrier_and_friction(shape):
    # the barrier's and the friction's batch-last kernels (the ground's distance per coordinate, the
    # sphere's through the stacked default) against autograd's gradient and Hessian of their
    # element energies; the friction's marked vertices against its majorized `element_hessian`
    if shape == "ground":
        obstacle = Ground(barrier_distance=0.02, friction=0.8)
    else:
        obstacle = es.SphereObstacle((0.1, -0.5, 0.05), 0.5, barrier_distance=0.02, friction=0.8)
    terms, x = _contact_terms(obstacle)
    friction = terms[1]
    assert int((friction.weight > 0).sum()) > 3  # some vertices in contact
    for term in terms:
        corners = x[:, term.element_vertices].requires_grad_(True)
        energy = term.element_energy(corners, None)
        (gradient,) = torch.autograd.grad(energy.sum(), corners)
        corners = corners.detach()
        value, forces = term.batch_last_energy_and_forces(corner_entries(corners), None)
        assert close(value, energy.detach().T)
        assert close(torch.stack([torch.stack(row) for row in forces]).permute(3, 2, 1, 0), gradient)
        exact = torch.stack(term.batch_last_hessian_entries(corner_entries(corners), None))
        def energy_of(c: torch.Tensor, entry: int, term=term) -> torch.Tensor:
            # entry `entry`'s element energies, with that entry's lagged data (x_n, P, μλ)
            return term.element_energy(c.expand(len(x), -1, -1, -1), None)[entry]

        expected = as_upper(autograd_blocks(energy_of, corners), 1, 3)
        assert float(expected.abs().max()) > 0
        assert close(exact, expected)
    corners = x[:, friction.element_vertices]
    friction.set_curvature_hint(friction.weight > 0)
    marked = torch.stack(friction.batch_last_hessian_entries(corner_entries(corners), None))
    assert close(marked, as_upper(friction.element_hessian(corners, None), 1, 3))
    assert not close(marked, exact)  # the marks change the blocks of the vertices sliding beyond ε
