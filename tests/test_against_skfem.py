"""Quasi-static cantilevers under gravity, energysim against scikit-fem's linear P1 elasticity.

energysim minimises a stable neo-Hookean energy plus gravity with Newton–CG, using its own
kinematics, autograd gradients, closed-form Hessian blocks and lumped masses. scikit-fem
assembles the linear-elastic stiffness with its own P1 basis, quadrature and Lamé conversion,
builds the consistent load vector of ρg, and solves by a direct sparse factorisation. The two
share only the mesh (same vertices, same elements) and the numbers E, ν, ρ, g, so agreement
checks energysim's whole static path against an independent FEM code.

At small strain the neo-Hookean model linearises to exactly the elasticity scikit-fem solves
(checked directly on the rest stiffness below), and both use the same elements, so they lock
identically (the ν = 0.49 case too). What remains between the beams is the nonlinearity that
energysim keeps, which relative to the deflection grows in proportion to the load: for a tip
sag s it is mostly the axial shortening of the bent beam, which linear theory leaves out, about
0.6 s/L of the field; the tip deflection moves far less (below 0.2 s/L relative, most at
ν = 0.49). E = 1 GPa under 9.81 m/s² puts s/L between 1.6e-4 and 1.1e-3, small enough for that,
yet the strains stay large against the float64 rounding of the energy, which a much smaller
load would bring up to the level of the solver's stopping test.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import skfem_reference as ref
import torch

import energysim as es

LENGTH, DEPTH = 1.0, 0.1
DENSITY = 1000.0
YOUNGS = 1e9
GRAVITY = 9.81
CELLS = {3: (20, 2, 2), 2: (40, 4)}


def gravity_vector(dim: int, g: float) -> tuple[float, ...]:
    return (0.0, -g) if dim == 2 else (0.0, -g, 0.0)


def beam(dim: int) -> es.SimplexMesh:
    if dim == 2:
        return es.TriMesh.box(size=(LENGTH, DEPTH), cells=CELLS[2])
    return es.TetMesh.box(size=(LENGTH, DEPTH, DEPTH), cells=CELLS[3])


def youngs_modulus_field(mesh: es.SimplexMesh, per_element: bool) -> float | np.ndarray:
    if not per_element:
        return YOUNGS
    # the half next to the clamp, where the bending moment is largest, four times stiffer
    centroid_x = mesh.vertices.numpy()[mesh.elements.numpy()].mean(axis=1)[:, 0]
    return np.where(centroid_x < 0.5 * LENGTH, 4.0 * YOUNGS, YOUNGS)


@functools.cache
def energysim_displacement(
    dim: int, poissons_ratio: float, g: float, per_element: bool = False
) -> np.ndarray:
    """Equilibrium displacement `[n, d]` from `es.solve_static`, clamped at x = 0 (cached across tests)."""
    mesh = beam(dim)
    youngs = youngs_modulus_field(mesh, per_element)
    scene = es.Scene(mesh, density=DENSITY, gravity=gravity_vector(dim, g))
    scene.add(es.NeoHookean(youngs_modulus=torch.as_tensor(youngs), poissons_ratio=poissons_ratio))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] == 0.0).reshape(-1))
    # The velocity residual h M⁻¹ ∇E starts at h·g on every free vertex; ask for 1e-4 of that,
    # which leaves a solver error near 1e-6 of the deflection, far below what is compared. Not
    # tighter: Newton–CG's line search can stall near 1e-5 of it on these beams, where the
    # energy's rounding error exceeds the decrease it has to detect.
    solver = es.NewtonCG(tol=1e-4 * scene.dt * g, max_iter=30)
    result = es.solve_static(scene, solver=solver)
    assert result.stats.converged, result.stats.summary()
    return (result.state - mesh.vertices).numpy()


@functools.cache
def skfem_displacement(dim: int, poissons_ratio: float, g: float, per_element: bool = False) -> np.ndarray:
    """The linear-elastic P1 solution `[n, d]` of the same clamped beam, from scikit-fem."""
    mesh = beam(dim)
    vertices, elements = mesh.vertices.numpy(), mesh.elements.numpy()
    basis = ref.vector_basis(vertices, elements)
    stiffness = ref.stiffness(basis, youngs_modulus_field(mesh, per_element), poissons_ratio)
    load = ref.body_force_load(basis, DENSITY, gravity_vector(dim, g))
    return ref.clamped_displacement(basis, stiffness, load, np.flatnonzero(vertices[:, 0] == 0.0))


def tip_deflection(dim: int, displacement: np.ndarray) -> float:
    """Mean y-displacement of the vertices at x = L, in m."""
    tip = np.isclose(beam(dim).vertices.numpy()[:, 0], LENGTH)
    return float(displacement[tip, 1].mean())


def compare(dim: int, poissons_ratio: float, per_element: bool = False) -> tuple[float, float, float]:
    """(tip relative difference, field relative difference, scikit-fem tip deflection in m)."""
    u_es = energysim_displacement(dim, poissons_ratio, GRAVITY, per_element)
    u_sk = skfem_displacement(dim, poissons_ratio, GRAVITY, per_element)
    tip_es, tip_sk = tip_deflection(dim, u_es), tip_deflection(dim, u_sk)
    tip_error = abs(tip_es - tip_sk) / abs(tip_sk)
    field_error = np.linalg.norm(u_es - u_sk, axis=1).max() / np.linalg.norm(u_sk, axis=1).max()
    return float(tip_error), float(field_error), float(tip_sk)


def assert_agreement(tip_error: float, field_error: float, tip_sk: float) -> None:
    # guards against a vacuous comparison: the beam must sag, by a small fraction of its length
    assert -3e-3 * LENGTH < tip_sk < -1e-5 * LENGTH, f"scikit-fem tip deflection {tip_sk:.3e} m"
    assert tip_error < 1e-2, f"tip deflection differs by {tip_error:.2e} (relative)"
    assert field_error < 1e-2, f"max |u_es - u_skfem| / max |u_skfem| = {field_error:.2e}"


# --- the reference itself -----------------------------------------------------------------------


@pytest.mark.parametrize("dim", [2, 3])
def test_consistent_load_equals_lumped_gravity(dim):
    # energysim's gravity acts through lumped masses, the reference uses scikit-fem's consistent
    # load. For P1 elements and uniform ρg these coincide (∫_e N_i = V_e/(d+1)), so the comparisons
    # below are like with like without feeding energysim's masses into the reference.
    mesh = beam(dim)
    scene = es.Scene(mesh, density=DENSITY, gravity=gravity_vector(dim, GRAVITY))
    basis = ref.vector_basis(mesh.vertices.numpy(), mesh.elements.numpy())
    consistent = ref.nodal(basis, ref.body_force_load(basis, DENSITY, gravity_vector(dim, GRAVITY)))
    lumped = scene.vertex_mass.numpy()[:, None] * np.asarray(gravity_vector(dim, GRAVITY))
    np.testing.assert_allclose(consistent, lumped, rtol=0, atol=1e-12 * np.abs(lumped).max())


def test_reference_per_element_form_reduces_to_the_stock_form():
    # the heterogeneous-E form is hand-written; with a uniform field it must be scikit-fem's own
    mesh = beam(3)
    basis = ref.vector_basis(mesh.vertices.numpy(), mesh.elements.numpy())
    stock = ref.stiffness(basis, YOUNGS, 0.3)
    field = ref.stiffness(basis, np.full(mesh.num_elements, YOUNGS), 0.3)
    assert abs(stock - field).max() < 1e-12 * abs(stock).max()


# --- energysim against scikit-fem ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("dim", "poissons_ratio", "per_element"),
    [(3, 0.3, False), (3, 0.49, False), (2, 0.3, False), (3, 0.3, True)],
    ids=["3d", "3d-nu0.49", "2d", "3d-per-element"],
)
@pytest.mark.parametrize("hessian", ["elements", "autograd"])
def test_rest_stiffness_is_skfem_linear_elasticity(dim, poissons_ratio, per_element, hessian):
    # The beams below agree only to within their nonlinearity; at F = I the neo-Hookean Hessian
    # must equal the linear-elastic stiffness exactly, whatever the load. Both the closed-form
    # element blocks Newton-CG uses and plain autograd are checked, on random vectors.
    mesh = beam(dim)
    youngs = youngs_modulus_field(mesh, per_element)
    scene = es.Scene(mesh, density=DENSITY, gravity=None)
    scene.add(es.NeoHookean(youngs_modulus=torch.as_tensor(youngs), poissons_ratio=poissons_ratio))
    objective = es.Objective(list(scene.terms), free=scene.free, residual_scale=scene.dt / scene.vertex_mass)
    v = torch.randn(4, *mesh.vertices.shape, dtype=torch.float64)
    x = mesh.vertices.expand_as(v)
    product = objective.hessian(x, use_element_blocks=hessian == "elements").matvec(v).numpy()

    basis = ref.vector_basis(mesh.vertices.numpy(), mesh.elements.numpy())
    stiffness = ref.stiffness(basis, youngs, poissons_ratio)
    expected = np.empty_like(product)
    for b, vb in enumerate(v.numpy()):
        dofs = np.empty(basis.N)
        dofs[basis.nodal_dofs] = vb.T
        expected[b] = ref.nodal(basis, stiffness @ dofs)
    error = np.abs(product - expected).max() / np.abs(expected).max()
    assert error < 1e-12, f"max |H v - K v| / max |K v| = {error:.2e}"


def test_cantilever_3d_matches_skfem():
    tip_error, field_error, tip_sk = compare(3, 0.3)
    assert_agreement(tip_error, field_error, tip_sk)
    assert tip_error < 1e-4  # measured ~1e-6: the remaining difference is the nonlinearity


def test_near_incompressible_cantilever_3d_matches_skfem():
    # both codes use the same P1 tets, which lock the same way: the locked answer must agree too
    tip_error, field_error, tip_sk = compare(3, 0.49)
    assert_agreement(tip_error, field_error, tip_sk)
    assert tip_error < 1e-3


def test_plane_strain_cantilever_2d_matches_skfem():
    tip_error, field_error, tip_sk = compare(2, 0.3)
    assert_agreement(tip_error, field_error, tip_sk)
    assert tip_error < 1e-4


def test_per_element_youngs_modulus_matches_skfem():
    tip_error, field_error, tip_sk = compare(3, 0.3, per_element=True)
    assert_agreement(tip_error, field_error, tip_sk)
    # the field must change the answer a lot, or a code that ignored it could still pass
    uniform = tip_deflection(3, skfem_displacement(3, 0.3, GRAVITY))
    stiffened = tip_deflection(3, skfem_displacement(3, 0.3, GRAVITY, per_element=True))
    assert abs(stiffened) < 0.5 * abs(uniform)


def test_doubling_gravity_doubles_the_deflection():
    # in the linear regime the response is proportional to the load; what is left is the
    # nonlinearity (~1e-6 of the tip deflection at this load) and the solver's tolerance
    single = tip_deflection(3, energysim_displacement(3, 0.3, GRAVITY))
    double = tip_deflection(3, energysim_displacement(3, 0.3, 2.0 * GRAVITY))
    ratio = double / single
    assert abs(ratio - 2.0) < 1e-3, f"deflection ratio {ratio:.8f} for twice the gravity"
