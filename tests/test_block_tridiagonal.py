"""Block-tridiagonal and band direct solves over breadth-first vertex levels, checked against dense
float64 algebra (torch.linalg.solve / Cholesky of the assembled matrix)."""

from __future__ import annotations

import sys

import pytest
import torch

import energysim as es
from energysim.creatures import resting_state
from energysim.integrators.adjoint import step_terms
from energysim.linalg.banded import band_cholesky_solve, prefer_band
from energysim.linalg.block_tridiagonal import (
    block_cholesky,
    block_cholesky_solve,
    from_levels,
    prefer_levels,
    to_levels,
    vertex_levels,
)
from energysim.linalg.linear_solve import INDEFINITE_SHIFTS, choose, level_layout_of
from energysim.objective.objective import Objective

RTOL = 1e-10


def _objective(
    scene: es.Scene, state: torch.Tensor, action: torch.Tensor | None
) -> tuple[Objective, torch.Tensor]:
    """The step objective at the previous positions, built as `energysim.integrators.step.step` builds it."""
    x, v = scene.split_state(state)
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, v, scene.free)
    objective = Objective(
        terms=terms, free=scene.free, residual_scale=scene.dt / scene.vertex_mass, action=action, anchor=x
    )
    terms[0].anchor = x
    return objective, x


def _worm_batch(
    noise: list[float], fix: bool = False, activation: float = 0.3
) -> tuple[es.Scene, torch.Tensor, torch.Tensor]:
    """A worm scene, a batch of perturbed resting states (one entry per noise amplitude, in m) and
    random actions in [−activation, activation]. Full activations at rest make H indefinite."""
    worm = es.load_creature("worm")
    scene = worm.scene()
    if fix:
        scene.fix(torch.nonzero(scene.rest_positions[:, 0] == scene.rest_positions[:, 0].min()).flatten())
    generator = torch.Generator().manual_seed(3)
    batch = len(noise)
    state = resting_state(scene).expand(batch, -1).clone()
    x, v = scene.split_state(state)
    amplitude = torch.tensor(noise, dtype=x.dtype)[:, None, None]
    shift = amplitude * torch.randn(x.shape, generator=generator, dtype=x.dtype)
    shift[..., 1] = shift[..., 1].abs()  # upwards only: every vertex stays above the ground
    x = x + shift
    v = v + 0.1 * torch.randn(v.shape, generator=generator, dtype=v.dtype)
    action = activation * (2 * torch.rand(batch, worm.num_actuators, generator=generator, dtype=x.dtype) - 1)
    return scene, torch.cat([x.flatten(1), v.flatten(1)], dim=1), action


def _meshes() -> dict[str, es.TetMesh | es.TriMesh]:
    return {
        "worm": es.load_creature("worm").mesh,
        "tet_box": es.TetMesh.box(size=(1.0, 1.0, 1.0), cells=(3, 3, 3)),
        "tri_box": es.TriMesh.box(size=(1.0, 0.2), cells=(20, 4)),
        "quadruped": es.load_creature("quadruped").mesh,
    }


@pytest.mark.parametrize("name", ["worm", "tet_box", "tri_box", "quadruped"])
def test_every_element_lies_in_one_level_or_two_adjacent(name: str) -> None:
    mesh = _meshes()[name]
    elements = mesh.elements
    levels = vertex_levels([elements], mesh.vertices.shape[0])
    spread = levels[elements].amax(dim=1) - levels[elements].amin(dim=1)
    assert int(spread.max()) <= 1
    # the levels are 0 … L−1 with none empty, so the padded blocks hold no empty level
    widths = torch.bincount(levels)
    assert int(widths.min()) >= 1 and int(levels.min()) == 0


def _vertex_bandwidth(place: torch.Tensor, elements: torch.Tensor) -> int:
    """The largest distance in the order `place` (`[n]`, vertex → position) of two vertices that
    share an element."""
    corners = place[elements]
    return int((corners[:, :, None] - corners[:, None, :]).abs().max())


