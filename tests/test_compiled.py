"""Compiled objective evaluations (`Solver(compile=True)`) against the eager ones: the same energies,
gradients, dense Hessians and trajectories, and a clear fallback where compiling is not possible."""

from __future__ import annotations

import warnings

import pytest
import torch
from conftest import lay_out_per_element, small_box

import energysim as es
from energysim.contact.friction import LaggedFriction
from energysim.contact.obstacles import CCD_SAFETY
from energysim.creatures import load_creature, resting_state
from energysim.energies.base import EnergyTerm
from energysim.integrators.adjoint import step_terms
from energysim.integrators.common import state_energies
from energysim.integrators.implicit_stage import rows_of
from energysim.linalg import native
from energysim.linalg.linear_solve import level_layout_of
from energysim.objective import batch_last, compiled, compiled_hessian
from energysim.objective.objective import Objective


def _worm_objective(batch: int = 1, viscosity: bool = False) -> tuple[es.Scene, Objective, torch.Tensor]:
    """The step objective of the worm lying on the ground with its muscles on (and the env's body
    viscosity where asked), at a perturbed x."""
    scene = load_creature("worm").scene(1 / 60, 0.8)
    if viscosity:
        scene.add(es.Viscosity(30.0))
    generator = torch.Generator().manual_seed(0)
    state = resting_state(scene).reshape(1, -1).expand(batch, -1)
    x, v = scene.split_state(state)
    v = v + 0.05 * torch.randn(v.shape, generator=generator, dtype=v.dtype)
    action = torch.rand(batch, 10, generator=generator, dtype=x.dtype) * 2 - 1
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, v, scene.free)
    objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass, action, anchor=x.clone())
    terms[0].anchor = objective.anchor
    probe = x + 1e-4 * torch.randn(x.shape, generator=generator, dtype=x.dtype)
    return scene, objective, probe


# (batch, laid out batch-last): the CPU lays out every batch batch-last, a GPU small ones per element;
# a batch of `HOST_CODE_MIN_BATCH` also runs C++ host code
BATCH = compiled.HOST_CODE_MIN_BATCH
LAYOUTS = [(2, False), (2, True), (BATCH, True)]


@pytest.fixture(params=LAYOUTS, ids=lambda case: f"{case[0]}-{'batch-last' if case[1] else 'per-element'}")
def batch_layout(request, monkeypatch) -> tuple[int, bool]:
    """(batch, laid out batch-last) of `LAYOUTS`, the layout in force for the test."""
    batch, batch_last = request.param
    if not batch_last:
        lay_out_per_element(monkeypatch)
    return batch, batch_last


def test_compiled_energy_gradient_and_dense_hessian_equal_the_eager_ones(batch_layout: tuple[int, bool]):
    # a batch laid out batch-last (with the body's viscosity) evaluates its element terms batch-last
    # (`batch_last_energy_and_forces`)
    batch, batch_last = batch_layout
    _, objective, x = _worm_objective(batch=batch, viscosity=batch_last)
    assert any(isinstance(term, LaggedFriction) for term in objective.terms)  # every kind of term
    energy, gradient = objective.energy_and_gradient(x)
    eager_energy = objective.energy(x)
    dense = objective.hessian(x).dense(x)
    objective.compiled = True
    compiled_energy, compiled_gradient = objective.energy_and_gradient(x)
    # a batch of `HOST_CODE_MIN_BATCH` runs the function compiled with C++ host code
    assert ("energy_and_gradient", "cpu", batch >= compiled.HOST_CODE_MIN_BATCH) in compiled._COMPILED
    assert torch.allclose(compiled_energy, energy, rtol=1e-12, atol=0)
    assert torch.allclose(objective.energy(x), eager_energy, rtol=1e-12, atol=0)
    assert torch.allclose(compiled_gradient, gradient, rtol=0, atol=1e-9 * float(gradient.abs().max()))
    compiled_dense = objective.dense_hessian(x)
    assert torch.allclose(compiled_dense, dense, rtol=0, atol=1e-9 * float(dense.abs().max()))


