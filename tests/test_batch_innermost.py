"""The batch-innermost copies of per-entry data (`energysim.linalg.batch_innermost`): the same values as
the permuted originals, in rows padded apart, for the lagged viscosity and friction and their row
subsets alike."""

from __future__ import annotations

import torch

import energysim as es
from energysim.contact.friction import LaggedFriction
from energysim.fem.kinematics import deformation_gradient
from energysim.linalg.batch_innermost import BATCH_ROW_PADDING, batch_innermost


def assert_padded_copy(copy: torch.Tensor, original: torch.Tensor, *dims: int) -> None:
    expected = original.permute(*dims)
    assert copy.shape == expected.shape
    assert torch.equal(copy, expected)
    assert copy.stride(-1) == 1
    assert copy.stride(-2) == copy.shape[-1] + BATCH_ROW_PADDING
    assert copy.data_ptr() != original.data_ptr()


def test_batch_innermost_copies_the_permuted_values_into_padded_rows_and_keeps_the_gradient():
    values = torch.randn(5, 7, 3, dtype=torch.float64, requires_grad=True)
    copy = batch_innermost(values, 2, 1, 0)
    assert_padded_copy(copy, values.detach(), 2, 1, 0)
    weights = torch.randn(copy.shape, dtype=torch.float64)
    (gradient,) = torch.autograd.grad((copy * weights).sum(), values)
    assert torch.equal(gradient, weights.permute(2, 1, 0))


def test_lagged_viscosity_keeps_ds_dm_inverse_batch_innermost_also_for_a_subset():
    mesh = es.TetMesh.box(size=(0.3, 0.1, 0.1), cells=(3, 1, 1))
    scene = es.Scene(mesh, density=1000.0, dt=1 / 60, gravity=None)
    term = es.Viscosity(30.0)
    scene.add(term)
    generator = torch.Generator().manual_seed(0)
    x = scene.rest_positions + 0.02 * torch.randn(
        (9, scene.num_vertices, 3), generator=generator, dtype=torch.float64
    )
    (lagged,) = term.lagged_terms(x, 1 / 60)
    # F_n = Σ_b x_b ⊗ ∇N_b equals Ds Dm⁻¹, the kinematics' own definition
    expected = deformation_gradient(x[:, term.element_vertices], term.rest_edge_inverse)
    assert torch.allclose(lagged.start_gradient, expected, rtol=0.0, atol=1e-13)
    assert_padded_copy(lagged.start_gradient_t, lagged.start_gradient, 2, 3, 1, 0)
    rows = torch.tensor([7, 2, 4])
    part = lagged.rows(rows)
    assert_padded_copy(part.start_gradient_t, lagged.start_gradient[rows], 2, 3, 1, 0)


def test_lagged_friction_lays_out_its_step_data_batch_innermost_also_for_a_subset():
    generator = torch.Generator().manual_seed(2)
    batch, vertices = 10, 4
    normal = torch.nn.functional.normalize(
        torch.randn(batch, vertices, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    term = LaggedFriction(
        torch.arange(vertices)[:, None],
        torch.randn(batch, vertices, 3, generator=generator, dtype=torch.float64),
        normal,
        torch.rand(batch, vertices, generator=generator, dtype=torch.float64),
        torch.tensor(1.0, dtype=torch.float64),
        1e-4,
    )
    for friction in (term, term.rows(torch.tensor([9, 0, 3, 3]))):
        assert_padded_copy(friction.previous_positions_t, friction.previous_positions, 2, 1, 0)
        assert_padded_copy(friction.projector_t, friction.projector, 2, 3, 1, 0)
        assert_padded_copy(friction.weight_t, friction.weight, 1, 0)
