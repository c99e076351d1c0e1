"""Kelvin–Voigt viscosity against exact references: ∂D/∂v against autograd, the power identity
v·∂D/∂v = 2D of a quadratic dissipation, zero force for every rigid motion, the batch-last and
lagged (implicit) forms against the eager one, conservation of momentum and angular momentum,
and the explicit step's damping limit."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import random_rotation

import energysim as es
from energysim.energies.base import scatter_vertices
from energysim.integrators import explicit


def viscous_box(viscosity: float = 30.0) -> tuple[es.Scene, es.Viscosity]:
    mesh = es.TetMesh.box(size=(0.3, 0.1, 0.1), cells=(3, 1, 1))
    scene = es.Scene(mesh, density=1000.0, dt=1 / 60, gravity=None)
    scene.add(es.NeoHookean(1e5, 0.4))
    term = es.Viscosity(viscosity)
    scene.add(term)
    return scene, term


def random_motion(scene: es.Scene, batch: int = 3, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    shape = (batch, scene.num_vertices, 3)
    x = scene.rest_positions + 0.02 * torch.randn(shape, generator=generator, dtype=torch.float64)
    return x, torch.randn(shape, generator=generator, dtype=torch.float64)


def test_dissipation_gradient_is_exact_and_takes_twice_the_dissipation():
    scene, term = viscous_box()
    x, v = random_motion(scene)
    velocity = v.clone().requires_grad_(True)
    (expected,) = torch.autograd.grad(term.dissipation(x, velocity).sum(), velocity)
    gradient = term.dissipation_gradient(x, v)
    assert torch.allclose(gradient, expected, rtol=1e-12, atol=1e-12 * float(expected.abs().max()))
    # D is quadratic in v: the viscous forces' power is −v·∂D/∂v = −2D
    power = (v * gradient).sum(dim=(-1, -2))
    assert torch.allclose(power, 2 * term.dissipation(x, v), rtol=1e-12)
    assert bool((term.dissipation(x, v) > 0).all())


def test_rigid_motions_are_not_damped():
    scene, term = viscous_box()
    rotation = random_rotation(3, torch.Generator().manual_seed(1))
    x = (scene.rest_positions @ rotation.T)[None]
    spin = torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64)
    v = torch.linalg.cross(spin.expand_as(x), x) + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    assert float(term.dissipation(x, v).abs().max()) < 1e-12
    assert float(term.dissipation_gradient(x, v).abs().max()) < 1e-10


def test_batch_last_and_lagged_forms_equal_the_eager_gradient():
    scene, term = viscous_box()
    x, v = random_motion(scene)
    expected = term.dissipation_gradient(x, v)
    corners = x[:, term.element_vertices].permute(3, 2, 1, 0)  # [d, k, m, B]
    rates = v[:, term.element_vertices].permute(3, 2, 1, 0)
    forces = term.batch_last_dissipation_gradient(
        [[corners[i, b] for b in range(4)] for i in range(3)],
        [[rates[i, b] for b in range(4)] for i in range(3)],
    )
    per_corner = torch.stack([torch.stack(row) for row in forces]).permute(3, 2, 1, 0)
    got = scatter_vertices(per_corner, term.element_vertices, scene.num_vertices)
    assert torch.allclose(got, expected, rtol=1e-12, atol=1e-12 * float(expected.abs().max()))
    # an implicit step's term: at x = x_n + h v its gradient is the viscous force at v, F lagged at x_n
    h = 1 / 60
    (lagged,) = term.lagged_terms(x, h)
    _, gradient = lagged.value_and_gradient(x + h * v)
    assert torch.allclose(gradient, expected, rtol=1e-10, atol=1e-10 * float(expected.abs().max()))
    # and its closed-form Hessian blocks are autograd's
    positions = (x + h * v)[:1, lagged.element_vertices][:, :1]
    blocks = lagged.element_hessian(positions, None)[0, 0]

    def energy(flat: torch.Tensor) -> torch.Tensor:
        moved = (x + h * v)[:1, lagged.element_vertices].clone()
        moved[0, 0] = flat.reshape(4, 3)
        return lagged.element_energy(moved, None)[0, 0]

    expected_blocks = torch.autograd.functional.hessian(energy, positions[0, 0].reshape(-1))
    assert torch.allclose(
        blocks, expected_blocks, rtol=1e-10, atol=1e-10 * float(expected_blocks.abs().max())
    )


@pytest.mark.parametrize(
    ("integrator", "viscosity", "steps"), [("leapfrog", 5.0, 30), ("implicit_euler", 50.0, 2)]
)
def test_viscosity_damps_deformation_and_keeps_both_momenta(integrator, viscosity, steps):
    # no gravity, no ground: the viscous forces are internal and torque-free, so p stays, and so
    # does L under leapfrog (its kicks act at one configuration; implicit Euler's do not keep L);
    # the energy of deformation goes, where without viscosity leapfrog keeps it
    x0 = viscous_box()[0].rest_positions * torch.tensor([1.1, 0.95, 0.95], dtype=torch.float64)
    v0 = torch.zeros_like(x0)
    v0[:, 0] = 0.5
    v0[:, 1] = 0.4 * x0[:, 0]  # a spin about z on top of a drift along x
    results = {}
    for damped in (False, True):
        scene, _ = viscous_box(viscosity)
        if not damped:
            scene.terms = scene.terms[:-1]  # the same body without its viscosity
        scene.integrator = integrator
        if integrator == "leapfrog":
            scene.substeps = es.stable_substeps(scene)
        state = scene.initial_state(positions=x0, velocities=v0)
        mass = scene.vertex_mass[:, None]

        def momenta(state: torch.Tensor, scene: es.Scene = scene, mass: torch.Tensor = mass) -> tuple:
            x, v = (part[0] for part in scene.split_state(state))
            linear = (mass * v).sum(dim=0)
            angular = torch.linalg.cross(x, mass * v).sum(dim=0)
            return linear, angular, float(0.5 * (mass * v**2).sum() + scene.terms[0](x[None]).sum())

        start = momenta(state)
        for _ in range(steps):
            state = es.timestep(scene, state)
        results[damped] = (start, momenta(state))
    (p0, l0, e0), (p1, l1, e1) = results[True]
    assert torch.allclose(p1, p0, rtol=0, atol=1e-10)
    _, (_, _, e_plain) = results[False]
    if integrator == "leapfrog":
        assert torch.allclose(l1, l0, rtol=0, atol=1e-12)
        assert e_plain == pytest.approx(e0, rel=2e-2)  # symplectic: its O(h²) band
        assert e1 < 0.9 * e_plain
    else:
        # implicit Euler damps by itself (at h = 1/60 s as much as viscosity within 30 steps):
        # viscosity still takes more, 3 % in 2 steps
        assert e1 < 0.99 * e_plain


def test_the_damping_limit_bounds_the_substeps():
    # stiff damping: the viscous kick's limit 1/γ_max, not the Courant limit, sets the substeps
    scene, term = viscous_box(300.0)
    scene.integrator = "leapfrog"
    x = scene.rest_positions[None]
    gamma_step = explicit.stable_damping_step([term], x, scene.vertex_mass, scene.free)
    scene.substeps = es.stable_substeps(scene)
    assert scene.substeps == math.ceil(scene.dt / (explicit.COURANT_SAFETY * gamma_step))
    state = scene.initial_state(positions=scene.rest_positions * 1.05)
    for _ in range(10):
        state = es.timestep(scene, state)  # stable at that count
    # at a third of them the viscous kick overshoots (hγ ≈ 2.2 > 1), and the step says so
    scene.substeps = max(1, scene.substeps // 3)
    with pytest.raises(es.InstabilityError, match="viscous limit 1/γ_max"):
        state = scene.initial_state(positions=scene.rest_positions * 1.05)
        for _ in range(30):
            state = es.timestep(scene, state)


def test_bad_viscosity_is_refused():
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="viscosity must be finite and > 0"):
            es.Viscosity(bad)
    with pytest.raises(ValueError, match="viscosity must be a scalar"):
        es.Viscosity(torch.ones(3))