def test_the_compiled_line_trial_equals_the_eager_one_and_refuses_an_inadmissible_start(
    batch_layout: tuple[int, bool]
):
    # the first trial of a line search: CCD-limited step, energy, gradient, slopes and residual
    batch, batch_last = batch_layout
    _, objective, x = _worm_objective(batch=batch, viscosity=batch_last)
    x = x + torch.tensor([0.0, 1e-3, 0.0], dtype=x.dtype)  # the probe's noise put some vertices below
    energy, gradient = objective.energy_and_gradient(x)
    direction = -1e-3 * gradient / gradient.abs().amax()
    direction[:, :, 1] -= 0.02  # downwards, into the ground: the step limit binds
    judging = (_judge, (energy,))
    eager = objective.trial(x, direction, gradient, *judging)
    assert bool((eager.step < 1).all())
    assert torch.equal(eager.step, objective.max_step(x, direction))
    objective.compiled = True
    fast = objective.trial(x, direction, gradient, *judging)
    for name in ("step", "x", "energy", "gradient", "slope", "trial_slope", "residual"):
        value, reference = getattr(fast, name), getattr(eager, name)
        assert torch.allclose(value, reference, rtol=1e-10, atol=1e-9 * float(reference.abs().max())), name
    # the caller's judgement of the trial, evaluated in the same call: the energy's change there
    assert torch.allclose(fast.verdict[0], fast.energy - energy, rtol=1e-9, atol=0)
    assert torch.allclose(eager.verdict[0], eager.energy - energy, rtol=1e-9, atol=0)
    # a batch evaluated batch-last also gives the friction's curvature hints of an iteration ending
    # at the trial, as the term itself marks them; eagerly and element-major, the solver asks the term
    assert eager.hints is None
    if not batch_last:
        assert fast.hints is None
    else:
        hinting = [term for term in objective.terms if term.has_curvature_hint]
        assert len(hinting) == len(fast.hints) == 1
        assert torch.equal(fast.hints[0], hinting[0].curvature_hint(x, fast.x))
    inside = x.clone()
    inside[1, 3, 1] = -1e-3  # one vertex below the ground, in the second entry only
    with pytest.raises(ValueError, match=r"not admissible: vertices \[3\]"):
        objective.trial(inside, direction, gradient, *judging)


def _judge(step, slope, trial_energy, trial_slope, energy):
    # a line search's judgement of a trial (`Objective.trial`'s `judge`): here, E's change
    return (trial_energy - energy,)


@pytest.mark.parametrize("split", [False, True])
def test_cut_back_candidates_stop_short_of_the_ground_compiled_as_eagerly(split, monkeypatch):
    # the warm start's choice: each candidate cut back towards x_n to the CCD-safe fraction, with E;
    # compiled in one call, or (`split`, a large batch's way) the cuts in one and each energy apart
    called = []
    original_call = compiled.call

    def recorded(name, *arguments, **keywords):  # noqa: ANN001, ANN002, ANN003, ANN202
        called.append(name)
        return original_call(name, *arguments, **keywords)

    monkeypatch.setattr(compiled, "call", recorded)
    if split:
        monkeypatch.setattr(compiled, "CUT_BACK_SPLIT_MIN_ROWS", 1)
    _, objective, x = _worm_objective(batch=2)
    origin = x + torch.tensor([0.0, 1e-3, 0.0], dtype=x.dtype)
    lowest = origin[..., 1].amin(dim=-1)
    down = origin - torch.tensor([0.0, 5e-3, 0.0], dtype=x.dtype)  # through the ground
    up = origin + torch.tensor([0.0, 1e-3, 0.0], dtype=x.dtype)  # free: taken whole
    cuts, energies = objective.cut_back(origin, [down, up])
    fraction = CCD_SAFETY * lowest / 5e-3  # of the way down, where the lowest vertex keeps 20 % of its gap
    assert torch.allclose(cuts[0], origin + fraction[:, None, None] * (down - origin), rtol=0, atol=1e-15)
    assert torch.equal(cuts[1], up)
    for position, energy in zip((origin, *cuts), energies, strict=True):
        assert torch.allclose(energy, objective.energy(position), rtol=1e-12, atol=0)
    objective.compiled = True
    fast_cuts, fast_energies = objective.cut_back(origin, [down, up])
    assert called == (["cut_targets"] + ["energy"] * 3 if split else ["cut_back"])
    assert torch.allclose(fast_cuts, cuts, rtol=0, atol=1e-15)
    assert torch.allclose(fast_energies, energies, rtol=1e-10, atol=0)
    inside = origin.clone()
    inside[0, 7, 1] = -1e-4
    with pytest.raises(ValueError, match=r"not admissible: vertices \[7\]"):
        objective.cut_back(inside, [down, up])


