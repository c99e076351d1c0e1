"""The second-order TR-BDF2 step against exact references: free fall (exact for a second-order
scheme), the linear oscillator's discrete recurrence written in the textbook trapezoid / BDF2
form, second-order convergence, gradients against central differences, and contact."""

from __future__ import annotations

import importlib
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import rigid_alignment_error, small_box
from test_gradients import TIGHT, beam, central_difference, loss_after

import energysim as es
from energysim.creatures import resting_state


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("solver", [es.NewtonCG(tol=1e-11), es.LBFGS(tol=1e-11, max_iter=2000)])
def test_free_fall_is_exact(dim, solver):
    # a second-order scheme integrates constant acceleration exactly: x = x₀ + v₀t + ½gt²,
    # where implicit Euler lags by ½h g t
    gravity = (0.0, -9.81) if dim == 2 else (0.0, -9.81, 0.0)
    scene = es.Scene(small_box(dim), dt=0.05, gravity=gravity, solver=solver, integrator="tr_bdf2")
    scene.add(es.NeoHookean(1e5, 0.3))
    v0 = torch.zeros(scene.num_vertices, dim, dtype=torch.float64)
    v0[:, 0] = 1.5
    state = scene.initial_state(velocities=v0)
    g = torch.tensor(gravity, dtype=torch.float64)
    for n in range(1, 21):
        state = es.timestep(scene, state)
        x, v = scene.split_state(state)
        t = n * scene.dt
        assert torch.allclose(x[0], scene.rest_positions + t * v0 + 0.5 * t**2 * g, atol=1e-9, rtol=0)
        assert torch.allclose(v[0], v0 + t * g, atol=1e-8, rtol=0)


def tr_bdf2_oscillator(u: float, v: float, omega: float, h: float, steps: int) -> np.ndarray:
    """(u, u̇) after each step of ü = −ω²u, from the textbook stages: the trapezoidal rule over h/2,
    then the three-point backward difference over t_n, t_n + h/2, t_n + h."""
    out = []
    w2 = omega**2
    for _ in range(steps):
        # trapezoid: u½ = u + h/4 (v + v½), v½ = v + h/4 (−ω²u − ω²u½)
        matrix = np.array([[1.0, -h / 4], [h / 4 * w2, 1.0]])
        u_half, v_half = np.linalg.solve(matrix, [u + h / 4 * v, v - h / 4 * w2 * u])
        # BDF2: h v₁ = 3u₁ − 4u½ + u, −h ω² u₁ = 3v₁ − 4v½ + v
        matrix = np.array([[3.0, -h], [h * w2, 3.0]])
        u, v = np.linalg.solve(matrix, [4 * u_half - u, 4 * v_half - v])
        out.append((u, v))
    return np.array(out)


def two_mass_spring(dt: float, integrator: str) -> tuple[es.Scene, torch.Tensor, float]:
    # two masses m on one spring k along it: the stretch obeys ü = −ω²u with ω² = 2k/m, exactly
    mesh = es.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]])
    mass, stiffness = 2.0, 50.0
    scene = es.Scene(
        mesh,
        dt=dt,
        gravity=None,
        vertex_mass=torch.full((4,), mass),
        solver=es.NewtonCG(tol=1e-12),
        integrator=integrator,
    )
    scene.add(es.Springs(edges=[[0, 1]], stiffness=stiffness))
    x0 = mesh.vertices.clone()
    x0[1, 0] += 0.05
    x0[0, 0] -= 0.05
    return scene, scene.initial_state(positions=x0), math.sqrt(2 * stiffness / mass)


def stretch_and_rate(scene: es.Scene, state: torch.Tensor) -> tuple[float, float]:
    x, v = scene.split_state(state)
    return float(x[0, 1, 0] - x[0, 0, 0] - 1.0), float(v[0, 1, 0] - v[0, 0, 0])


@pytest.mark.parametrize("steps_per_period", [6, 40])
def test_oscillator_follows_the_exact_discrete_recurrence(steps_per_period):
    omega = math.sqrt(50.0)
    dt = 2 * math.pi / omega / steps_per_period
    scene, state, omega = two_mass_spring(dt, "tr_bdf2")
    expected = tr_bdf2_oscillator(0.1, 0.0, omega, dt, 30)
    for n in range(30):
        state = es.timestep(scene, state)
        stretch, rate = stretch_and_rate(scene, state)
        assert stretch == pytest.approx(expected[n, 0], abs=1e-10)
        assert rate == pytest.approx(expected[n, 1], abs=1e-9)
    # and it keeps the slow oscillation: after 30 steps at 40 per period it lost < 0.1 % of its
    # amplitude, where implicit Euler loses 1 − (1 + (2π/40)²)^(−15) = 31 %
    if steps_per_period == 40:
        assert math.hypot(omega * stretch, rate) / (omega * 0.1) > 0.999


