"""Fibre muscles against independent numbers: autograd Hessians, finite differences, the rest state,
rigid invariance, the equilibrium fibre stretch 1 − c·a, a differentiable step, and bad inputs."""

from __future__ import annotations

import pytest
import torch
from conftest import random_rotation, small_box

import energysim as es
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.fem.kinematics import deformation_gradient, simplex_rest_frame
from energysim.fem.materials import stable_neo_hookean_density
from energysim.objective.derivatives import autograd_element_hessian, energy_and_gradient

C = 0.3  # max_contraction used throughout


def random_muscles(mesh: es.SimplexMesh, generator: torch.Generator | None = None) -> FibreMuscles:
    """Random non-unit fibres, three actuators and passive elements, per-element stiffness; bound."""
    count, dim = mesh.num_elements, mesh.dim
    fibres = torch.randn(count, dim, dtype=torch.float64, generator=generator) * 3.0
    actuators = torch.arange(count) % 4 - 1  # -1, 0, 1, 2, -1, ...
    stiffness = torch.linspace(1e4, 1e5, count, dtype=torch.float64)
    term = FibreMuscles(fibres, actuators, stiffness=stiffness, max_contraction=C)
    term.bind(mesh, torch.ones(mesh.num_vertices, dtype=torch.float64))
    return term


def uniform_muscles(mesh: es.SimplexMesh, fibre: torch.Tensor, stiffness: float = 1e5) -> FibreMuscles:
    """Every element one actuator (0) with the same fibre."""
    count = mesh.num_elements
    return FibreMuscles(fibre.expand(count, -1), torch.zeros(count, dtype=torch.int64), stiffness, C)


def unit(vector: torch.Tensor) -> torch.Tensor:
    return vector / vector.norm()


@pytest.mark.parametrize("dim", [2, 3])
def test_closed_form_hessian_matches_autograd(dim):
    mesh = small_box(dim)
    term = random_muscles(mesh)
    x = (mesh.vertices + 0.15 * torch.randn(2, *mesh.vertices.shape, dtype=torch.float64)).contiguous()
    x[1] = 0.5 * mesh.vertices  # squashed: fibres shorter than their target, 1 − λ*/λ < 0 (indefinite)
    action = torch.tensor([[1.0, -0.5, 0.25], [-1.0, 0.0, 3.0]], dtype=torch.float64)  # 3.0: clamped
    for a in (None, action):
        closed = term.element_hessian(x[:, term.element_vertices], a)
        auto = autograd_element_hessian(term, x, a)
        assert closed.shape == (2, term.element_vertices.shape[0], (dim + 1) * dim, (dim + 1) * dim)
        assert torch.allclose(closed, auto, rtol=1e-9, atol=1e-9 * float(auto.abs().max()))
    # the squashed state really probes the indefinite branch
    assert float(torch.linalg.eigvalsh(closed[1]).min()) < -1e-3 * float(closed[1].abs().max())