def test_scenes_that_differ_only_in_a_terms_float_are_each_evaluated_with_their_own():
    # the ground's d̂ is a float attribute of a term: each value gets graphs of its own. Dynamo's
    # default makes a float a graph input once it has met a second value, and in torch 2.13 such a
    # graph kept the first value in some operations: A's barrier energy came back with B's d̂ (4e-4
    # relative), so two compiled envs with different grounds in one process failed their solves
    def objective(d_hat: float) -> tuple[Objective, torch.Tensor]:
        scene = load_creature("worm").scene(1 / 60, 0.8, barrier_distance=d_hat)
        state = resting_state(scene).reshape(1, -1).expand(2, -1)
        x, v = scene.split_state(state)
        terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, v, scene.free)
        built = Objective(terms, scene.free, scene.dt / scene.vertex_mass, None, anchor=x.clone())
        terms[0].anchor = built.anchor
        # vertices from d̂/2 up (the second entry 0.2 mm higher): some lie between the d̂ values,
        # inside one barrier's range and outside another's
        x = x.clone()
        x[1, :, 1] += 2e-4
        return built, x

    for d_hat in (9e-4, 3e-4, 9e-4):
        built, x = objective(d_hat)
        energy, gradient = built.energy_and_gradient(x)
        built.compiled = True
        compiled_energy, compiled_gradient = built.energy_and_gradient(x)
        assert torch.allclose(compiled_energy, energy, rtol=1e-12, atol=0), d_hat
        assert torch.allclose(compiled_gradient, gradient, rtol=0, atol=1e-9 * float(gradient.abs().max()))


def test_the_compiled_dense_hessian_eliminates_fixed_dofs_like_the_assembly():
    scene = es.Scene(small_box(3), dt=1 / 60)
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.fix([0, 1, 2])
    x = scene.rest_positions[None] + 0.01 * torch.randn(1, scene.num_vertices, 3, dtype=torch.float64)
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, 0 * x, scene.free)
    objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass)
    dense = objective.hessian(x).dense(x)
    objective.compiled = True
    assert torch.allclose(objective.dense_hessian(x), dense, rtol=0, atol=1e-9 * float(dense.abs().max()))
    assert torch.equal(objective.dense_hessian(x)[0, 0], torch.eye(scene.num_vertices * 3, dtype=x.dtype)[0])


def _pinned_worm_objective(
    pinned: bool, batch: int = 2, viscosity: bool = False
) -> tuple[es.Scene, Objective, torch.Tensor]:
    """`_worm_objective` of `batch` entries (with the body's `viscosity`), with vertices 0, 5 and 77
    fixed where `pinned`."""
    scene, objective, x = _worm_objective(batch=batch, viscosity=viscosity)
    if pinned:
        free = scene.free.clone()
        free[[0, 5, 77]] = False
        objective.free = free
    return scene, objective, x


def _without_corner(bands: torch.Tensor) -> torch.Tensor:
    # band storage `[B, N, u + 1]` with the corner slots LAPACK never reads (j + r ≥ N) zeroed
    size, width = bands.shape[1], bands.shape[2]
    return bands.masked_fill(torch.arange(size)[:, None] + torch.arange(width) >= size, 0.0)


@pytest.mark.parametrize("pinned", [False, True])
def test_the_compiled_band_hessian_equals_the_dense_one_in_band_storage(
    pinned: bool, batch_layout: tuple[int, bool]
):
    # assembled straight into band storage: the muscle and elastic blocks of the same elements are
    # summed before their scatter, so are the barrier's and friction's; fixed DOFs are eliminated.
    # Batch-last, from the batch-last entries (`energysim.fem.hessian_entries`)
    batch, batch_last = batch_layout
    scene, objective, x = _pinned_worm_objective(pinned, batch, viscosity=batch_last)
    layout = level_layout_of(objective.element_groups(), x)
    dense = objective.hessian(x).dense(x)
    objective.compiled = True
    bands = objective.band_hessian(x, layout)
    expected = _without_corner(dense.reshape(batch, -1)[:, layout.band_entries])
    assert torch.allclose(_without_corner(bands), expected, rtol=0, atol=1e-9 * float(dense.abs().max()))
    if pinned:
        # a pinned DOF's column holds the identity's: 1 on the diagonal, 0 below it
        dof = int(layout.band_position[5 * 3 + 1])
        assert float(bands[0, dof, 0]) == 1.0 and float(bands[0, dof, 1:].abs().max()) == 0.0
        # another pinned set on the same layout: the cached elimination follows the set, not the layout
        free = scene.free.clone()
        free[[3, 9]] = False
        objective.free = free
        bands = objective.band_hessian(x, layout)
        objective.compiled = False
        dense = objective.hessian(x).dense(x)
        expected = _without_corner(dense.reshape(batch, -1)[:, layout.band_entries])
        assert torch.allclose(_without_corner(bands), expected, rtol=0, atol=1e-9 * float(dense.abs().max()))


