"""The linear solves of `energysim.linalg.linear_solve` and `energysim.linalg.conjugate_gradient`,
checked against torch.linalg.solve on random systems, and the chooser's decisions."""

from __future__ import annotations

import pytest
import torch

import energysim as es
from energysim.creatures import resting_state
from energysim.integrators.adjoint import solve_adjoint, step_terms
from energysim.linalg.assembly import cached_pattern
from energysim.linalg.block_tridiagonal import gather_blocks
from energysim.linalg.conjugate_gradient import ConjugateGradient, batched_dot
from energysim.linalg.linear_solve import (
    BandCholesky,
    DenseCholesky,
    LevelCholesky,
    choose,
    eager_system,
    level_layout_of,
    solve_with_shifts,
)
from energysim.objective.objective import Objective

RTOL = 1e-10


def _chain_spd(batch: int, vertices: int, fixed: list[int], seed: int) -> torch.Tensor:
    """Random SPD matrices `[B, N, N]` (N = 3·vertices) coupling only neighbouring vertices of a chain
    (so that the band and level solves apply), with the DOFs of the `fixed` vertices eliminated
    (identity rows and columns), as the Hessian assembly does."""
    generator = torch.Generator().manual_seed(seed)
    size = 3 * vertices
    matrices = torch.zeros(batch, size, size, dtype=torch.float64)
    for v in range(vertices - 1):
        block = torch.randn(batch, 6, 6, generator=generator, dtype=torch.float64)
        matrices[:, 3 * v : 3 * v + 6, 3 * v : 3 * v + 6] += block @ block.mT
    matrices += 0.5 * torch.eye(size, dtype=torch.float64)
    for v in fixed:
        dofs = slice(3 * v, 3 * v + 3)
        matrices[:, dofs, :] = 0.0
        matrices[:, :, dofs] = 0.0
        matrices[:, dofs, dofs] = torch.eye(3, dtype=torch.float64)
    return matrices


def _chain_groups(vertices: int) -> list[torch.Tensor]:
    return [torch.stack([torch.arange(vertices - 1), torch.arange(1, vertices)], dim=1)]