def test_error_falls_with_the_square_of_the_step():
    errors = {}
    for integrator in ("implicit_euler", "tr_bdf2"):
        for steps in (20, 40, 80):
            omega = math.sqrt(50.0)
            scene, state, omega = two_mass_spring(2 * math.pi / omega / steps, integrator)
            for _ in range(steps):  # one period: the exact stretch is back at 0.1
                state = es.timestep(scene, state)
            stretch, rate = stretch_and_rate(scene, state)
            errors[integrator, steps] = math.hypot(stretch - 0.1, rate / omega)
    for steps in (20, 40):
        assert errors["tr_bdf2", steps] / errors["tr_bdf2", 2 * steps] > 3.5  # order ≥ 2
        assert errors["implicit_euler", steps] / errors["implicit_euler", 2 * steps] < 2.2  # order 1
    # and with a quarter of the steps it is still five times more accurate than implicit Euler
    assert errors["tr_bdf2", 20] < errors["implicit_euler", 80] / 5


@pytest.mark.parametrize("grad_mode", ["implicit", "unrolled"])
def test_gradients_match_central_differences(grad_mode):
    scene = beam(torch.tensor(2e4, dtype=torch.float64, requires_grad=True))
    scene.integrator = "tr_bdf2"
    youngs = scene.terms[1].youngs_modulus
    velocity = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
    velocity[:, 1] = 0.3
    state = scene.initial_state(velocities=velocity).requires_grad_(True)
    action = torch.tensor([0.4, -0.2], dtype=torch.float64, requires_grad=True)
    grad_state, grad_action, grad_youngs = torch.autograd.grad(
        loss_after(scene, state, 5, action, grad_mode), [state, action, youngs]
    )
    generator = torch.Generator().manual_seed(0)
    direction = torch.randn(state.shape, dtype=torch.float64, generator=generator) * 1e-2
    fd = central_difference(lambda s: loss_after(scene, s, 5, action), state.detach(), direction, 1e-3)
    assert float(grad_state @ direction) == pytest.approx(fd, rel=1e-5)
    towards = torch.tensor([1.0, -0.5], dtype=torch.float64)
    fd = central_difference(lambda a: loss_after(scene, state, 5, a), action.detach(), towards, 1e-4)
    assert float(grad_action @ towards) == pytest.approx(fd, rel=1e-5)

    def with_modulus(value: torch.Tensor) -> torch.Tensor:
        other = beam(float(value))
        other.integrator = "tr_bdf2"
        return loss_after(other, state, 5, action)

    fd = central_difference(with_modulus, torch.tensor(2e4, dtype=torch.float64), torch.tensor(1.0), 20.0)
    assert float(grad_youngs) == pytest.approx(fd, rel=1e-4)
    assert TIGHT < 1e-9


def test_a_fast_drop_on_frictional_ground_stays_above_it_and_comes_to_rest():
    mesh = es.TetMesh.box(size=(0.2, 0.2, 0.2), cells=(2, 2, 2))
    scene = es.Scene(mesh, dt=1 / 24, integrator="tr_bdf2", solver=es.NewtonCG(tol=1e-6))
    scene.add(es.NeoHookean(1e5, 0.45))
    scene.add(es.Ground(0.0, friction=0.5))
    positions = mesh.vertices + torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64)
    velocities = torch.zeros_like(positions)
    velocities[:] = torch.tensor([1.0, -20.0, 0.0], dtype=torch.float64)
    state = scene.initial_state(positions, velocities)
    lowest = math.inf
    for _ in range(48):  # 2 s
        result = es.step(scene, state)
        assert result.stats.converged, result.stats.summary()
        state = result.state
        x, v = scene.split_state(state)
        assert torch.isfinite(state).all()
        lowest = min(lowest, float(x[0, :, 1].min()))
    assert lowest > 0.0  # never through the ground
    assert float(v.abs().max()) < 1e-2  # at rest: friction stopped the slide, the bounce died out
    assert float(x[0, :, 1].max()) < 0.25  # resting on the ground, not bouncing above it