def test_the_constant_hessian_part_is_assembled_once_and_serves_every_later_x(batch_layout: tuple[int, bool]):
    # the inertia and the lagged viscosity (`has_constant_hessian`) are assembled at the first call
    # and kept; later calls at other positions add the other terms to a copy: each result equals
    # the eager Hessian at its own x, in band and in dense storage
    batch, batch_last = batch_layout
    _, objective, x = _worm_objective(batch=batch, viscosity=True)
    assert {type(term).__name__ for term in objective.terms if term.has_constant_hessian} == {
        "Inertia",
        "LaggedViscosity",
    }
    layout = level_layout_of(objective.element_groups(), x)
    generator = torch.Generator().manual_seed(1)
    positions = [x, x + 2e-4 * torch.randn(x.shape, generator=generator, dtype=x.dtype), x]
    expected = []
    for y in positions:
        expected.append(objective.hessian(y).dense(y))
    objective.compiled = True
    for y, dense in zip(positions, expected, strict=True):
        tolerance = 1e-9 * float(dense.abs().max())
        bands = objective.band_hessian(y, layout)
        reference = _without_corner(dense.reshape(batch, -1)[:, layout.band_entries])
        assert torch.allclose(_without_corner(bands), reference, rtol=0, atol=tolerance)
        assert torch.allclose(objective.dense_hessian(y), dense, rtol=0, atol=tolerance)
    storages = [key[0] for key in objective._constant_hessians if key[0] in ("band", "dense", "levels")]
    assert sorted(storages) == ["band", "dense"]  # one kept part per storage, whatever x
    # the factorisation may overwrite what it is given: the kept part is a copy's source, never returned
    bands.zero_()
    again = objective.band_hessian(x, layout)
    reference = _without_corner(expected[0].reshape(batch, -1)[:, layout.band_entries])
    tolerance = 1e-9 * float(expected[0].abs().max())
    assert torch.allclose(_without_corner(again), reference, rtol=0, atol=tolerance)


@pytest.mark.parametrize(
    ("batch", "rows", "small_per_element"),
    [(8, [6, 1, 5], True), (8, [6, 1, 5], False), (10, [0, 2, 3, 4, 5, 7, 8, 9], False)],
)
def test_a_subset_objective_slices_the_constant_hessian_part_from_its_parent(
    batch: int, rows: list[int], small_per_element: bool, monkeypatch
):
    # a solver's objective of the rows still iterating (`rows_of`) takes the inertia's and the lagged
    # viscosity's part from its parent's storage, and its Hessian is the eager one of those rows at
    # their positions: from a batch-last parent into batch-last rows, and, with a GPU's rule for small
    # batches (`small_per_element`), into 3 rows laid out per element
    if small_per_element:
        gpu_rule = batch_last.OTHER_DEVICES_BATCH_LAST_MIN_BATCH
        monkeypatch.setitem(batch_last.BATCH_LAST_MIN_BATCH, "cpu", gpu_rule)
    scene, objective, x = _worm_objective(batch=batch, viscosity=True)
    layout = level_layout_of(objective.element_groups(), x)
    objective.compiled = True
    objective.band_hessian(x, layout)
    entries = torch.tensor(rows)
    part = rows_of(objective, scene.terms, entries)
    assert part is not None
    names = []
    original = compiled.call
    monkeypatch.setattr(
        compiled_hessian,
        "call",
        lambda name, *arguments, **options: names.append(name) or original(name, *arguments, **options),
    )
    generator = torch.Generator().manual_seed(2)
    y = x[entries] + 1e-4 * torch.randn(x[entries].shape, generator=generator, dtype=x.dtype)
    part.compiled = True
    bands = part.band_hessian(y, layout)
    assert not any(name.startswith("constant_") for name in names) and names
    part.compiled = False
    dense = part.hessian(y).dense(y)
    reference = _without_corner(dense.reshape(len(rows), -1)[:, layout.band_entries])
    assert torch.allclose(_without_corner(bands), reference, rtol=0, atol=1e-9 * float(dense.abs().max()))