@pytest.mark.parametrize("dim", [2, 3])
def test_gradient_matches_central_differences(dim):
    mesh = small_box(dim)
    term = random_muscles(mesh)
    x = (mesh.vertices + 0.1 * torch.randn_like(mesh.vertices))[None]
    action = torch.tensor([[0.7, -0.3, 0.1]], dtype=torch.float64)
    _, gradient = energy_and_gradient(lambda y: term(y, action), x)
    eps = 1e-6
    for _ in range(5):
        v = torch.randn_like(x)
        finite = (term(x + eps * v, action) - term(x - eps * v, action)) / (2 * eps)
        exact = (gradient * v).sum()
        assert float(finite) == pytest.approx(float(exact), rel=1e-7, abs=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_rest_shape_has_zero_energy_and_force_without_activation(dim):
    mesh = small_box(dim)
    term = random_muscles(mesh)
    zero = torch.zeros(1, term.num_actuators, dtype=torch.float64)
    for action in (None, zero):
        energy, gradient = energy_and_gradient(lambda y, a=action: term(y, a), mesh.vertices[None])
        assert abs(float(energy)) < 1e-20
        assert float(gradient.abs().max()) < 1e-9
    # an activation makes the rest shape stressed: E = Σ V k/2 (c a)² over the driven elements
    action = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    driven = term.element_actuator == 0
    expected = (term.rest_volume * term.element_stiffness() / 2 * C**2)[driven].sum()
    assert float(term(mesh.vertices[None], action)) == pytest.approx(float(expected), rel=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_energy_is_invariant_under_rotation_and_translation(dim):
    mesh = small_box(dim)
    term = random_muscles(mesh)
    deformed = mesh.vertices + 0.1 * torch.randn_like(mesh.vertices)
    moved = deformed @ random_rotation(dim).T + torch.randn(dim, dtype=torch.float64)
    action = torch.tensor([[0.5, -0.8, 1.0]], dtype=torch.float64)
    before, after = float(term(deformed[None], action)), float(term(moved[None], action))
    assert before > 1.0
    assert after == pytest.approx(before, rel=1e-12)


def test_fibre_stretch_is_the_stretch_along_the_rest_fibre():
    # F = diag(2, 3, 5) stretches a fibre along (1, 1, 0)/√2 to |(2, 3, 0)|/√2 = √(13/2)
    mesh = es.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]])
    term = FibreMuscles(torch.tensor([[1.0, 1.0, 0.0]]), torch.tensor([0]), stiffness=2.0, max_contraction=C)
    term.bind(mesh, torch.ones(4, dtype=torch.float64))
    x = mesh.vertices * torch.tensor([2.0, 3.0, 5.0], dtype=torch.float64)
    stretch = (13 / 2) ** 0.5
    assert float(term.fibre_stretch(x[None])) == pytest.approx(stretch, rel=1e-14)
    # V k/2 (λ − (1 − c a))² with V = 1/6, k = 2, a = 0.5
    action = torch.tensor([[0.5]], dtype=torch.float64)
    expected = (1 / 6) * (2.0 / 2) * (stretch - (1 - C * 0.5)) ** 2
    assert float(term(x[None], action)) == pytest.approx(expected, rel=1e-14)


def test_collapsed_fibre_has_finite_force_and_hessian():
    # every vertex at one point: F m = 0, where ‖F m‖ has no derivative; the floor keeps both
    # the force and the double-backward Hessian finite
    mesh = small_box(3, cells=1)
    term = uniform_muscles(mesh, unit(torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)), stiffness=1e3)
    term.bind(mesh, torch.ones(mesh.num_vertices, dtype=torch.float64))
    x = torch.zeros(1, mesh.num_vertices, 3, dtype=torch.float64)
    action = torch.tensor([[0.5]], dtype=torch.float64)
    energy, gradient = energy_and_gradient(lambda y: term(y, action), x)
    expected = (term.rest_volume * 1e3 / 2 * (1 - C * 0.5) ** 2).sum()
    assert float(energy) == pytest.approx(float(expected), rel=1e-12)
    assert torch.isfinite(gradient).all()
    assert torch.isfinite(autograd_element_hessian(term, x, action)).all()
    assert torch.isfinite(term.element_hessian(x[:, term.element_vertices], action)).all()


def test_action_is_clamped_to_one():
    mesh = small_box(3, cells=1)
    term = uniform_muscles(mesh, unit(torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)))
    term.bind(mesh, torch.ones(mesh.num_vertices, dtype=torch.float64))
    x = mesh.vertices[None] * 0.9
    one, two = torch.ones(1, 1, dtype=torch.float64), torch.full((1, 1), 2.0, dtype=torch.float64)
    assert float(term(x, two)) == float(term(x, one))
    assert float(term(x, -two)) == float(term(x, -one))


