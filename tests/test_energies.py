"""Energy terms against independent numbers: rest state, rigid invariance, linear elasticity,
uniaxial stress, closed-form versus autograd Hessians, and inverted elements."""

from __future__ import annotations

import pytest
import torch
from conftest import random_rotation, small_box

import energysim as es
from energysim.fem.kernels import stable_neo_hookean_stress_hessian
from energysim.fem.materials import lame_parameters, stable_neo_hookean_density
from energysim.integrators.adjoint import step_terms
from energysim.objective.derivatives import (
    autograd_element_hessian,
    energy_and_gradient,
    hessian_vector_product,
)


def bound_term(term, mesh):
    term.bind(mesh, torch.ones(mesh.num_vertices, dtype=torch.float64))
    return term


@pytest.mark.parametrize("dim", [2, 3])
def test_zero_energy_and_zero_force_at_rest(dim):
    mesh = small_box(dim)
    for term in (es.NeoHookean(1e5, 0.3), es.Springs(stiffness=1e3)):
        bound_term(term, mesh)
        energy, gradient = energy_and_gradient(lambda x, t=term: t(x), mesh.vertices[None])
        assert abs(float(energy)) < 1e-9
        assert gradient.abs().max() < 1e-9


@pytest.mark.parametrize("dim", [2, 3])
def test_elastic_energy_is_invariant_under_rotation_and_translation(dim):
    mesh = small_box(dim)
    deformed = mesh.vertices + 0.1 * torch.randn_like(mesh.vertices)
    rotation = random_rotation(dim)
    moved = deformed @ rotation.T + torch.randn(dim, dtype=torch.float64)
    for term in (es.NeoHookean(1e5, 0.3), es.Springs(stiffness=1e3)):
        bound_term(term, mesh)
        before, after = float(term(deformed[None])), float(term(moved[None]))
        assert before > 1.0
        assert after == pytest.approx(before, rel=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_small_strain_energy_matches_linear_elasticity(dim):
    youngs, poisson = torch.tensor(2e5, dtype=torch.float64), torch.tensor(0.35, dtype=torch.float64)
    mu, lam = lame_parameters(youngs, poisson)
    strain_direction = torch.randn(dim, dim, dtype=torch.float64)
    errors = []
    for size in (1e-3, 1e-4):
        gradient = size * strain_direction
        epsilon = 0.5 * (gradient + gradient.T)
        linear = mu * (epsilon * epsilon).sum() + 0.5 * lam * torch.trace(epsilon) ** 2
        psi = stable_neo_hookean_density(torch.eye(dim, dtype=torch.float64) + gradient, mu, lam)
        errors.append(float(abs(psi - linear) / linear))
    # the difference is cubic in the strain: relative error ∝ size, so it drops tenfold
    assert errors[0] < 1e-2
    assert errors[1] < 0.15 * errors[0]


def test_uniaxial_stress_matches_the_closed_form():
    # Smith et al. 2018: P = μ'F + λ'(J − α) cof F − μ' F/(I_C + 1). For F = diag(s, 1, 1):
    # cof F = diag(1, s, s), J = s, I_C = s² + 2; with μ' = 4μ/3, λ' = λ + 5μ/6, α = 1 + 3μ'/(4λ').
    youngs, poisson = torch.tensor(1e6, dtype=torch.float64), torch.tensor(0.3, dtype=torch.float64)
    mu, lam = lame_parameters(youngs, poisson)
    mu_s, lam_s = 4 * mu / 3, lam + 5 * mu / 6
    alpha = 1 + 0.75 * mu_s / lam_s
    for stretch in (0.5, 0.9, 1.0, 1.2, 2.0):
        F = torch.diag(torch.tensor([stretch, 1.0, 1.0], dtype=torch.float64)).requires_grad_()
        (P,) = torch.autograd.grad(stable_neo_hookean_density(F, mu, lam), F)
        damping = 1 / (stretch**2 + 3)
        expected_axial = mu_s * stretch + lam_s * (stretch - alpha) - mu_s * stretch * damping
        expected_lateral = mu_s + lam_s * (stretch - alpha) * stretch - mu_s * damping
        assert float(P[0, 0]) == pytest.approx(float(expected_axial), rel=1e-12, abs=1e-6)
        assert float(P[1, 1]) == pytest.approx(float(expected_lateral), rel=1e-12, abs=1e-6)
        assert abs(float(P[0, 1])) < 1e-9
    # at small stretch the axial stress is Young's modulus times the strain, with lateral
    # stress λ ε (the lateral faces are held): the linear-elastic uniaxial-strain response
    strain = 1e-6
    F = torch.diag(torch.tensor([1 + strain, 1.0, 1.0], dtype=torch.float64)).requires_grad_()
    (P,) = torch.autograd.grad(stable_neo_hookean_density(F, mu, lam), F)
    assert float(P[0, 0]) == pytest.approx(float((lam + 2 * mu) * strain), rel=1e-5)
    assert float(P[1, 1]) == pytest.approx(float(lam * strain), rel=1e-5)


@pytest.mark.parametrize("dim", [2, 3])
def test_closed_form_stress_hessian_matches_autograd(dim):
    F = torch.eye(dim, dtype=torch.float64) + 0.4 * torch.randn(20, dim, dim, dtype=torch.float64)
    F[0] = -F[0]  # an inverted one
    mu, lam = torch.rand(20, dtype=torch.float64) + 0.5, 10 * torch.rand(20, dtype=torch.float64)
    closed = stable_neo_hookean_stress_hessian(F, mu, lam)
    auto = torch.func.vmap(torch.func.hessian(stable_neo_hookean_density))(F, mu, lam)
    assert torch.allclose(closed, auto.reshape(20, dim * dim, dim * dim), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_element_hessian_blocks_match_autograd_and_finite_differences(dim):
    mesh = small_box(dim)
    term = bound_term(
        es.NeoHookean(torch.linspace(1e4, 1e5, mesh.num_elements, dtype=torch.float64), 0.45), mesh
    )
    x = (mesh.vertices + 0.1 * torch.randn_like(mesh.vertices))[None].repeat(2, 1, 1)
    closed = term.element_hessian(x[:, term.element_vertices], None)
    auto = autograd_element_hessian(term, x, None)
    assert torch.allclose(closed, auto, rtol=1e-10, atol=1e-8 * auto.abs().max())
    # and the global product H v against a central difference of gradients
    v = torch.randn_like(x)
    eps = 1e-6
    grad = lambda y: energy_and_gradient(lambda z: term(z), y)[1]  # noqa: E731
    finite = (grad(x + eps * v) - grad(x - eps * v)) / (2 * eps)
    exact = hessian_vector_product(lambda z: term(z), x, v)
    assert torch.allclose(exact, finite, rtol=1e-6, atol=1e-6 * finite.abs().max())


def test_spring_energy_and_force():
    mesh = es.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]])
    springs = bound_term(es.Springs(edges=[[0, 1]], stiffness=200.0, rest_length=0.5), mesh)
    x = mesh.vertices[None].clone()
    energy, gradient = energy_and_gradient(lambda y: springs(y), x)
    assert float(energy) == pytest.approx(0.5 * 200.0 * 0.5**2, rel=1e-12)
    # the stretched spring pulls vertex 1 back toward vertex 0 with k (ℓ − ℓ₀) = 100 N
    assert gradient[0, 1].tolist() == pytest.approx([100.0, 0.0, 0.0], abs=1e-9)
    assert gradient[0, 0].tolist() == pytest.approx([-100.0, 0.0, 0.0], abs=1e-9)