def test_a_subset_objective_takes_the_float32_copies_of_the_scene_terms_from_its_parent(monkeypatch):
    # with float32 Hessians the translation-invariant terms are evaluated from float32 copies; the
    # scene's terms serve every subset of a solve as they are, so a subset uses its parent's copies,
    # and its Hessian is still the eager one of its rows to float32's precision
    scene, objective, x = _worm_objective(batch=10, viscosity=True)
    layout = level_layout_of(objective.element_groups(), x)
    objective.compiled = True
    objective.band_hessian(x, layout, single=True)
    copied = []
    original = EnergyTerm.in_precision
    monkeypatch.setattr(
        EnergyTerm, "in_precision", lambda term, dtype: copied.append(term) or original(term, dtype)
    )
    entries = torch.tensor([0, 2, 3, 4, 5, 7, 8, 9])
    part = rows_of(objective, scene.terms, entries)
    generator = torch.Generator().manual_seed(3)
    y = x[entries] + 1e-4 * torch.randn(x[entries].shape, generator=generator, dtype=x.dtype)
    part.compiled = True
    bands = part.band_hessian(y, layout, single=True)
    assert copied == []
    assert bands.dtype == torch.float32
    part.compiled = False
    dense = part.hessian(y).dense(y)
    reference = _without_corner(dense.reshape(len(entries), -1)[:, layout.band_entries])
    tolerance = 1e-5 * float(dense.abs().max())
    assert torch.allclose(_without_corner(bands).double(), reference, rtol=0, atol=tolerance)


def test_the_terms_declared_constant_have_the_same_hessian_everywhere():
    # `has_constant_hessian` is what lets the part be kept: checked by autograd at two distant states
    _, objective, x = _worm_objective(batch=1, viscosity=True)
    generator = torch.Generator().manual_seed(2)
    other = x + 1e-2 * torch.randn(x.shape, generator=generator, dtype=x.dtype)
    for term in objective.terms:
        if not term.has_constant_hessian:
            continue

        def energy(y: torch.Tensor, term=term) -> torch.Tensor:
            return term(y.reshape(x.shape), objective.action).sum()

        first = torch.autograd.functional.hessian(energy, x.reshape(-1))
        second = torch.autograd.functional.hessian(energy, other.reshape(-1))
        name, tolerance = type(term).__name__, 1e-9 * float(first.abs().max())
        assert tolerance > 0, name
        assert torch.allclose(first, second, rtol=0, atol=tolerance), name


def _padded_levels(dense: torch.Tensor, layout) -> tuple[torch.Tensor, torch.Tensor]:
    # the level blocks read off dense matrices `[B, N, N]`: each DOF at its padded slot, identity
    # rows for the padding, then the diagonal and sub-diagonal S×S blocks
    batch, levels, size = dense.shape[0], layout.num_levels, layout.level_size
    padded = torch.eye(levels * size, dtype=dense.dtype).repeat(batch, 1, 1)
    slots = layout.dof_slots
    padded[:, slots[:, None], slots[None, :]] = dense
    blocks = padded.reshape(batch, levels, size, levels, size)
    diagonal = torch.stack([blocks[:, k, :, k] for k in range(levels)], dim=1)
    lower = torch.stack([blocks[:, k + 1, :, k] for k in range(levels - 1)], dim=1)
    return diagonal, lower


@pytest.mark.parametrize("pinned", [False, True])
def test_the_compiled_level_hessian_equals_the_dense_one_in_level_blocks(pinned: bool):
    # assembled straight into the block-tridiagonal solve's level blocks (its path on a GPU): the
    # worm's levels are padded (not all hold S DOFs), and fixed DOFs are eliminated
    _, objective, x = _pinned_worm_objective(pinned)
    layout = level_layout_of(objective.element_groups(), x)
    assert layout.num_levels * layout.level_size > x.shape[1] * 3  # some padding
    dense = objective.hessian(x).dense(x)
    objective.compiled = True
    diagonal, lower = objective.level_hessian(x, layout)
    expected_diagonal, expected_lower = _padded_levels(dense, layout)
    tolerance = 1e-9 * float(dense.abs().max())
    assert torch.allclose(diagonal, expected_diagonal, rtol=0, atol=tolerance)
    assert torch.allclose(lower, expected_lower, rtol=0, atol=tolerance)
    if pinned:
        assert float(dense[0, 5 * 3 + 1, 5 * 3 + 1]) == 1.0  # the dense one's identity row, matched