def stretches_and_body_stress(mesh, x, fibre, body):
    """Per element: stretch |F m| along the fibre, |F t| along unit t ⟂ m, and the body's first
    Piola–Kirchhoff stress P (Pa) applied to m and to the t's."""
    rest_edge_inverse, _ = simplex_rest_frame(mesh.vertices, mesh.elements)
    F = deformation_gradient(x[mesh.elements], rest_edge_inverse).requires_grad_()
    (P,) = torch.autograd.grad(stable_neo_hookean_density(F, *body.lame()).sum(), F)
    dim = mesh.dim
    eye = torch.eye(dim, dtype=fibre.dtype)
    basis, _ = torch.linalg.qr(torch.cat([fibre[:, None], eye[:, : dim - 1]], dim=1))
    across = basis[:, 1:]
    F = F.detach()
    return (
        (F @ fibre).norm(dim=-1),
        (F @ across).norm(dim=-2),
        (P @ fibre).norm(dim=-1),
        (P @ across).norm(dim=-2),
    )


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("activation", [0.5, -1.0])
def test_equilibrium_fibre_stretch_is_one_minus_c_times_activation(dim, activation):
    mesh = small_box(dim)
    fibre = unit(torch.randn(dim, dtype=torch.float64))
    target = 1 - C * activation
    action = torch.tensor([[activation]], dtype=torch.float64)

    # the muscle alone: every element reaches its target fibre stretch (one vertex pinned; the
    # rest is free, so nothing but the muscle sets the shape)
    scene = es.Scene(mesh, gravity=None, solver=es.NewtonCG(tol=1e-12))
    muscles = scene.add(uniform_muscles(mesh, fibre))
    scene.fix([0])
    result = es.solve_static(scene, action=action)
    assert result.stats.converged
    stretch = muscles.fibre_stretch(result.state[None])
    assert torch.allclose(stretch, torch.full((1,), target, dtype=torch.float64), rtol=0, atol=1e-6)

    # with a weak, Poisson-free body (E = k/100) the fibre stretch gives way by about E/k of the
    # strain. The muscle pulls only along its fibre, so the free body carries no stress across it
    # (P t = 0), and the transverse stretch stays near 1: only the body's nonlinear Poisson effect,
    # where a muscle contracting in every direction would move it by c·a
    scene = es.Scene(mesh, gravity=None, solver=es.NewtonCG(tol=1e-12))
    scene.add(uniform_muscles(mesh, fibre))
    body = scene.add(es.NeoHookean(youngs_modulus=1e3, poissons_ratio=0.0))
    scene.fix([0])
    result = es.solve_static(scene, action=action)
    assert result.stats.converged
    along, across, stress_along, stress_across = stretches_and_body_stress(mesh, result.state, fibre, body)
    strain = C * abs(activation)
    assert float((along - target).abs().max()) < 0.02 * strain
    assert float(((along - target) * (1 - target)).min()) > 0  # short of the target, towards the rest length
    assert float(stress_across.max()) < 1e-6 * float(stress_along.min())
    assert float((across - 1).abs().max()) < 0.15 * strain


def test_step_gradient_with_respect_to_the_action_matches_central_differences():
    mesh = small_box(3, cells=1)
    fibre = unit(torch.tensor([1.0, 0.2, 0.0], dtype=torch.float64))
    scene = es.Scene(mesh, gravity=None, solver=es.NewtonCG(tol=1e-13))
    scene.add(es.NeoHookean(youngs_modulus=1e4, poissons_ratio=0.3))
    actuators = (mesh.vertices[mesh.elements].mean(dim=1)[:, 1] > 0.5).to(torch.int64)  # bottom 0, top 1
    scene.add(FibreMuscles(fibre.expand(mesh.num_elements, -1), actuators, stiffness=5e4, max_contraction=C))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] == 0).reshape(-1))
    weights = torch.randn(mesh.num_vertices, 3, dtype=torch.float64)
    state = scene.initial_state()

    def loss(action):
        x, _ = scene.split_state(es.timestep(scene, state, action))
        return (x[0] * weights).sum()

    action = torch.tensor([0.4, -0.2], dtype=torch.float64, requires_grad=True)
    (gradient,) = torch.autograd.grad(loss(action), action)
    eps = 1e-3
    for j in range(2):
        step = torch.zeros(2, dtype=torch.float64)
        step[j] = eps
        with torch.no_grad():
            finite = (loss(action + step) - loss(action - step)) / (2 * eps)
        assert float(gradient[j]) == pytest.approx(float(finite), rel=1e-6)
    assert float(gradient.abs().min()) > 0


def test_stiffness_gradient_is_energy_over_stiffness():
    mesh = small_box(2)
    stiffness = torch.full((mesh.num_elements,), 1e4, dtype=torch.float64, requires_grad=True)
    term = FibreMuscles(
        torch.ones(mesh.num_elements, 2), torch.zeros(mesh.num_elements, dtype=torch.int64), stiffness
    )
    term.bind(mesh, torch.ones(mesh.num_vertices, dtype=torch.float64))
    x = (mesh.vertices + 0.1 * torch.randn_like(mesh.vertices))[None]
    action = torch.tensor([[0.3]], dtype=torch.float64)
    (gradient,) = torch.autograd.grad(term(x, action), stiffness)
    per_element = term.element_energy(x[:, term.element_vertices], action)[0]
    assert torch.allclose(gradient, per_element.detach() / 1e4, rtol=1e-12, atol=0)