def test_collapsed_spring_has_finite_force():
    mesh = es.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]])
    springs = bound_term(es.Springs(edges=[[0, 1]], stiffness=10.0), mesh)
    x = mesh.vertices[None].clone()
    x[0, 1] = x[0, 0]
    energy, gradient = energy_and_gradient(lambda y: springs(y), x)
    assert torch.isfinite(gradient).all()
    assert float(energy) == pytest.approx(0.5 * 10.0 * 1.0, rel=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_inverted_and_flat_elements_have_finite_energy_and_push_back(dim):
    mesh = small_box(dim, cells=1)
    term = bound_term(es.NeoHookean(1e5, 0.3), mesh)
    for squash in (-1.0, 0.0):  # reflected (every element inverted) and squashed flat
        x = mesh.vertices.clone()
        x[:, 1] *= squash
        energy, gradient = energy_and_gradient(lambda y: term(y), x[None])
        assert torch.isfinite(energy).all() and torch.isfinite(gradient).all()
        # a small step down the gradient must raise the element volumes (towards J = α > 0)
        from energysim.mesh import signed_volumes

        before = signed_volumes(x, mesh.elements).sum()
        after = signed_volumes(x - 1e-9 * gradient[0], mesh.elements).sum()
        assert after > before


def test_gravity_energy_is_minus_m_g_dot_x():
    mesh = small_box(3, cells=1)
    mass = torch.rand(mesh.num_vertices, dtype=torch.float64) + 0.5
    gravity = es.Gravity((0.0, -9.81, 0.0))
    gravity.bind(mesh, mass)
    x = torch.randn(1, mesh.num_vertices, 3, dtype=torch.float64)
    assert float(gravity(x)) == pytest.approx(float((mass * 9.81 * x[0, :, 1]).sum()), rel=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_closed_form_spring_hessians_match_autograd(dim):
    mesh = small_box(dim)
    edges = mesh.edges()
    x = (mesh.vertices + 0.2 * torch.randn_like(mesh.vertices))[None].repeat(2, 1, 1)
    x[0, edges[0, 1]] = x[0, edges[0, 0]] + 1e-3  # one nearly collapsed spring
    action = torch.tensor([[0.7, -0.4], [1.5, 0.2]], dtype=torch.float64)  # 1.5 is clamped to 1
    plain = bound_term(es.Springs(stiffness=torch.rand(edges.shape[0], dtype=torch.float64) + 0.5), mesh)
    actuated = bound_term(
        es.ActuatedSprings(edges, actuators=torch.arange(edges.shape[0]) % 2, stiffness=40.0), mesh
    )
    for term in (plain, actuated):
        closed = term.element_hessian(x[:, term.element_vertices], action)
        auto = autograd_element_hessian(term, x, action)
        assert torch.allclose(closed, auto, rtol=1e-9, atol=1e-9 * float(auto.abs().max()))


def _kernel_cases():
    """(name, scene-building function) for every term with a closed-form gradient kernel."""

    def elastic(dim):
        def build(scene):
            scene.add(es.NeoHookean(1e5, 0.45))

        return build

    def springs(scene):
        scene.add(es.Springs(stiffness=1e3))

    def actuated(scene):
        edges = scene.mesh.edges()
        scene.add(es.ActuatedSprings(edges, torch.arange(edges.shape[0]) % 2, stiffness=1e3))

    def fibres(scene):
        m = scene.mesh.num_elements
        fibres = torch.randn(m, scene.dim, dtype=torch.float64)
        scene.add(es.FibreMuscles(fibres, torch.arange(m) % 2, stiffness=3e5))

    def obstacles(scene):
        scene.add(es.Ground(-0.2, normal=(0.1, 1.0, 0.2), friction=0.5, barrier_distance=0.5))
        scene.add(es.SphereObstacle((0.5, -0.8, 0.5), 0.7, barrier_distance=0.5))
        scene.add(es.BoxObstacle((-0.6, -0.5, -0.6), (-0.1, 0.8, 0.3), barrier_distance=0.5))

    return [
        ("neo-hookean-2d", 2, elastic(2)),
        ("neo-hookean-3d", 3, elastic(3)),
        ("springs", 3, springs),
        ("actuated-springs", 3, actuated),
        ("fibre-muscles-2d", 2, fibres),
        ("fibre-muscles-3d", 3, fibres),
        ("obstacles-and-friction", 3, obstacles),
    ]


@pytest.mark.parametrize("name, dim, build", _kernel_cases(), ids=[c[0] for c in _kernel_cases()])
@pytest.mark.parametrize("inverted", [False, True], ids=["deformed", "inverted"])
def test_closed_form_gradients_match_autograd(name, dim, build, inverted):
    mesh = small_box(dim)
    scene = es.Scene(mesh, gravity=(0.0, -9.81, 0.0)[:dim])
    build(scene)
    x = mesh.vertices + 0.05 * torch.randn_like(mesh.vertices)
    if inverted and "obstacles" not in name:
        x[:, 1] = -x[:, 1]  # every element turned inside out
    x = x[None]
    velocity = 0.3 * torch.randn_like(x)
    # the step's own terms too: inertia and, where obstacles touch, lagged friction
    previous = x - 0.01 * velocity
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, previous, velocity, scene.free)
    action = torch.rand(1, 8, dtype=torch.float64) * 2 - 1
    assert any(type(term).__name__ == "LaggedFriction" for term in terms) or "obstacles" not in name
    for term in terms:
        result = term.value_and_gradient(x, action)
        assert result is not None, type(term).__name__
        energy, reference = energy_and_gradient(lambda y, t=term: t(y, action), x)
        torch.testing.assert_close(result[0], energy, rtol=1e-12, atol=1e-12)
        scale = float(reference.abs().max()) + 1e-300
        torch.testing.assert_close(result[1], reference, rtol=1e-9, atol=1e-11 * scale)