def test_a_compiled_level_solve_takes_the_steps_of_the_eager_one():
    # `direct="levels"` compiled (the batched path on a GPU, here forced on the CPU): the Newton
    # directions come from the compiled level blocks, and two steps of 2 worms under random
    # activations land where the eager level solve lands, with the same iterations
    from energysim.linalg.linear_solve import choose

    scene = load_creature("worm").scene(1 / 60, 0.8)
    state = resting_state(scene).reshape(1, -1).expand(2, -1).clone()
    generator = torch.Generator().manual_seed(1)
    actions = torch.rand(2, 2, 10, generator=generator, dtype=state.dtype) * 2 - 1
    results = {}
    for compile_flag in (False, True):
        solver = es.NewtonCG(tol=1e-8, direct="levels", indefinite="shift", compile=compile_flag)
        current, iterations = state, []
        for action in actions:
            result = es.step(scene, current, action=action, solver=solver)
            assert result.stats.converged
            current = result.state
            iterations.append(result.stats.iterations)
        results[compile_flag] = (current, iterations)
    assert results[True][1] == results[False][1]
    assert torch.allclose(results[True][0], results[False][0], rtol=0, atol=1e-9)
    # asked for, the compiled levels are planned; on the CPU "auto" keeps the compiled band solve
    _, objective, x = _worm_objective(batch=3)
    plan = choose(objective.element_groups(), x, method="levels", compiled_max_dofs=5000)
    assert plan.method == "levels" and plan.compiled and plan.layout is not None
    assert choose(objective.element_groups(), x, compiled_max_dofs=5000).method == "banded"


def test_the_compiled_band_solve_shifts_an_indefinite_hessian_as_the_eager_one():
    # `indefinite="shift"`: the compiled band path keeps H to factorise H + τ|diag H| again. Full
    # random activations at rest make the worm's H indefinite
    scene, objective, x = _worm_objective(batch=2)
    dense = objective.hessian(x).dense(x)
    assert torch.linalg.cholesky_ex(dense).info.ne(0).tolist() == [True, True]
    _, gradient = objective.energy_and_gradient(x)
    wanted = torch.ones(2, dtype=torch.bool)
    eager, eager_solved = es.NewtonCG(direct="banded", indefinite="shift")._direct(
        objective.hessian(x), -gradient, x, wanted
    )
    objective.compiled = True
    solver = es.NewtonCG(direct="banded", indefinite="shift", compile=True)
    direction, solved = solver._compiled_direct(objective, -gradient, x, wanted)
    assert solved.tolist() == eager_solved.tolist() == [True, True]
    error = (direction - eager).flatten(1).norm(dim=1) / eager.flatten(1).norm(dim=1)
    assert float(error.max()) < 1e-8
    assert bool(((direction * gradient).sum(dim=(1, 2)) < 0).all())


@pytest.mark.skipif(native.library() is None, reason="no C band kernels on this machine")
@pytest.mark.parametrize(("batch", "batch_last"), [(4, False), (4, True), (BATCH, True)])
def test_float32_band_factors_give_the_float64_newton_step_to_float32_accuracy(
    batch: int, batch_last: bool, monkeypatch
):
    # `factor_precision="single"`: the Hessian and its factorisation are float32 (the Hessian
    # per element or batch-last); the shifted retries of the indefinite entries pick the same τ,
    # and the steps stay downhill
    if not batch_last:
        lay_out_per_element(monkeypatch)
    _, objective, x = _worm_objective(batch=batch)
    objective.compiled = True
    _, gradient = objective.energy_and_gradient(x)
    wanted = torch.ones(batch, dtype=torch.bool)
    directions = {}
    for precision in ("double", "single"):
        solver = es.NewtonCG(direct="banded", indefinite="shift", compile=True, factor_precision=precision)
        directions[precision], solved = solver._compiled_direct(objective, -gradient, x, wanted)
        assert solved.tolist() == [True] * batch
    double, single = directions["double"], directions["single"]
    error = (single - double).flatten(1).norm(dim=1) / double.flatten(1).norm(dim=1)
    assert float(error.max()) < 1e-3
    assert bool(((single * gradient).sum(dim=(1, 2)) < 0).all())


def test_a_compiled_walk_takes_the_same_steps_as_an_eager_one():
    # the worm's gait for 0.2 s, with the dense direct solve from the compiled Hessian
    scene = load_creature("worm").scene(1 / 60, 0.8)
    actions = [torch.sin(torch.arange(10, dtype=torch.float64) + 0.3 * k) for k in range(12)]
    runs = {}
    for compile_flag in (False, True):
        solver = es.NewtonCG(tol=1e-6, compile=compile_flag)
        state, iterations = resting_state(scene), []
        for action in actions:
            result = es.step(scene, state, action, solver=solver)
            state, iterations = result.state, [*iterations, result.stats.iterations]
        runs[compile_flag] = (state, iterations)
    assert runs[True][1] == runs[False][1]
    assert torch.allclose(runs[True][0], runs[False][0], rtol=0, atol=1e-10)


