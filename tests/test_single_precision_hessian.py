"""The float32 band Hessian that float32 band factorisations take (`band_hessian(single=True)`): the
translation invariance it relies on, its precision far from the origin against the float64 Hessian,
and the float32 copies of terms it evaluates."""

from __future__ import annotations

import pytest
import torch
from conftest import lay_out_per_element, small_box

import energysim as es
from energysim.contact.obstacles import Ground
from energysim.creatures import load_creature, resting_state
from energysim.integrators.adjoint import step_terms
from energysim.linalg.linear_solve import level_layout_of
from energysim.objective.objective import Objective

# 1 km along the ground: float32 spaces positions there 6e-5 m apart, so the worm's neo-Hookean
# blocks taken at absolute float32 positions are off by 0.8 % of the largest entry (4e-7 relative)
FAR = 1000.0


def _worm_objective(batch: int, shift: float) -> tuple[Objective, torch.Tensor]:
    """The compiled step objective of `batch` worms (with the body's viscosity, muscles on, moving),
    all moved `shift` metres along the ground, and a probe point near their start."""
    scene = load_creature("worm").scene(1 / 60, 0.8)
    scene.add(es.Viscosity(30.0))
    generator = torch.Generator().manual_seed(3)
    state = resting_state(scene).reshape(1, -1).expand(batch, -1)
    x, v = scene.split_state(state)
    normal = next(term for term in scene.terms if isinstance(term, Ground)).normal
    along = torch.tensor([1.0, 0.0, 1.0], dtype=x.dtype)
    along = along - (along @ normal) * normal
    x = x + shift * along / along.norm()
    v = v + 0.05 * torch.randn(v.shape, generator=generator, dtype=v.dtype)
    action = torch.rand(batch, 10, generator=generator, dtype=x.dtype) * 2 - 1
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, v, scene.free)
    objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass, action, compiled=True)
    probe = x + 1e-4 * torch.randn(x.shape, generator=generator, dtype=x.dtype)
    return objective, probe


def _generator() -> torch.Generator:
    return torch.Generator().manual_seed(7)


def test_the_terms_declared_translation_invariant_are():
    # E(x + c) = E(x) for a shift c common to every vertex, in float64, for every declared term of
    # the moving worm (elasticity, muscles, body viscosity) and for springs on a box
    objective, x = _worm_objective(batch=2, shift=0.0)
    shift = torch.tensor([123.4, -56.7, 8.9], dtype=x.dtype)
    box = small_box(3)
    springs = [es.Springs(stiffness=50.0), es.ActuatedSprings(torch.tensor([[0, 1], [2, 3]]), [0, 1], 40.0)]
    scene = es.Scene(box, gravity=None)
    for term in springs:
        scene.add(term)
    wobble = torch.randn(1, *box.vertices.shape, generator=_generator(), dtype=box.vertices.dtype)
    box_x = box.vertices[None] + 0.01 * wobble
    declared = 0
    cases = [(term, x, objective.action) for term in objective.terms]
    cases += [(term, box_x, torch.full((1, 2), 0.5, dtype=box_x.dtype)) for term in springs]
    for term, at, action in cases:
        if not term.is_translation_invariant:
            continue
        declared += 1
        energy = term(at, action)
        assert torch.allclose(term(at + shift, action), energy, rtol=1e-9, atol=1e-12)
    assert declared == 5  # neo-Hookean, fibre muscles, lagged viscosity, both springs


@pytest.mark.parametrize(("batch", "batch_last"), [(4, False), (4, True), (8, True)])
def test_the_float32_band_hessian_keeps_float32_precision_a_kilometre_away(
    batch: int, batch_last: bool, monkeypatch
):
    # per element (a GPU's layout of small batches) and batch-last; the worms' Hessians entry by
    # entry against the float64 ones, to a few float32 roundings of the largest entry (measured
    # 1.1e-7 and 1.7e-7)
    if not batch_last:
        lay_out_per_element(monkeypatch)
    objective, x = _worm_objective(batch, shift=FAR)
    layout = level_layout_of(objective.element_groups(), x)
    double = objective.band_hessian(x, layout)
    single = objective.band_hessian(x, layout, single=True)
    assert double.dtype == torch.float64 and single.dtype == torch.float32
    scale = double.abs().amax(dim=(1, 2))
    error = (single.double() - double).abs().amax(dim=(1, 2)) / scale
    assert float(error.max()) < 3e-6
    # the same Hessians as at the origin, within float32's rounding
    near, near_x = _worm_objective(batch, shift=0.0)
    at_origin = near.band_hessian(near_x, layout, single=True).double()
    assert float(((single.double() - at_origin).abs().amax(dim=(1, 2)) / scale).max()) < 3e-6


def test_a_float32_copy_of_a_term_leaves_the_term_as_it_was():
    scene = load_creature("worm").scene(1 / 60, 0.8)
    muscles = next(term for term in scene.terms if isinstance(term, es.FibreMuscles))
    muscles.stiffness = torch.nn.Parameter(muscles.stiffness.detach().clone())
    before = {name: tensor.clone() for name, tensor in muscles.state_dict().items()}
    copy = muscles.in_precision(torch.float32)
    assert copy.stiffness.dtype == torch.float32 and not copy.stiffness.requires_grad
    assert copy.rest_volume.dtype == torch.float32 and copy.element_vertices.dtype == torch.int64
    assert isinstance(muscles.stiffness, torch.nn.Parameter) and muscles.stiffness.dtype == torch.float64
    for name, tensor in muscles.state_dict().items():
        assert tensor.dtype == before[name].dtype and torch.equal(tensor, before[name])
    x = scene.split_state(resting_state(scene)[None])[0]
    action = torch.full((1, 10), 0.7, dtype=x.dtype)
    expected = muscles(x, action)
    assert torch.allclose(copy(x.float(), action.float()).double(), expected, rtol=1e-5)