def _reference(matrices: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    pairs = zip(matrices, rhs, strict=True)
    solves = [torch.linalg.solve(matrix, vector.reshape(-1)) for matrix, vector in pairs]
    return torch.stack(solves).reshape(rhs.shape)


def _relative_error(solution: torch.Tensor, expected: torch.Tensor) -> float:
    return float(((solution - expected).flatten(1).norm(dim=1) / expected.flatten(1).norm(dim=1)).max())


def _level_system(matrices: torch.Tensor, like: torch.Tensor, groups: list[torch.Tensor]) -> LevelCholesky:
    # the level blocks of the dense matrices, from their entries in the sparsity pattern's order,
    # as `HessianOperator.level_blocks` gathers them from the assembled CSR values
    batch, n, dim = like.shape
    size = n * dim
    pattern = cached_pattern(groups, n, dim, batch)
    rows, cols = pattern.row_indices, pattern.col_indices
    values = matrices[rows // size, rows % size, cols % size]
    layout = level_layout_of(groups, like)
    return LevelCholesky(*gather_blocks(values, layout), layout)


def test_one_level_layout_serves_every_batch_size() -> None:
    # a batch that drops its converged entries meets several sizes in one solve: the layout (a
    # per-entry ordering) is built once, not once per size
    groups = _chain_groups(12)
    layouts = [level_layout_of(groups, torch.zeros(batch, 12, 3, dtype=torch.float64)) for batch in (1, 3, 7)]
    assert layouts[0] is layouts[1] is layouts[2]


@pytest.mark.parametrize("method", ["dense", "banded", "levels", "cg"])
def test_each_linear_solve_equals_torch_solve_on_random_spd_systems_with_fixed_dofs(method: str) -> None:
    vertices, fixed = 12, [0, 5]
    matrices = _chain_spd(3, vertices, fixed, seed=1)
    like = torch.zeros(3, vertices, 3, dtype=torch.float64)
    rhs = torch.randn(like.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    groups = _chain_groups(vertices)
    expected = _reference(matrices, rhs)
    wanted = torch.ones(3, dtype=torch.bool)
    if method == "dense":
        solution, solved = DenseCholesky(matrices).solve(rhs, wanted)
    elif method == "banded":
        solution, solved = BandCholesky.from_dense(matrices, level_layout_of(groups, like)).solve(rhs, wanted)
    elif method == "levels":
        solution, solved = _level_system(matrices, like, groups).solve(rhs, wanted)
    else:
        result = ConjugateGradient(max_iter=500).solve(
            lambda v: (matrices @ v.reshape(3, -1, 1)).reshape(v.shape), rhs, lambda r: r, 1e-13
        )
        solution, solved = result.solution, result.converged
    assert solved.tolist() == [True, True, True]
    assert _relative_error(solution, expected) < RTOL
    # a fixed DOF's row is the identity's: the solution there is the right-hand side
    torch.testing.assert_close(solution[:, fixed], rhs[:, fixed], rtol=RTOL, atol=0.0)


def test_an_indefinite_entry_is_left_unsolved_or_shifted_to_a_descent_direction() -> None:
    matrices = _chain_spd(2, 8, [], seed=3)
    largest = float(torch.linalg.eigvalsh(matrices[1]).max())
    matrices[1] -= 0.75 * largest * torch.eye(24, dtype=torch.float64)
    assert torch.linalg.cholesky_ex(matrices).info.ne(0).tolist() == [False, True]
    rhs = torch.randn(2, 8, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    wanted = torch.ones(2, dtype=torch.bool)
    plain, solved = solve_with_shifts(DenseCholesky(matrices), rhs, wanted)
    assert solved.tolist() == [True, False] and bool((plain[1] == 0).all())
    shifted, solved = solve_with_shifts(DenseCholesky(matrices), rhs, wanted, (1e-2, 1e-1, 1.0, 10.0))
    assert solved.tolist() == [True, True]
    assert float((shifted[1] * rhs[1]).sum()) > 0.0  # along rhs = −∇E: downhill


def test_truncated_cg_on_an_indefinite_system_returns_a_descent_direction() -> None:
    # H = diag(1, …, 1, −1, …): the model has no minimum; Steihaug stops on the negative curvature
    # with a direction p along which the gradient g = −rhs decreases, gᵀp < 0
    size = 12
    diagonal = torch.cat([torch.linspace(1.0, 4.0, size // 2), -torch.linspace(1.0, 2.0, size // 2)])
    diagonal = diagonal.double()[torch.randperm(size, generator=torch.Generator().manual_seed(5))]
    rhs = torch.randn(1, size // 3, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    result = ConjugateGradient(max_iter=100, truncate=True).solve(
        lambda v: v * diagonal.reshape(v.shape[1:]), rhs, lambda r: r, 1e-12
    )
    assert result.indefinite.tolist() == [True]
    assert float(batched_dot(-rhs, result.solution)) < 0.0
    # without truncation the same system is flagged, for the caller to refuse
    plain = ConjugateGradient(max_iter=100).solve(
        lambda v: v * diagonal.reshape(v.shape[1:]), rhs, lambda r: r, 1e-12
    )
    assert plain.indefinite.tolist() == [True] and plain.converged.tolist() == [False]


def _worm(batch: int, noise: float = 0.0) -> tuple[es.Scene, torch.Tensor, torch.Tensor]:
    """A worm scene and a batch of `batch` resting positions `[B, n, 3]` moved by `noise` m
    (upwards only, above the ground), with their velocities."""
    scene = es.load_creature("worm").scene()
    state = resting_state(scene).expand(batch, -1).clone()
    x, v = scene.split_state(state)
    shift = noise * torch.randn(x.shape, generator=torch.Generator().manual_seed(7), dtype=x.dtype)
    shift[..., 1] = shift[..., 1].abs()
    return scene, x + shift, v


def test_the_chooser_picks_by_size_batch_and_assembly() -> None:
    scene, x, v = _worm(16)
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, v, scene.free)
    groups = Objective(terms, scene.free, scene.dt / scene.vertex_mass).element_groups()
    # one worm (432 DOFs) on the CPU: band Cholesky; a batch of 16: the level solve
    assert choose(groups, x[:1]).method == "banded"
    assert choose(groups, x).method == "levels"
    # above the direct limit: CG; a compiled band Hessian raises the limit and wins for any batch
    assert choose(groups, x, max_dofs=400).method == "cg"
    compiled = choose(groups, x, max_dofs=400, compiled_max_dofs=5000)
    assert (compiled.method, compiled.compiled) == ("banded", True)
    # a forced method is kept; with no coupling elements there is nothing to order: dense
    assert choose(groups, x, method="dense").method == "dense"
    assert choose([], x).method == "dense"
    # a small box: dense
    box = torch.zeros(1, 8, 3, dtype=torch.float64)
    assert choose([torch.tensor([[0, 1, 2, 3], [4, 5, 6, 7]])], box).method == "dense"


def test_the_adjoint_solution_equals_the_forward_linear_solve_of_the_same_system() -> None:
    # the backward's u = H⁻¹ b and Newton's direct direction for the same H and right-hand side
    for batch in (1, 3):
        scene, x, v = _worm(batch, noise=1e-4)
        terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, v, scene.free)
        objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass)
        operator = objective.hessian(x)
        rhs = torch.randn(x.shape, generator=torch.Generator().manual_seed(8), dtype=x.dtype)
        rhs = rhs * scene.free[:, None]
        adjoint = solve_adjoint(operator, rhs, x, 1e-12, 600)
        forward, solved = es.NewtonCG()._direct(operator, rhs, x, torch.ones(batch, dtype=torch.bool))
        assert bool(solved.all())
        assert _relative_error(adjoint, forward) < RTOL
        plan = choose([elements for elements, _ in operator.blocks], x)
        assert plan.method == ("banded" if batch == 1 else "levels")
        dense = operator.dense(x)
        assert _relative_error(adjoint, _reference(dense, rhs)) < 1e-8
        # the adjoint's CG (no direct solve) reaches the same solution
        by_cg = solve_adjoint(operator, rhs, x, 1e-12, 0)
        assert _relative_error(by_cg, adjoint) < 1e-8
        assert eager_system(choose([], x, max_dofs=0), operator, x) is None