def test_a_compiled_tr_bdf2_swing_takes_the_same_steps_as_an_eager_one():
    # TR-BDF2's start acceleration and its energy check evaluate through compiled functions too;
    # a box pinned at one end swings under gravity, so the energy check compares real energies
    mesh = small_box(3)
    runs = {}
    for compile_flag in (False, True):
        scene = es.Scene(mesh, dt=1 / 48, integrator="tr_bdf2")
        scene.add(es.NeoHookean(1e5, 0.3))
        scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9))
        solver = es.NewtonCG(tol=1e-8, compile=compile_flag)
        state, iterations = scene.initial_state(), []
        for _ in range(6):
            result = es.step(scene, state, solver=solver)
            state, iterations = result.state, [*iterations, result.stats.iterations]
        runs[compile_flag] = (state, iterations)
    assert runs[True][1] == runs[False][1]
    assert torch.allclose(runs[True][0], runs[False][0], rtol=0, atol=1e-10)
    assert float(runs[True][0].abs().max()) > 0.01  # it did swing


def test_compiled_leapfrog_substeps_equal_the_eager_ones_and_blow_up_as_clearly():
    # the compiled chunks (8 unrolled substeps, then the rest) with the element-major neo-Hookean
    # gradient, against the eager loop on the same swinging box; and past the Courant limit the
    # compiled path raises the same error
    mesh = small_box(3)
    runs = {}
    for compile_flag in (False, True):
        scene = es.Scene(mesh, dt=1 / 24, integrator="leapfrog", substeps=10)
        scene.add(es.NeoHookean(1e4, 0.3))
        scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9))
        solver = es.NewtonCG(compile=compile_flag)
        state = scene.initial_state()
        for _ in range(4):
            state = es.step(scene, state, solver=solver).state
        runs[compile_flag] = state
        scene.dt, scene.substeps = 0.5, 1
        with pytest.raises(es.InstabilityError, match="Courant limit"):
            es.step(scene, state, solver=solver)
    assert torch.allclose(runs[True], runs[False], rtol=0, atol=1e-11)
    assert float(runs[True].abs().max()) > 0.05  # it did swing


def test_the_compiled_energy_check_sums_the_same_energies_as_the_eager_one():
    # every kind of scene term (elastic, muscles, gravity, the ground's barrier), each at x itself
    scene, objective, x = _worm_objective(batch=2)
    x = x + torch.tensor([0.0, 1e-3, 0.0], dtype=x.dtype)  # the probe's noise put some vertices below
    energies = state_energies
    v = torch.randn(x.shape, dtype=x.dtype)
    eager = energies(scene, x, v, objective.action, compiled=False)
    fast = energies(scene, x, v, objective.action, compiled=True)
    for a, b in zip(fast, eager, strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=0)
    assert float(eager[1].min()) < float(eager[2].min())  # gravity counts in the scale, not in motion


def test_a_new_time_step_compiles_no_new_graph():
    # h reaches the compiled functions as data (the inertia's M/h², friction's ε_v h): as floats it
    # was baked into each graph, one per h and per TR-BDF2 stage, and past torch.compile's limit of
    # 8 graphs per function the evaluations silently fell back to eager
    scene = load_creature("worm").scene(1 / 60, 0.8)
    solver = es.NewtonCG(tol=1e-6, compile=True)
    action = torch.sin(torch.arange(10, dtype=torch.float64))
    state = es.step(scene, resting_state(scene), action, solver=solver).state
    counters = torch._dynamo.utils.counters
    graphs = counters["stats"]["unique_graphs"]
    assert graphs > 0
    for dt in (1 / 50, 1 / 75, 1 / 100, 1 / 125, 1 / 150):
        scene.dt = dt
        result = es.step(scene, state, action, solver=solver)
        assert result.stats.converged
        state = result.state
    assert counters["stats"]["unique_graphs"] == graphs


class _PlainSpring(es.EnergyTerm):
    """A term with no closed forms: only its energy, for autograd."""

    def forward(self, x: torch.Tensor, action: torch.Tensor | None = None) -> torch.Tensor:
        return 50.0 * ((x[:, 0] - x[:, 1]).norm(dim=-1) - 1.0) ** 2


def test_terms_without_closed_forms_are_evaluated_eagerly():
    scene = es.Scene(small_box(3), dt=1 / 60, gravity=None)
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.add(_PlainSpring())
    velocities = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
    velocities[0, 0] = -1.0
    state = scene.initial_state(velocities=velocities)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no compile attempt, so no warning either
        compiled_step = es.step(scene, state, solver=es.NewtonCG(tol=1e-9, compile=True)).state
    eager_step = es.step(scene, state, solver=es.NewtonCG(tol=1e-9)).state
    assert torch.allclose(compiled_step, eager_step, rtol=0, atol=1e-12)