def test_passive_elements_are_left_out_and_their_fibres_ignored():
    mesh = small_box(3, cells=1)
    fibres = torch.zeros(mesh.num_elements, 3, dtype=torch.float64)  # passive ones may have no fibre
    actuators = torch.full((mesh.num_elements,), -1, dtype=torch.int64)
    actuators[[1, 4]] = torch.tensor([0, 1])
    fibres[[1, 4]] = torch.tensor([[0.0, 2.0, 0.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    term = FibreMuscles(fibres, actuators)
    term.bind(mesh, torch.ones(mesh.num_vertices, dtype=torch.float64))
    assert term.num_actuators == 2
    assert term.element_index.tolist() == [1, 4]
    assert torch.equal(term.element_vertices, mesh.elements[[1, 4]])
    assert torch.allclose(term.fibres[[1, 4]].norm(dim=-1), torch.ones(2, dtype=torch.float64))


def test_muscles_on_every_element_share_the_meshs_element_tensor_with_the_elastic_term():
    # the compiled batch evaluations gather and scatter terms together where they hold the same
    # `element_vertices` tensor; the energy is the one of a private copy of the elements
    scene = es.Scene(small_box(3), gravity=None)
    elastic = scene.add(es.NeoHookean(1e5, 0.3))
    fibres = torch.ones(scene.mesh.num_elements, 3, dtype=torch.float64)
    muscles = scene.add(FibreMuscles(fibres, torch.zeros(scene.mesh.num_elements, dtype=torch.int64)))
    assert muscles.element_vertices is elastic.element_vertices
    x = scene.mesh.vertices[None] * torch.tensor([1.1, 0.9, 1.0], dtype=torch.float64)
    action = torch.full((1, 1), 0.6, dtype=torch.float64)
    energy = muscles(x, action)
    muscles.element_vertices = scene.mesh.elements.clone()
    assert torch.allclose(muscles(x, action), energy, rtol=1e-14, atol=0.0) and float(energy) > 0


def test_bad_inputs_raise_clear_errors():
    mesh = small_box(3, cells=1)
    count = mesh.num_elements
    fibres = torch.ones(count, 3, dtype=torch.float64)
    actuators = torch.zeros(count, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"shape \[m, 2\] or \[m, 3\]"):
        FibreMuscles(torch.ones(count, 4), actuators)
    with pytest.raises(ValueError, match=r"shape \[6\]"):
        FibreMuscles(fibres, torch.zeros(count - 1, dtype=torch.int64))
    with pytest.raises(ValueError, match="integers"):
        FibreMuscles(fibres, torch.zeros(count))
    bad = actuators.clone()
    bad[3] = -2
    with pytest.raises(ValueError, match=r"offending elements \[3\]"):
        FibreMuscles(fibres, bad)
    with pytest.raises(ValueError, match="no element has an actuator"):
        FibreMuscles(fibres, torch.full((count,), -1))
    zero = fibres.clone()
    zero[2] = 0.0
    zero[5, 1] = float("nan")
    with pytest.raises(ValueError, match=r"actuated elements \[2, 5\] have zero-length or non-finite fibres"):
        FibreMuscles(zero, actuators)
    for contraction in (0.0, 1.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match=r"max_contraction must lie in \(0, 1\)"):
            FibreMuscles(fibres, actuators, max_contraction=contraction)
    for stiffness in (0.0, -1.0, float("inf"), torch.tensor([1.0, -1.0, 1.0, 1.0, 1.0, 1.0])):
        with pytest.raises(ValueError, match="stiffness must be finite and > 0 Pa"):
            FibreMuscles(fibres, actuators, stiffness=stiffness)
    ones = torch.ones(mesh.num_vertices, dtype=torch.float64)
    with pytest.raises(ValueError, match="describe 6 elements in 3D; the mesh has 8 elements in 2D"):
        FibreMuscles(torch.ones(6, 3), torch.zeros(6, dtype=torch.int64)).bind(small_box(2), ones)
    with pytest.raises(ValueError, match=r"scalar or have shape \[6\]"):
        FibreMuscles(fibres, actuators, stiffness=torch.ones(4)).bind(mesh, ones)
    term = FibreMuscles(fibres, torch.arange(count) % 3)
    term.bind(mesh, ones)
    with pytest.raises(ValueError, match="action has 2 entries; these muscles need 3"):
        term(mesh.vertices[None], torch.zeros(1, 2, dtype=torch.float64))