@pytest.mark.parametrize("name", ["worm", "tet_box", "tri_box", "quadruped"])
def test_level_order_is_a_narrow_band(name: str) -> None:
    # the band solves factorise in the layout's order at a cost ∝ u². Held to two independent
    # orders of the same graph: the same levels with each in vertex-index order, and (in 3D, where
    # the creatures are) SciPy's reverse Cuthill–McKee ordering
    mesh = _meshes()[name]
    elements, n = mesh.elements, mesh.vertices.shape[0]
    dim = mesh.vertices.shape[1]
    layout = level_layout_of([elements], torch.zeros(1, n, dim, dtype=torch.float64))
    place = layout.band_position.reshape(n, dim)[:, 0] // dim  # the DOFs of a vertex are consecutive
    ours = _vertex_bandwidth(place, elements)
    assert layout.half_bandwidth == dim * ours + dim - 1
    levels = vertex_levels([elements], n)
    index_order = torch.empty(n, dtype=torch.int64)
    index_order[torch.sort(levels, stable=True).indices] = torch.arange(n)
    assert ours <= _vertex_bandwidth(index_order, elements)
    if dim == 3:
        sparse = pytest.importorskip("scipy.sparse")
        csgraph = pytest.importorskip("scipy.sparse.csgraph")
        pairs = elements[:, :, None].expand(-1, -1, dim + 1), elements[:, None, :].expand(-1, dim + 1, -1)
        rows, cols = (pair.reshape(-1).numpy() for pair in pairs)
        graph = sparse.csr_matrix((torch.ones(rows.size).numpy(), (rows, cols)), shape=(n, n))
        reverse = torch.as_tensor(csgraph.reverse_cuthill_mckee(graph, symmetric_mode=True).copy())
        reference = torch.empty(n, dtype=torch.int64)
        reference[reverse.long()] = torch.arange(n)
        assert ours <= _vertex_bandwidth(reference, elements)
    if name == "worm":
        assert ours == 10  # 14 with each level in vertex-index order (u = 32 against 44)


@pytest.mark.parametrize("name", ["worm", "tet_box", "tri_box", "quadruped"])
def test_levels_cost_the_least_of_every_start(name: str) -> None:
    # a mesh this small tries every vertex as the levels' start: the cost L·s³ of the levels chosen
    # is the least of every start's breadth-first levels, found here by a plain Python search
    mesh = _meshes()[name]
    n = mesh.vertices.shape[0]
    neighbours: list[set[int]] = [set() for _ in range(n)]
    for element in mesh.elements.tolist():
        for vertex in element:
            neighbours[vertex].update(element)
    least = None
    for start in range(n):
        frontier, seen, widths = [start], {start}, []
        while frontier:
            widths.append(len(frontier))
            frontier = [w for v in frontier for w in neighbours[v] if w not in seen]
            frontier = list(dict.fromkeys(frontier))
            seen.update(frontier)
        cost = len(widths) * max(widths) ** 3
        least = cost if least is None else min(least, cost)
    widths = torch.bincount(vertex_levels([mesh.elements], n))
    assert widths.numel() * int(widths.max()) ** 3 == least


def test_worm_levels_are_cross_sections() -> None:
    # the worm is a 16 × 3 × 3 vertex grid along x: levels from one end are at most 9 vertices wide,
    # and there are at least 16 of them (a dense factorisation costs ≈ 100× more)
    mesh = es.load_creature("worm").mesh
    levels = vertex_levels([mesh.elements], mesh.vertices.shape[0])
    widths = torch.bincount(levels)
    assert widths.numel() >= 16 and int(widths.max()) <= 9