def test_a_function_that_fails_to_compile_warns_and_falls_back_to_eager(monkeypatch):
    def broken(*args: object) -> None:
        raise RuntimeError("no C++ compiler found")

    monkeypatch.setattr(compiled, "_COMPILED", {("energy", "cpu", False): broken})
    monkeypatch.setattr(compiled, "_FAILED", set())
    _, objective, x = _worm_objective()
    eager = objective.energy(x)
    objective.compiled = True
    with pytest.warns(RuntimeWarning, match="could not compile the objective's energy .*no C\\+\\+ compiler"):
        assert torch.equal(objective.energy(x), eager)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once only
        assert torch.equal(objective.energy(x), eager)


def test_a_compiled_band_hessian_takes_the_direct_solve_past_the_eager_limit():
    # 891 DOFs: over the 600 an eagerly assembled direct solve takes, so eagerly CG solves; compiled,
    # the Hessian goes straight into band storage and the band Cholesky solves (no Hessian-vector
    # products). Both stop at the same residual, so the steps agree to that tolerance.
    mesh = es.TetMesh.box(size=(1.2, 0.2, 0.2), cells=(32, 2, 2))
    assert 600 < mesh.num_vertices * 3 <= 5000
    scene = es.Scene(mesh, dt=1 / 60)
    scene.add(es.NeoHookean(1e5, 0.3))
    scene.fix(torch.nonzero(mesh.vertices[:, 0] < 1e-9))
    results = {}
    for compile_flag in (False, True):
        solver = es.NewtonCG(tol=1e-9, compile=compile_flag)
        assert solver.direct_limit(compiled_band=True) == 5000 and solver.direct_limit() == 600
        state = scene.initial_state()
        hvps = 0
        for _ in range(3):
            result = es.step(scene, state, solver=solver)
            state, hvps = result.state, hvps + result.stats.hvp_evals
            assert result.stats.converged
        results[compile_flag] = (state, hvps)
    assert results[False][1] > 0 and results[True][1] == 0
    assert torch.allclose(results[True][0], results[False][0], rtol=0, atol=1e-9)
    # an explicit limit holds for every path
    assert es.NewtonCG(direct_max_dofs=0, compile=True).direct_limit(compiled_band=True) == 0
    with pytest.raises(ValueError, match="direct_max_dofs"):
        es.NewtonCG(direct_max_dofs=-1)


def test_small_matmul_traced_by_the_compiler_equals_the_matrix_product():
    # the broadcast form the compiler fuses, against `@`, with a batch broadcast as the Hessian uses it
    from energysim.linalg.small_matmul import small_matmul

    generator = torch.Generator().manual_seed(0)
    strain_map_t = torch.randn(5, 12, 9, generator=generator, dtype=torch.float64)
    stiffness = torch.randn(2, 5, 9, 9, generator=generator, dtype=torch.float64)
    strain_map = strain_map_t.transpose(-1, -2)
    expected = strain_map_t @ (stiffness @ strain_map)
    eager = small_matmul(strain_map_t, small_matmul(stiffness, strain_map))
    def fused(a: torch.Tensor, s: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return small_matmul(a, small_matmul(s, b, fuse_on_cpu=True), fuse_on_cpu=True)

    traced = torch.compile(fused, fullgraph=True)
    result = traced(strain_map_t, stiffness, strain_map)
    assert torch.equal(eager, expected)
    assert result.shape == expected.shape == (2, 5, 12, 12)
    assert torch.allclose(result, expected, rtol=0, atol=1e-12 * float(expected.abs().max()))


def test_kept_factorisations_hand_an_indefinite_hessian_to_the_shifted_solve():
    # `reuse_factorization`: a new factor that fails (the worm's H is indefinite here) keeps no
    # factor for that entry and leaves the iteration to the usual path, whose shifted solve it equals
    _, objective, x = _worm_objective(batch=2)
    objective.compiled = True
    _, gradient = objective.energy_and_gradient(x)
    wanted = torch.ones(2, dtype=torch.bool)
    plain = es.NewtonCG(direct="banded", indefinite="shift", compile=True)
    expected, expected_solved = plain._compiled_direct(objective, -gradient, x, wanted)
    kept = es.NewtonCG(direct="banded", indefinite="shift", compile=True, reuse_factorization=0.5)
    direction, solved = kept._compiled_direct(objective, -gradient, x, wanted)
    assert solved.tolist() == expected_solved.tolist() == [True, True]
    assert torch.equal(direction, expected)
    ((_, factors),) = kept._factors._factors.values()
    assert factors == [None, None]
