"""Contact in explicit steps, against exact references: the per-vertex projection's closed form,
sliding down a slope at g(sin θ − μ cos θ), sticking where μ > tan θ, a fast drop that never
penetrates and never gains energy; and the batch-last compiled kernels against the element-major
ones they replace."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import random_rotation

import energysim as es
from energysim.creatures import load_creature, resting_state
from energysim.fem.kernels import stable_neo_hookean_density_and_stress, stable_neo_hookean_stress_entries


def test_contact_velocity_is_the_closed_form_projection():
    scene = es.Scene(es.TetMesh.box(size=(1.0, 1.0, 1.0), cells=(1, 1, 1)), dt=0.01)
    ground = es.Ground(0.0, friction=0.5)
    scene.add(ground)
    x = scene.rest_positions[None].clone()  # vertices 0.. on y = 0 and y = 1
    v = torch.zeros_like(x)
    low = x[0, :, 1] == 0
    horizon = 0.01
    # approaching at 2 m/s with 3 m/s of slip: the normal impulse is 2 m/s, friction takes μ·2 = 1
    v[0, :, 0], v[0, :, 1] = 3.0, -2.0
    out = ground.contact_velocity(x, v, horizon)
    assert torch.allclose(out[0, low], torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64), atol=1e-15)
    # vertices at y = 1 reach y = 0.98 within the horizon: untouched
    assert torch.equal(out[0, ~low], v[0, ~low])
    # slip below μ × impulse: the vertex sticks
    v[0, :, 0] = 0.6
    stuck = ground.contact_velocity(x, v, horizon)[0, low]
    assert torch.allclose(stuck, torch.zeros_like(stuck))
    # a vertex 1 mm above the ground may still fall 1 mm in the horizon: to −0.1 m/s, no more
    lifted = x + torch.tensor([0.0, 1e-3, 0.0], dtype=torch.float64)
    out = ground.contact_velocity(lifted, v, horizon)
    assert torch.allclose(out[0, low, 1], torch.full((int(low.sum()),), -0.1, dtype=torch.float64))
    # leaving the ground: no impulse, no friction
    v[0, :, 1] = 1.0
    assert torch.equal(ground.contact_velocity(x, v, horizon), v)


def slope_scene(friction: float, angle: float, compile: bool = False) -> tuple[es.Scene, torch.Tensor]:
    """A stiff 20 × 10 × 10 cm block resting on a slope of `angle` rad, leapfrog, 20 substeps."""
    mesh = es.TetMesh.box(size=(0.2, 0.1, 0.1), cells=(2, 1, 1))
    normal = (-math.sin(angle), math.cos(angle), 0.0)
    scene = es.Scene(
        mesh, density=1000.0, dt=1 / 60, gravity=(0.0, -9.81, 0.0), integrator="leapfrog", substeps=20
    )
    scene.solver = es.NewtonCG(compile=compile)
    scene.add(es.NeoHookean(1e6, 0.3))
    ground = es.Ground(0.0, normal=normal, friction=friction)
    scene.add(ground)
    c, s = math.cos(angle), math.sin(angle)
    rotation = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    x = scene.rest_positions @ rotation.T
    x = x - ground.signed_distance(x).min() * ground.normal
    return scene, scene.initial_state(positions=x)


def slid(scene: es.Scene, state: torch.Tensor, steps: int, angle: float) -> tuple[float, float]:
    """Distance the centre moved down the slope after `steps` steps, and the lowest signed distance."""
    down = torch.tensor([-math.cos(angle), -math.sin(angle), 0.0], dtype=torch.float64)
    start = scene.split_state(state)[0].reshape(-1, 3).mean(dim=0)
    lowest = math.inf
    for _ in range(steps):
        state = es.timestep(scene, state)
        x = scene.split_state(state)[0].reshape(-1, 3)
        lowest = min(lowest, float(scene.terms[-1].signed_distance(x).min()))
    return float(((x.mean(dim=0) - start) * down).sum()), lowest


def test_sliding_down_a_slope_follows_coulomb():
    # s(t) = ½ g (sin θ − μ cos θ) t² for a block that slides from rest
    angle, friction, steps = math.radians(30), 0.3, 60
    scene, state = slope_scene(friction, angle)
    distance, lowest = slid(scene, state, steps, angle)
    t = steps * scene.dt
    expected = 0.5 * 9.81 * (math.sin(angle) - friction * math.cos(angle)) * t**2
    assert distance == pytest.approx(expected, rel=5e-3)  # measured 1.5e-3 (the block settles first)
    assert lowest > -1e-12  # no penetration, ever


def test_a_block_sticks_where_friction_exceeds_the_slope():
    angle, friction = math.radians(30), 0.7  # tan 30° = 0.577 < 0.7
    scene, state = slope_scene(friction, angle)
    settled, lowest = slid(scene, state, 30, angle)
    state_after = state
    for _ in range(30):
        state_after = es.timestep(scene, state_after)
    later, _ = slid(scene, state_after, 30, angle)
    # the block shears and bounces as its weight comes onto the slope (0.8 mm in the first 0.5 s;
    # nothing damps its elastic waves), then stays: at μ = 0.3 it slides 0.30 m in 0.5 s
    assert abs(settled) < 2e-3
    assert abs(later) < 1e-5  # from step 30 to 60
    assert lowest > -1e-12


def test_a_fast_drop_never_penetrates_and_never_gains_energy():
    mesh = es.TetMesh.box(size=(0.3, 0.1, 0.1), cells=(3, 1, 1))
    scene = es.Scene(mesh, density=1000.0, dt=1 / 60, gravity=(0.0, -9.81, 0.0), integrator="leapfrog")
    scene.add(es.NeoHookean(2e5, 0.3))
    ground = es.Ground(-0.05, friction=0.5)
    scene.add(ground)
    # the estimate at rest (6 substeps) is not enough for the squashed body: the impact stiffens it
    # past that step's limit, and the step says so (`InstabilityError`, advising 8)
    scene.substeps = 4 * es.stable_substeps(scene)
    velocity = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
    velocity[:, 0], velocity[:, 1] = 2.0, -20.0  # 20 m/s into the ground, slipping at 2 m/s
    rotation = random_rotation(3, torch.Generator().manual_seed(4))
    x0 = scene.rest_positions @ rotation.T + torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64)
    state = scene.initial_state(positions=x0, velocities=velocity)
    mass = scene.vertex_mass[:, None]

    def energy(state: torch.Tensor) -> float:
        x, v = scene.split_state(state)
        potential = sum(term(x).sum() for term in scene.terms if not isinstance(term, es.Ground))
        return float(0.5 * (mass * v[0] ** 2).sum() + potential)

    energies = [energy(state)]
    for _ in range(30):
        state = es.timestep(scene, state)
        x, _ = scene.split_state(state)
        assert float(ground.signed_distance(x).min()) > -1e-12
        energies.append(energy(state))
    # the inelastic impact took about half the energy (618 → 304 J); after it, the body rings
    # undamped, its energy in leapfrog's O(h²) band (±0.1 % measured), neither growing nor drifting
    assert max(energies[1:]) <= energies[0] * (1 + 1e-12)
    after = energies[3:]
    assert max(after) < 0.6 * energies[0]
    assert (max(after) - min(after)) < 5e-3 * max(after)
    assert sum(after[-10:]) / 10 <= sum(after[:10]) / 10 * (1 + 1e-3)


def test_contact_the_projection_cannot_handle_is_refused_and_starts_inside_are_errors():
    scene = es.Scene(es.TetMesh.box(size=(1.0, 1.0, 1.0), cells=(1, 1, 1)), dt=0.01, integrator="leapfrog")
    scene.add(es.NeoHookean(1e4, 0.3))
    scene.add(es.BoxObstacle(lower=(-1.0, -2.0, -1.0), upper=(2.0, -1.0, 2.0)))
    with pytest.raises(ValueError, match="no contact model for BoxObstacle"):
        es.timestep(scene, scene.initial_state())
    sunk = es.Scene(es.TetMesh.box(size=(1.0, 1.0, 1.0), cells=(1, 1, 1)), dt=0.01, integrator="leapfrog")
    sunk.add(es.NeoHookean(1e4, 0.3))
    sunk.add(es.Ground(0.5))
    with pytest.raises(ValueError, match="not admissible: vertices .* inside"):
        es.timestep(sunk, sunk.initial_state())


@pytest.mark.parametrize("dim", [2, 3])
def test_stress_entries_equal_the_matrix_form(dim):
    generator = torch.Generator().manual_seed(dim)
    F = torch.eye(dim, dtype=torch.float64) + 0.6 * torch.randn(50, dim, dim, generator=generator)
    F[0] = -F[0]  # inverted
    F[1, :, 0] = 0.0  # flat
    mu = torch.tensor(3.0e4, dtype=torch.float64)
    lam = torch.rand(50, generator=generator, dtype=torch.float64) * 1e5
    _, expected = stable_neo_hookean_density_and_stress(F, mu, lam)
    entries_of_f = [[F[:, i, j] for j in range(dim)] for i in range(dim)]
    entries = stable_neo_hookean_stress_entries(entries_of_f, mu, lam)
    got = torch.stack([torch.stack(row, dim=-1) for row in entries], dim=-2)
    assert torch.allclose(got, expected, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("name", ["worm", "crawler2d"])
def test_batch_last_forces_equal_the_terms_gradients(name):
    creature = load_creature(name)
    scene = creature.scene(1 / 60)
    batch, dim = 5, creature.dim
    generator = torch.Generator().manual_seed(1)
    x = scene.rest_positions + 0.01 * torch.randn(batch, scene.num_vertices, dim, generator=generator)
    action = 2 * torch.rand(batch, creature.num_actuators, generator=generator, dtype=torch.float64) - 1
    for term in scene.terms:
        if not (isinstance(term, es.ElementEnergy) and term.has_batch_last_kernel):
            continue
        corners = x[:, term.element_vertices].permute(3, 2, 1, 0)  # [d, k, m, B]
        forces = term.batch_last_forces(
            [[corners[i, b] for b in range(dim + 1)] for i in range(dim)], action.T
        )
        got = torch.stack([torch.stack(row) for row in forces]).permute(3, 2, 1, 0)  # [B, m, k, d]
        _, expected = term.value_and_gradient(x, action)
        scattered = es.energies.base.scatter_vertices(got, term.element_vertices, scene.num_vertices)
        assert torch.allclose(scattered, expected, rtol=1e-12, atol=1e-9 * float(expected.abs().max()))


@pytest.mark.heavy
def test_compiled_batch_last_leapfrog_equals_the_eager_step():
    # 8 worms: the compiled step lays the batch innermost (`compiled.leapfrog`); the eager one does
    # the same arithmetic element by element
    creature = load_creature("worm")
    batch = 8
    generator = torch.Generator().manual_seed(0)
    action = 2 * torch.rand(batch, creature.num_actuators, generator=generator, dtype=torch.float64) - 1
    results = []
    for compile in (False, True):
        scene = creature.scene(1 / 60, solver=es.NewtonCG(compile=compile))
        scene.integrator, scene.substeps = "leapfrog", 32
        state = resting_state(scene, scene.rest_positions.expand(batch, -1, -1))
        for _ in range(2):
            state = es.timestep(scene, state, action)
        results.append(state)
    assert torch.allclose(results[1], results[0], rtol=0, atol=1e-10)