def _dense_solve(dense: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """The reference solve of a batch: one torch.linalg.solve per entry. A batched LU solve of these
    sizes fails in this MKL build once torch's thread count has been lowered and raised again
    ("Pivots given to lu_solve must all be greater or equal to 1"), as the test fixtures do."""
    solves = [torch.linalg.solve(matrix, vector) for matrix, vector in zip(dense, rhs, strict=True)]
    return torch.stack(solves)


@pytest.mark.parametrize("fix", [False, True])
def test_block_solve_equals_dense_solve_on_the_worm_hessian(fix: bool) -> None:
    scene, state, action = _worm_batch([0.0, 1e-4, 3e-4], fix=fix)
    objective, x = _objective(scene, state, action)
    operator = objective.hessian(x)
    dense = operator.dense(x)
    diagonal, lower, layout = operator.level_blocks(x)
    rhs = torch.randn(x.shape, generator=torch.Generator().manual_seed(5), dtype=x.dtype)
    factor = block_cholesky(diagonal, lower)
    assert bool(factor.positive_definite.all())
    solution = from_levels(block_cholesky_solve(factor, to_levels(rhs, layout)), layout, x)
    expected = _dense_solve(dense, rhs.reshape(3, -1, 1)).reshape(x.shape)
    error = (solution - expected).flatten(1).norm(dim=1) / expected.flatten(1).norm(dim=1)
    assert float(error.max()) < RTOL
    if fix:  # fixed DOFs are eliminated: identity rows, so the solve returns the right-hand side there
        fixed = ~scene.free
        torch.testing.assert_close(solution[:, fixed], rhs[:, fixed], rtol=RTOL, atol=0.0)


def _indefinite_directions(solver: es.NewtonCG) -> tuple[torch.Tensor, ...]:
    """`solver`'s direct Newton directions for three worms whose middle one has an indefinite
    Hessian (3 mm of noise on 1 cm elements inverts some tets): the directions, which entries they
    solved, the dense Hessians, the gradients and x."""
    scene, state, action = _worm_batch([1e-4, 3e-3, 0.0])
    objective, x = _objective(scene, state, action)
    operator = objective.hessian(x)
    dense = operator.dense(x)
    assert torch.linalg.cholesky_ex(dense).info.ne(0).tolist() == [False, True, False]
    _, gradient = objective.energy_and_gradient(x)
    direction, solved = solver._direct(operator, -gradient, x, torch.ones(3, dtype=torch.bool))
    return direction, solved, dense, gradient, x


@pytest.mark.parametrize("method", ["levels", "banded", "dense"])
def test_indefinite_entry_is_unsolved_and_the_others_exact(method: str) -> None:
    direction, solved, dense, gradient, x = _indefinite_directions(es.NewtonCG(direct=method))
    assert solved.tolist() == [True, False, True]
    expected = _dense_solve(dense, -gradient.reshape(3, -1, 1)).reshape(x.shape)
    for entry in (0, 2):
        error = (direction[entry] - expected[entry]).norm() / expected[entry].norm()
        assert float(error) < RTOL
    assert bool((direction[1] == 0).all())


@pytest.mark.parametrize("method", ["levels", "banded", "dense"])
def test_indefinite_entry_takes_the_first_shift_that_factorises(method: str) -> None:
    # Levenberg–Marquardt by hand: H + τ|diag H| for τ = 1e-2, 1e-1, ... until Cholesky succeeds
    solver = es.NewtonCG(direct=method, indefinite="shift")
    direction, solved, dense, gradient, x = _indefinite_directions(solver)
    assert solved.tolist() == [True, True, True]
    indefinite = dense[1]
    for shift in INDEFINITE_SHIFTS:
        shifted = indefinite + shift * torch.diag(indefinite.diagonal().abs())
        if int(torch.linalg.cholesky_ex(shifted).info) == 0:
            break
    expected = _dense_solve(shifted[None], -gradient[1].reshape(1, -1, 1)).reshape(x[1].shape)
    error = (direction[1] - expected).norm() / expected.norm()
    assert float(error) < RTOL
    assert float((direction[1] * gradient[1]).sum()) < 0.0  # downhill, as a positive definite system gives


@pytest.mark.parametrize("method", ["levels", "banded"])
def test_step_with_levels_or_band_equals_dense_step(method: str) -> None:
    scene, state, action = _worm_batch([0.0, 1e-4, 2e-4], fix=True)
    dense = es.step(scene, state, action, solver=es.NewtonCG(tol=1e-8, direct="dense"))
    other = es.step(scene, state, action, solver=es.NewtonCG(tol=1e-8, direct=method))
    assert dense.stats.converged and other.stats.converged
    scale = float((dense.state - state).abs().max())
    assert float((other.state - dense.state).abs().max()) < RTOL * max(scale, 1.0)


def test_band_solve_is_exact_and_refuses_an_indefinite_entry() -> None:
    # the second entry's Hessian is indefinite (as in the level-solve test above)
    scene, state, action = _worm_batch([1e-4, 3e-3, 0.0], fix=True)
    objective, x = _objective(scene, state, action)
    operator = objective.hessian(x)
    dense = operator.dense(x)
    _, _, layout = operator.level_blocks(x)
    size = dense.shape[-1]
    # the level order is a band ordering, far narrower than the matrix
    assert 4 * (layout.half_bandwidth + 1) < size
    rhs = torch.randn(3, size, generator=torch.Generator().manual_seed(7), dtype=x.dtype)
    solution, positive_definite = band_cholesky_solve(dense, rhs, layout)
    assert positive_definite.tolist() == [True, False, True]
    for entry in (0, 2):
        expected = torch.linalg.solve(dense[entry], rhs[entry])
        assert float((solution[entry] - expected).norm() / expected.norm()) < RTOL
    assert bool((solution[1] == 0).all())
    # float32 takes LAPACK's single-precision routines
    single, _ = band_cholesky_solve(dense[:1].float(), rhs[:1].float(), layout)
    expected = torch.linalg.solve(dense[0], rhs[0])
    assert single.dtype == torch.float32
    assert float((single[0].double() - expected).norm() / expected.norm()) < 1e-3


def test_auto_picks_band_for_one_worm_on_the_cpu_and_levels_for_a_batch() -> None:
    scene, state, action = _worm_batch([0.0] * 16)
    for batch, method in ((1, "banded"), (16, "levels")):
        objective, x = _objective(scene, state[:batch], action[:batch])
        groups = [elements for elements, _ in objective.hessian(x).blocks]
        assert choose(groups, x).method == method
        # a compiled Hessian is assembled in band storage: the band path for any batch
        assert choose(groups, x, compiled_max_dofs=5000).method == "banded"
    # LAPACK's band routines are CPU only: elsewhere one worm is factorised dense
    layout = level_layout_of(groups, x[:1])
    for compiled in (False, True):
        assert not prefer_band(layout, 1, x.shape[1] * x.shape[2], torch.device("cuda"), compiled=compiled)
    assert prefer_band(layout, 1, x.shape[1] * x.shape[2], torch.device("cpu"))
    assert not prefer_band(layout, 16, x.shape[1] * x.shape[2], torch.device("cpu"))


def test_unknown_direct_method_is_refused() -> None:
    with pytest.raises(ValueError, match="direct"):
        es.NewtonCG(direct="sparse")
    with pytest.raises(ValueError, match="factor_precision"):
        es.NewtonCG(factor_precision="half")


def test_batched_backward_through_the_level_solve_equals_single_entries() -> None:
    # B = 3 worms take the block-tridiagonal adjoint solve, one worm the band one: the gradients of
    # the same loss with respect to the state and the action must agree entry by entry
    scene, state, action = _worm_batch([0.0, 1e-4, 2e-4])
    scene.solver = es.NewtonCG(tol=1e-9)
    objective, x = _objective(scene, state, action)
    layout = objective.hessian(x).level_layout(x)
    assert prefer_levels(layout, 3, x.shape[1] * x.shape[2])
    assert not prefer_levels(layout, 1, x.shape[1] * x.shape[2])
    assert prefer_band(layout, 1, x.shape[1] * x.shape[2], x.device)
    weights = torch.randn(state.shape, generator=torch.Generator().manual_seed(5), dtype=state.dtype)

    def gradients(
        start: torch.Tensor, act: torch.Tensor, weight: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        start = start.clone().requires_grad_(True)
        act = act.clone().requires_grad_(True)
        (es.timestep(scene, start, act) * weight).sum().backward()
        return start.grad, act.grad

    batched_state, batched_action = gradients(state, action, weights)
    for i in range(3):
        single_state, single_action = gradients(state[i : i + 1], action[i : i + 1], weights[i : i + 1])
        scale = float(single_state.abs().max())
        assert float((batched_state[i] - single_state[0]).abs().max()) < 1e-7 * scale
        action_scale = float(single_action.abs().max())
        assert float((batched_action[i] - single_action[0]).abs().max()) < 1e-7 * action_scale


def test_backward_through_the_band_solve_equals_the_dense_one(monkeypatch: pytest.MonkeyPatch) -> None:
    # one worm's adjoint solve takes the band path; forced dense, the gradient must be the same
    scene, state, action = _worm_batch([1e-4])
    scene.solver = es.NewtonCG(tol=1e-9)
    weights = torch.randn(state.shape, generator=torch.Generator().manual_seed(6), dtype=state.dtype)

    def gradient() -> torch.Tensor:
        start = state.clone().requires_grad_(True)
        (es.timestep(scene, start, action) * weights).sum().backward()
        return start.grad

    band = gradient()
    # the backward's choice alone: the forward (`step`) keeps its band solve
    adjoint = sys.modules["energysim.integrators.adjoint"]
    original = adjoint.choose
    monkeypatch.setattr(adjoint, "choose", lambda *args, **kw: original(*args, **kw, method="dense"))
    dense = gradient()
    assert float((band - dense).abs().max()) < 1e-9 * float(dense.abs().max())


def test_converged_batch_entries_build_no_preconditioner(monkeypatch: pytest.MonkeyPatch) -> None:
    # an entry that has converged gets no direction (slope 0): counting it as going uphill made the
    # solver build the whole batch's Hessian operator for a preconditioned gradient nobody used
    scene, state, action = _worm_batch([0.0, 2e-3])
    state[0] = resting_state(scene)
    action[0] = 0.0
    built = []
    original = es.NewtonCG._preconditioner
    monkeypatch.setattr(es.NewtonCG, "_preconditioner", lambda *args: built.append(1) or original(*args))
    solver = es.NewtonCG(tol=1e-6, indefinite="shift", compact_below=0.0)
    together = es.step(scene, state, action, solver=solver)
    alone = [es.step(scene, state[entry], action[entry], solver=solver) for entry in range(2)]
    assert alone[0].stats.iterations < alone[1].stats.iterations == together.stats.iterations
    assert built == []
    for entry in range(2):
        assert torch.allclose(together.state[entry], alone[entry].state, rtol=0, atol=1e-10)