def test_a_batch_equals_its_entries_solved_alone():
    scene = beam()
    scene.integrator = "tr_bdf2"
    generator = torch.Generator().manual_seed(1)
    states = scene.initial_state(batch_size=3)
    states[:, scene.num_dofs :] = 0.2 * torch.randn(
        3, scene.num_dofs, dtype=torch.float64, generator=generator
    )
    actions = torch.tensor([[0.5, 0.0], [-0.3, 0.8], [0.0, 0.0]], dtype=torch.float64)
    together = es.timestep(scene, states, actions)
    for entry in range(3):
        alone = es.timestep(scene, states[entry], actions[entry])
        assert torch.allclose(together[entry], alone, atol=1e-9, rtol=0)


def test_an_unknown_integrator_is_refused():
    with pytest.raises(ValueError, match="integrator must be one of"):
        es.Scene(small_box(3), integrator="rk4")
    scene = es.Scene(small_box(3))
    with pytest.raises(ValueError, match="integrator must be one of"):
        scene.integrator = "bdf2"


def test_entries_touching_the_ground_take_implicit_euler_and_the_others_tr_bdf2():
    mesh = es.TetMesh.box(size=(0.2, 0.2, 0.2), cells=(1, 1, 1))
    scene = es.Scene(mesh, dt=1 / 30, integrator="tr_bdf2", solver=es.NewtonCG(tol=1e-10))
    scene.add(es.NeoHookean(1e5, 0.3))
    ground = scene.add(es.Ground(0.0, friction=0.3))
    resting = mesh.vertices + torch.tensor([0.0, 0.5 * ground.barrier_distance, 0.0], dtype=torch.float64)
    flying = mesh.vertices + torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64)
    sideways = torch.zeros_like(resting)
    sideways[:, 0] = 0.5
    states = torch.stack([scene.initial_state(resting, sideways), scene.initial_state(flying, sideways)])
    together = es.timestep(scene, states)
    flight = es.timestep(scene, states[1])
    scene.integrator = "implicit_euler"
    contact = es.timestep(scene, states[0])
    assert torch.allclose(together[0], contact, atol=1e-9, rtol=0)
    assert torch.allclose(together[1], flight, atol=1e-9, rtol=0)
    # the flying box is in free fall, which TR-BDF2 integrates exactly
    x, _ = scene.split_state(together[1])
    assert float(x[0, :, 1].mean() - flying[:, 1].mean()) == pytest.approx(
        -0.5 * 9.81 * scene.dt**2, abs=1e-9
    )


def stability_matrix():
    scripts = Path(__file__).resolve().parents[1] / "scripts"
    if str(scripts) not in sys.path:
        sys.path.insert(0, str(scripts))
    return importlib.import_module("stability_matrix")


@pytest.mark.parametrize("case", ["random", "flat", "inverted", "nu=0.495", "ratio=1e4", "impact"])
def test_hard_cases_never_gain_energy_and_end_where_they_must(case):
    # the trapezoidal stage takes the start's forces at face value: on a scrambled, flattened or
    # inverted body they are huge, and without the energy guard a flattened box gained 80 % of its
    # energy in one step and a scrambled one blew up
    matrix = stability_matrix()
    spec = matrix.CASES[case]
    scene, state = spec.build()
    scene.integrator = "tr_bdf2"
    scene.solver = es.NewtonCG(tol=1e-5, max_iter=100)
    start, scale = matrix.mechanical_energy(scene, state)
    grounded = bool(matrix.obstacles_of(scene))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", es.ConvergenceWarning)  # the inverted start warns once
        for _ in range(round(spec.seconds / scene.dt)):
            previous = matrix.mechanical_energy(scene, state)[0]
            state = es.timestep(scene, state)
            assert torch.isfinite(state).all()
            energy = matrix.mechanical_energy(scene, state)[0]
            assert energy <= previous + 1e-9 * scale + 1e-6 * abs(previous)
            if grounded:
                assert float(scene.split_state(state)[0][0, :, 1].min()) > 0.0
    x, v = scene.split_state(state)
    if spec.recovers_rest_shape:
        size = float((scene.rest_positions.amax(0) - scene.rest_positions.amin(0)).norm())
        assert rigid_alignment_error(x[0], scene.rest_positions) < 1e-2 * size
    assert energy < start


def test_a_creature_that_always_touches_the_ground_walks_exactly_as_with_implicit_euler():
    worm = es.load_creature("worm")
    scenes = {name: worm.scene(1 / 60, 0.8, es.NewtonCG(tol=1e-4)) for name in es.IMPLICIT_INTEGRATORS}
    for name, scene in scenes.items():
        scene.integrator = name
    states = {name: resting_state(scene) for name, scene in scenes.items()}
    for k in range(6):
        action = worm.gait_action(k / 60)
        states = {name: es.timestep(scenes[name], state, action) for name, state in states.items()}
        assert torch.equal(states["tr_bdf2"], states["implicit_euler"])
