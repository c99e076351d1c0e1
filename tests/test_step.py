"""The implicit-Euler step against exact discrete references: free fall, a linear oscillator's
damping factor, energy decay, cross-optimizer agreement, batches and pinned vertices."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import small_box

import energysim as es
from energysim.creatures import resting_state
from energysim.fem.kinematics import deformation_gradient
from energysim.fem.materials import stable_neo_hookean_density
from energysim.integrators.adjoint import step_terms
from energysim.integrators.implicit_stage import rows_of
from energysim.objective.derivatives import energy_and_gradient

SOLVERS = {
    "newton-cg": lambda tol: es.NewtonCG(tol=tol),
    "newton-cg-autograd": lambda tol: es.NewtonCG(tol=tol, hessian="autograd", max_cg_iter=2000),
    "lbfgs": lambda tol: es.LBFGS(tol=tol, max_iter=2000),
    "adam": lambda tol: es.Adam(tol=tol, max_iter=20000, lr=1e-3),
}


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("solver", ["newton-cg", "lbfgs"])
def test_free_fall_follows_the_implicit_euler_recurrence(dim, solver):
    # with constant g: v_n = v_0 + n h g and x_n = x_0 + n h v_0 + h² g n(n+1)/2, exactly
    gravity = (0.0, -9.81) if dim == 2 else (0.0, -9.81, 0.0)
    scene = es.Scene(small_box(dim), dt=0.05, gravity=gravity, solver=SOLVERS[solver](1e-10))
    scene.add(es.NeoHookean(1e5, 0.3))
    v0 = torch.zeros(scene.num_vertices, dim, dtype=torch.float64)
    v0[:, 0] = 1.5
    state = scene.initial_state(velocities=v0)
    g = torch.tensor(gravity, dtype=torch.float64)
    h = scene.dt
    for n in range(1, 21):
        state = es.timestep(scene, state)
        x, v = scene.split_state(state)
        expected_x = scene.rest_positions + n * h * v0 + h**2 * g * n * (n + 1) / 2
        assert torch.allclose(x[0], expected_x, atol=1e-9, rtol=0)
        assert torch.allclose(v[0], v0 + n * h * g, atol=1e-8, rtol=0)


@pytest.mark.parametrize("steps_per_period", [6, 40])
def test_two_mass_spring_decays_by_the_exact_implicit_euler_factor(steps_per_period):
    # Two unit masses joined by one spring oscillating along the spring: the stretch u obeys
    # ü = −ω² u with ω² = 2k/m, exactly linear. Implicit Euler multiplies sqrt((ωu)² + u̇²) by
    # 1/sqrt(1 + (ωh)²) per step, exactly.
    mesh = es.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]])
    mass, stiffness = 2.0, 50.0
    omega = math.sqrt(2 * stiffness / mass)
    dt = 2 * math.pi / omega / steps_per_period
    scene = es.Scene(
        mesh, dt=dt, gravity=None, vertex_mass=torch.full((4,), mass), solver=es.NewtonCG(tol=1e-12)
    )
    scene.add(es.Springs(edges=[[0, 1]], stiffness=stiffness))
    x0 = mesh.vertices.clone()
    x0[1, 0] += 0.05
    x0[0, 0] -= 0.05
    state = scene.initial_state(positions=x0)

    def amplitude(state):
        x, v = scene.split_state(state)
        stretch = x[0, 1, 0] - x[0, 0, 0] - 1.0
        rate = v[0, 1, 0] - v[0, 0, 0]
        return math.hypot(omega * float(stretch), float(rate))

    start = amplitude(state)
    factor = 1 / math.sqrt(1 + (omega * dt) ** 2)
    for n in range(1, 31):
        state = es.timestep(scene, state)
        assert amplitude(state) == pytest.approx(start * factor**n, rel=1e-9)


def total_energy(scene, nh, state):
    """Kinetic + elastic + gravitational energy, in J."""
    x, v = scene.split_state(state)
    kinetic = 0.5 * (scene.vertex_mass[:, None] * v[0] ** 2).sum()
    F = deformation_gradient(x[:, nh.element_vertices], nh.rest_edge_inverse)
    elastic = (nh.rest_volume * stable_neo_hookean_density(F, *nh.lame())).sum()
    potential = sum(float(term(x)) for term in scene.terms if isinstance(term, es.Gravity))
    return float(kinetic + elastic) + potential


@pytest.mark.parametrize("dim", [2, 3])
def test_total_energy_never_increases_in_a_free_oscillation(dim):
    mesh = (
        es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(8, 2, 2))
        if dim == 3
        else es.TriMesh.box(size=(1.0, 0.2), cells=(10, 2))
    )
    gravity = (0.0, -9.81, 0.0) if dim == 3 else (0.0, -9.81)
    scene = es.Scene(mesh, dt=1 / 60, gravity=gravity, solver=es.NewtonCG(tol=1e-9))
    nh = scene.add(es.NeoHookean(1e5, 0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    state = scene.initial_state()
    energies = [total_energy(scene, nh, state)]
    for _ in range(60):
        state = es.timestep(scene, state)
        energies.append(total_energy(scene, nh, state))
    drops = [b - a for a, b in zip(energies, energies[1:], strict=False)]
    scale = abs(energies[0] - min(energies))
    assert max(drops) <= 1e-9 * max(scale, 1.0)
    # and it does oscillate and lose energy: the tip goes down
    assert min(energies) < energies[0] - 1e-3


def swinging_state(scene, steps=3):
    state = scene.initial_state()
    for _ in range(steps):
        state = es.timestep(scene, state)
    return state


def test_all_optimizers_reach_the_same_next_state():
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(5, 1, 1))
    scene = es.Scene(mesh, dt=1 / 60, solver=es.NewtonCG(tol=1e-12))
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    state = swinging_state(scene)
    reference = es.step(scene, state).state
    # a residual r in m/s leaves a position error of at most about h·r per DOF (H ⪰ M/h²)
    for name, tol in (("newton-cg", 1e-7), ("newton-cg-autograd", 1e-7), ("lbfgs", 1e-7), ("adam", 1e-4)):
        result = es.step(scene, state, solver=SOLVERS[name](tol))
        assert result.stats.converged, result.stats.summary()
        x, _ = scene.split_state(result.state)
        x_ref, _ = scene.split_state(reference)
        error = float((x - x_ref).abs().max())
        assert error < 10 * scene.dt * tol, f"{name}: {error:.2e} m ({result.stats.summary()})"


def test_element_block_and_autograd_hessian_products_agree():
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(5, 1, 1))
    scene = es.Scene(mesh, dt=1 / 24)
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.add(es.Springs(stiffness=100.0))  # goes through the generic autograd element Hessian
    scene.fix([0, 1])
    x = (mesh.vertices + 0.05 * torch.randn_like(mesh.vertices))[None].repeat(2, 1, 1)
    inertia = es.Inertia(scene.vertex_mass, scene.dt, x + 0.01)
    objective = es.Objective(
        [inertia, *scene.terms], free=scene.free, residual_scale=scene.dt / scene.vertex_mass
    )
    v = torch.randn_like(x)
    blocks = objective.hessian(x, use_element_blocks=True).matvec(v)
    auto = objective.hessian(x, use_element_blocks=False).matvec(v)
    assert torch.allclose(blocks, auto, rtol=1e-10, atol=1e-10 * float(auto.abs().max()))
    # fixed DOFs are eliminated: the operator is the identity there
    assert torch.equal(blocks[:, :2], v[:, :2])
    # and both solve a step to the same state
    state = scene.initial_state(velocities=0.2 * torch.randn(mesh.num_vertices, 3, dtype=torch.float64))
    one = es.step(scene, state, solver=es.NewtonCG(tol=1e-10)).state
    two = es.step(scene, state, solver=es.NewtonCG(tol=1e-10, hessian="autograd", max_cg_iter=5000)).state
    assert torch.allclose(one, two, atol=1e-9)


def test_a_batch_is_solved_as_independent_problems():
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(4, 1, 1))
    scene = es.Scene(mesh, dt=1 / 30, solver=es.NewtonCG(tol=1e-10))
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.fix([0])
    velocities = [torch.randn(mesh.num_vertices, 3, dtype=torch.float64) for _ in range(3)]
    states = torch.stack([scene.initial_state(velocities=v) for v in velocities])
    batched = es.timestep(scene, states)
    assert batched.shape == states.shape
    for b in range(3):
        single = es.timestep(scene, states[b])
        assert torch.allclose(batched[b], single, atol=1e-9)


def test_a_batch_drops_converged_entries_and_still_equals_its_entries_solved_alone(monkeypatch):
    # three boxes fall freely (the warm start is exact, so they converge at once); the fourth is
    # thrown at the ground at 8 m/s and slides on it with friction, which takes many iterations:
    # once at most half of the entries still iterate, the solver goes on with those alone
    scene = es.Scene(small_box(3), dt=1 / 60, solver=es.NewtonCG(tol=1e-8))
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.add(es.Ground(height=-0.1, friction=0.5))
    thrown = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
    thrown[:, 1], thrown[:, 0] = -8.0, 1.0
    resting = torch.zeros_like(thrown)
    start = torch.stack([scene.initial_state(velocities=v) for v in (resting, resting, thrown, resting)])
    rows = []
    evaluate, line_trial = es.Objective.energy_and_gradient, es.Objective.trial

    def counting(self, x):
        rows.append(x.shape[0])
        return evaluate(self, x)

    def counting_trial(self, x, direction, gradient, *judging):
        rows.append(x.shape[0])
        return line_trial(self, x, direction, gradient, *judging)

    # every gradient a solve takes, at a point or at a line search's first trial, counts its rows
    monkeypatch.setattr(es.Objective, "energy_and_gradient", counting)
    monkeypatch.setattr(es.Objective, "trial", counting_trial)

    def run(solver: es.NewtonCG) -> tuple[torch.Tensor, int]:
        rows.clear()
        state = start
        for _ in range(3):  # the later steps start in contact: lagged friction is sliced too
            result = es.step(scene, state, solver=solver)
            assert result.stats.converged and result.stats.iterations >= 3
            state = result.state
        return state, sum(rows)

    compacted, compacted_rows = run(es.NewtonCG(tol=1e-8))
    full, full_rows = run(es.NewtonCG(tol=1e-8, compact_below=0.0))
    assert compacted_rows < 0.5 * full_rows
    assert torch.allclose(compacted, full, atol=1e-12, rtol=0)
    for b in range(4):
        state = start[b]
        for _ in range(3):
            state = es.step(scene, state).state
        assert torch.allclose(compacted[b], state, atol=1e-10, rtol=0)


def test_pinned_vertices_do_not_move_and_have_zero_velocity():
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(4, 1, 1))
    scene = es.Scene(mesh, dt=1 / 60)
    scene.add(es.NeoHookean(1e4, 0.3))
    pinned = torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1)
    scene.fix(pinned)
    velocities = torch.zeros(mesh.num_vertices, 3, dtype=torch.float64)
    velocities[:, 2] = 0.1  # the pinned ones too: pinning overrides the state's velocity
    state = scene.initial_state(velocities=velocities)
    for _ in range(5):
        state = es.timestep(scene, state)
    x, v = scene.split_state(state)
    assert torch.equal(x[0, pinned], mesh.vertices[pinned])
    assert torch.equal(v[0, pinned], torch.zeros_like(v[0, pinned]))
    assert x[0, :, 1].min() < -1e-3  # the free end fell


def test_a_body_at_rest_without_forces_stays_at_rest_in_zero_iterations():
    scene = es.Scene(small_box(3), gravity=None)
    scene.add(es.NeoHookean(1e5, 0.3))
    result = es.step(scene, scene.initial_state())
    assert result.stats.iterations == 0 and result.stats.converged
    assert torch.equal(result.state, scene.initial_state())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_device_and_dtype_follow_the_state(dtype):
    scene = es.Scene(small_box(3), solver=es.NewtonCG(tol=1e-3 if dtype == torch.float32 else 1e-8))
    scene.add(es.NeoHookean(1e5, 0.3))
    state = scene.initial_state().to(dtype)
    new = es.timestep(scene, state)
    assert new.dtype == dtype
    # the step ran on a copy in the state's dtype: the scene keeps its own
    assert scene.vertex_mass.dtype == torch.float64 and scene.terms[1].youngs_modulus.dtype == torch.float64
    # one step of free fall from rest: every vertex moves by h² g
    _, v = scene.split_state(new)
    assert torch.allclose(v[0, :, 1], torch.full_like(v[0, :, 1], -9.81 * scene.dt), rtol=1e-5)


def test_solve_static_finds_a_stationary_point_of_the_potential():
    mesh = es.TetMesh.box(size=(1.0, 0.2, 0.2), cells=(6, 2, 2))
    scene = es.Scene(mesh, gravity=(0.0, -9.81, 0.0))
    scene.add(es.NeoHookean(1e6, 0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9).reshape(-1))
    result = es.solve_static(scene, solver=es.NewtonCG(tol=1e-9))
    assert result.stats.converged, result.stats.summary()
    x = result.state
    # zero net force on the free vertices: |∇Φ| tiny compared with the weight
    potential = lambda y: sum(term(y) for term in scene.terms)  # noqa: E731
    _, gradient = energy_and_gradient(potential, x[None])
    weight = float(scene.vertex_mass.max() * 9.81)
    assert float(gradient[0, scene.free].abs().max()) < 1e-6 * weight
    tip_sag = float(x[:, 1].min())
    assert tip_sag < -1e-3
    # without a mass term the static problem is ill-conditioned for first-order methods,
    # but L-BFGS reaches a looser tolerance and the same sag
    loose = es.solve_static(scene, solver=es.LBFGS(tol=1e-4, max_iter=20000))
    assert loose.stats.converged, loose.stats.summary()
    assert float(loose.state[:, 1].min()) == pytest.approx(tip_sag, rel=1e-3)


def test_a_step_objective_sliced_to_some_entries_equals_one_built_for_them() -> None:
    # a solver restricts a step to the entries still iterating (compaction, lone backtracking): the
    # inertia and the lagged friction and viscosity slice their per-entry data (`EnergyTerm.rows`)
    # instead of being built again from those entries' state; both must be the same objective
    scene = es.load_creature("worm").scene(1 / 60, 0.8)
    scene.add(es.Viscosity(30.0))
    generator = torch.Generator().manual_seed(4)
    state = resting_state(scene).expand(4, -1)
    x, v = scene.split_state(state)
    v = v + 0.05 * torch.randn(v.shape, generator=generator, dtype=v.dtype)
    action = 2 * torch.rand(4, 10, generator=generator, dtype=x.dtype) - 1
    anchor = x + scene.dt * v

    def built(xp: torch.Tensor, vp: torch.Tensor, act: torch.Tensor, at: torch.Tensor) -> es.Objective:
        terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, xp, vp, scene.free, at)
        return es.Objective(terms, scene.free, scene.dt / scene.vertex_mass, act, at)

    rows = torch.tensor([3, 1])
    sliced = rows_of(built(x, v, action, anchor), scene.terms, rows)
    rebuilt = built(x[rows], v[rows], action[rows], anchor[rows])
    kinds = [type(term).__name__ for term in sliced.terms]
    assert kinds == [type(term).__name__ for term in rebuilt.terms]
    assert {"Inertia", "LaggedFriction", "LaggedViscosity"} <= set(kinds)
    probe = x[rows] + 1e-4 * torch.randn(x[rows].shape, generator=generator, dtype=x.dtype)
    pairs = zip(sliced.energy_and_gradient(probe), rebuilt.energy_and_gradient(probe), strict=True)
    for got, expected in pairs:
        torch.testing.assert_close(got, expected, rtol=1e-12, atol=0.0)
    got, expected = (objective.hessian(probe).dense(probe) for objective in (sliced, rebuilt))
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12 * float(expected.abs().max()))


def test_a_term_refuses_to_slice_a_registered_buffer() -> None:
    # `_with` copies a term shallowly: a registered buffer would stay shared with the original
    ground = es.Ground(friction=0.8)
    with pytest.raises(ValueError, match="normal"):
        ground._with(normal=torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
