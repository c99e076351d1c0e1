"""The explicit leapfrog integrator against exact references: the linear oscillator's discrete map
(position Verlet in closed form), free fall (exact for the scheme), second-order convergence and a
bounded, non-drifting energy on a nonlinear body, gradients against central differences, and clear
errors past the Courant limit, with contact it cannot model, and for bad settings."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import small_box
from test_gradients import beam, central_difference
from test_tr_bdf2 import stretch_and_rate, two_mass_spring

import energysim as es


def leapfrog_oscillator(u: float, v: float, omega: float, h: float, steps: int) -> np.ndarray:
    """(u, u̇) after each step of ü = −ω²u by drift ½h, kick h, drift ½h, as one 2×2 map."""
    drift = np.array([[1.0, h / 2], [0.0, 1.0]])
    kick = np.array([[1.0, 0.0], [-h * omega**2, 1.0]])
    one_step = drift @ kick @ drift
    out, state = [], np.array([u, v])
    for _ in range(steps):
        state = one_step @ state
        out.append(state)
    return np.array(out)


@pytest.mark.parametrize("substeps", [1, 3])
@pytest.mark.parametrize("steps_per_period", [3, 40])
def test_oscillator_follows_the_exact_discrete_map(steps_per_period, substeps):
    # 3 steps per period is ωh = 2.09 > 2, past the Courant limit with one substep: three
    # substeps bring it to 0.70
    omega = math.sqrt(2 * 50.0 / 2.0)
    dt = 2 * math.pi / omega / steps_per_period
    scene, state, omega = two_mass_spring(dt, "leapfrog")
    scene.substeps = substeps
    if omega * dt / substeps >= 2:
        with pytest.raises(es.InstabilityError, match="substeps"):
            for _ in range(30):
                state = es.timestep(scene, state)
        return
    expected = leapfrog_oscillator(0.1, 0.0, omega, dt / substeps, 30 * substeps)[substeps - 1 :: substeps]
    for n in range(30):
        state = es.timestep(scene, state)
        stretch, rate = stretch_and_rate(scene, state)
        assert stretch == pytest.approx(expected[n, 0], abs=1e-12)
        assert rate == pytest.approx(expected[n, 1], abs=1e-11)


def test_free_fall_is_exact():
    # the kick at the midpoint integrates a constant acceleration exactly: x = x₀ + v₀t + ½gt²
    scene = es.Scene(small_box(3), dt=0.05, gravity=(0.0, -9.81, 0.0), integrator="leapfrog", substeps=2)
    scene.add(es.NeoHookean(1e3, 0.3))
    v0 = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
    v0[:, 0] = 1.5
    state = scene.initial_state(velocities=v0)
    g = torch.tensor([0.0, -9.81, 0.0], dtype=torch.float64)
    for n in range(1, 11):
        state = es.timestep(scene, state)
        x, v = scene.split_state(state)
        t = n * scene.dt
        assert torch.allclose(x[0], scene.rest_positions + t * v0 + 0.5 * t**2 * g, atol=1e-12, rtol=0)
        assert torch.allclose(v[0], v0 + t * g, atol=1e-12, rtol=0)


def swinging_beam(substeps: int) -> es.Scene:
    mesh = es.TetMesh.box(size=(0.6, 0.1, 0.1), cells=(6, 1, 1))
    scene = es.Scene(mesh, dt=0.1, integrator="leapfrog", substeps=substeps)
    scene.add(es.NeoHookean(2e4, 0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    return scene


def run(scene: es.Scene, steps: int) -> tuple[torch.Tensor, list[float]]:
    """The last positions and the energy change since the start after each step, in J."""

    def energy(state: torch.Tensor) -> float:
        x, v = scene.split_state(state)
        with torch.no_grad():
            potential = sum(term(x, None) for term in scene.terms)
        return float(potential + 0.5 * (scene.vertex_mass[:, None] * v**2).sum())

    state = scene.initial_state()
    start, changes = energy(state), []
    for _ in range(steps):
        state = es.timestep(scene, state)
        changes.append(energy(state) - start)
    return scene.split_state(state)[0][0], changes


def test_second_order_convergence_and_bounded_energy_on_a_swinging_beam():
    # a soft beam falling from horizontal bends far out of the linear range: errors against a run
    # at a quarter of the finest step fall 4× per halving, and the energy stays in a band of width
    # O(h²) about its start with no drift
    reference, _ = run(swinging_beam(256), 10)
    errors, bands = [], []
    for substeps in (16, 32, 64):
        x, energies = run(swinging_beam(substeps), 10)
        errors.append(float((x - reference).norm(dim=-1).max()))
        bands.append(max(abs(e) for e in energies))
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(1.8 < order < 2.3 for order in orders), (errors, orders)
    band_orders = [math.log2(bands[i] / bands[i + 1]) for i in range(2)]
    assert all(1.7 < order < 2.3 for order in band_orders), (bands, band_orders)


def test_past_the_courant_limit_it_raises_with_the_limit_and_below_it_runs():
    scene = swinging_beam(4)
    state = scene.initial_state()
    with pytest.raises(es.InstabilityError, match=r"Courant limit .* about 2/ω_max = ([0-9.e-]+) s") as error:
        for _ in range(10):
            state = es.timestep(scene, state)
    assert torch.isfinite(state).all()  # the blown-up state was never returned
    advised = int(str(error.value).split("use at least ")[1].split(" substeps")[0])
    # the advice is the estimated limit rounded up: it runs, and well below it too
    for substeps in (advised, 2 * advised):
        scene = swinging_beam(substeps)
        x, energies = run(scene, 10)
        assert torch.isfinite(x).all() and max(abs(e) for e in energies) < 0.05


def test_contact_and_implicit_substeps_are_refused_and_substeps_are_checked():
    # half-spaces and spheres act by projection (tests/test_explicit_contact.py); a box cannot
    scene = es.Scene(small_box(3), dt=0.01, integrator="leapfrog")
    scene.add(es.NeoHookean(1e4, 0.3))
    scene.add(es.BoxObstacle(lower=(-1.0, -2.0, -1.0), upper=(2.0, -1.0, 2.0)))
    with pytest.raises(ValueError, match="no contact model for BoxObstacle"):
        es.timestep(scene, scene.initial_state())
    implicit = es.Scene(small_box(3), dt=0.01, substeps=4)
    implicit.add(es.NeoHookean(1e4, 0.3))
    with pytest.raises(ValueError, match="implicit step takes dt whole"):
        es.timestep(implicit, implicit.initial_state())
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="substeps must be an integer"):
            implicit.substeps = bad


def test_gradients_through_leapfrog_steps_match_central_differences():
    scene = beam()  # actuated springs and neo-Hookean, one end pinned
    scene.integrator = "leapfrog"
    scene.substeps = 8
    action = torch.tensor([0.4, -0.2], dtype=torch.float64)
    x0 = scene.rest_positions.reshape(-1)
    weights = torch.linspace(-1.0, 1.0, 2 * scene.num_dofs, dtype=torch.float64)

    def loss(v0: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        state = torch.cat([x0, v0])
        for _ in range(5):
            state = es.timestep(scene, state, act)
        return (weights * state).sum() + 0.5 * (state**2).sum()

    generator = torch.Generator().manual_seed(0)
    v0 = (0.3 * torch.randn(scene.num_dofs, generator=generator, dtype=torch.float64)).requires_grad_(True)
    act = action.clone().requires_grad_(True)
    loss(v0, act).backward()
    direction = torch.randn(scene.num_dofs, generator=generator, dtype=torch.float64)
    expected = central_difference(lambda v: loss(v, action), v0.detach(), direction, 1e-6)
    assert float(v0.grad @ direction) == pytest.approx(expected, rel=1e-7)
    direction = torch.tensor([1.0, 0.5], dtype=torch.float64)
    expected = central_difference(lambda a: loss(v0.detach(), a), action, direction, 1e-6)
    assert float(act.grad @ direction) == pytest.approx(expected, rel=1e-7)
