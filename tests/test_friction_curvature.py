"""The friction's curvature hint: where a Newton iteration reversed a sliding vertex's slip, its next
Hessian block is that of the quadratic majorizing the friction (f1(y)/y along the slip as well as
across it). Checked as mathematics (the quadratic lies above f0 and touches it), as a rule (which
vertices it marks), and as a solve (the analytic rest of a vertex pulled back into its static zone,
and a tumbling drop that ends where the exact blocks end)."""

from __future__ import annotations

import math

import pytest
import torch

import energysim as es
from energysim.contact.friction import LaggedFriction, mollified_slip, mollified_slip_gradient
from energysim.energies.inertia import Inertia
from energysim.objective.derivatives import autograd_element_hessian
from energysim.objective.objective import Objective

SMOOTHING = 1e-4  # ε = ε_v h, in m


def one_vertex_friction(slip_weight: float = 10.0, previous: torch.Tensor | None = None) -> LaggedFriction:
    # one vertex on a ground of normal +y, μλ = `slip_weight` N
    return LaggedFriction(
        torch.tensor([[0]]),
        torch.zeros(1, 1, 3, dtype=torch.float64) if previous is None else previous,
        torch.tensor([[[0.0, 1.0, 0.0]]], dtype=torch.float64),
        torch.tensor([[slip_weight]], dtype=torch.float64),
        torch.tensor(1.0, dtype=torch.float64),
        SMOOTHING,
    )


@pytest.mark.parametrize("length", [1.5, 4.0, 30.0])
def test_the_majorized_block_bounds_the_friction_from_above_and_touches_it(length):
    # q(v) = f0(y) + f1(y)/(2y) (‖v‖² − y²) ≥ f0(‖v‖) for all v: f1(y)/y falls as y grows. Its
    # Hessian (f1/y) P is the marked block; the exact one, with no curvature along the slip, gives
    # a quadratic that falls below f0 where the slip turns back
    generator = torch.Generator().manual_seed(1)
    u0 = torch.tensor([length * SMOOTHING * 0.6, 0.0, length * SMOOTHING * 0.8], dtype=torch.float64)
    term = one_vertex_friction(1.0)
    x = u0.reshape(1, 1, 3)
    term.set_curvature_hint(torch.tensor([[True]]))
    majorized = term.element_hessian(x[:, term.element_vertices], None)[0, 0]
    term.set_curvature_hint(torch.tensor([[False]]))
    exact = term.element_hessian(x[:, term.element_vertices], None)[0, 0]
    torch.testing.assert_close(exact, autograd_element_hessian(term, x, None)[0, 0], rtol=1e-9, atol=1e-6)
    value, slope = mollified_slip(u0, SMOOTHING), mollified_slip_gradient(u0, SMOOTHING)
    # tangential points around u0, out to the far side of the static zone
    points = torch.randn(4000, 3, generator=generator, dtype=torch.float64) * 2 * u0.norm()
    points[:, 1] = 0.0
    points = torch.cat([points, -u0[None], (u0 * torch.linspace(-3, 3, 61, dtype=torch.float64)[:, None])])
    steps = points - u0
    friction = mollified_slip(points, SMOOTHING)

    def model(block):
        return value + steps @ slope + 0.5 * ((steps @ block) * steps).sum(dim=-1)

    assert bool((model(majorized) >= friction - 1e-15).all())
    assert float((model(exact) - friction).min()) < -0.5 * SMOOTHING  # the exact model dips below
    assert bool((torch.linalg.eigvalsh(majorized) > -1e-9).all())


def test_in_the_static_zone_a_marked_block_is_the_exact_one():
    term = one_vertex_friction()
    x = torch.tensor([[[0.3 * SMOOTHING, 0.0, 0.4 * SMOOTHING]]], dtype=torch.float64)
    term.set_curvature_hint(torch.tensor([[True]]))
    torch.testing.assert_close(
        term.element_hessian(x[:, term.element_vertices], None),
        autograd_element_hessian(term, x, None),
        rtol=1e-9,
        atol=1e-6,
    )


def test_the_hint_marks_the_vertices_whose_slip_turned_back_and_still_slides():
    # four vertices of one batch entry, each from a start slip to an end slip (along x)
    starts = torch.tensor([3.0, 3.0, 3.0, 0.5]) * SMOOTHING
    ends = torch.tensor([-2.0, 2.0, -0.5, -2.0]) * SMOOTHING
    previous_positions = torch.zeros(1, 4, 3, dtype=torch.float64)
    term = LaggedFriction(
        torch.arange(4)[:, None],
        previous_positions,
        torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(1, 4, 3),
        torch.ones(1, 4, dtype=torch.float64),
        torch.tensor(0.5, dtype=torch.float64),
        SMOOTHING,
    )
    previous = torch.zeros(1, 4, 3, dtype=torch.float64)
    current = torch.zeros(1, 4, 3, dtype=torch.float64)
    previous[0, :, 0], current[0, :, 0] = starts, ends
    # a move along the normal is no slip: it cannot mark a vertex
    current[0, :, 1] = 1e-3
    marks = term.curvature_hint(previous, current)
    # reversed and sliding; same direction; reversed into the static zone; from the static zone
    assert marks.tolist() == [[True, False, False, True]]
    assert not bool(term.majorized.any())  # asking records nothing
    term.set_curvature_hint(marks)
    assert term.rows(torch.tensor([0, 0])).majorized.tolist() == [marks[0].tolist()] * 2


def test_the_hint_marks_only_vertices_in_contact_and_follows_their_entries_and_rows():
    # two entries, friction on state vertices 3 and 1 of 4 (in that order); in entry 0 vertex 1 has no
    # normal force. Every slip reverses from 3ε to −2ε: only the vertices with friction are marked
    state_vertices = torch.tensor([[3], [1]])
    normal_force = torch.tensor([[1.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    previous_positions = torch.zeros(2, 2, 3, dtype=torch.float64)
    normals = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(2, 2, 3)
    friction = torch.tensor(0.5, dtype=torch.float64)
    term = LaggedFriction(state_vertices, previous_positions, normals, normal_force, friction, SMOOTHING)
    previous = torch.zeros(2, 4, 3, dtype=torch.float64)
    current = torch.zeros(2, 4, 3, dtype=torch.float64)
    previous[:, :, 0], current[:, :, 0] = 3.0 * SMOOTHING, -2.0 * SMOOTHING
    assert term.curvature_hint(previous, current).tolist() == [[True, False], [True, True]]
    # a batch's rows in another order mark as those entries did
    rows = term.rows(torch.tensor([1, 0]))
    assert rows.curvature_hint(previous[[1, 0]], current[[1, 0]]).tolist() == [[True, True], [True, False]]


def test_the_batch_last_hint_marks_what_the_hint_marks():
    # the compiled line-search trial's form (`batch_last_curvature_hint`, the batch innermost, every
    # vertex) against the term's own: random slips around ε, some reversed, some without normal force
    from energysim.objective.batch_last import curvature_hints

    generator = torch.Generator().manual_seed(4)
    batch, count, vertices = 9, 12, 15
    state_vertices = torch.randperm(vertices, generator=generator)[:count, None]
    normals = torch.nn.functional.normalize(
        torch.randn(batch, count, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    normal_force = torch.rand(batch, count, generator=generator, dtype=torch.float64)
    normal_force[normal_force < 0.3] = 0.0
    start = torch.randn(batch, count, 3, generator=generator, dtype=torch.float64)
    term = LaggedFriction(state_vertices, start, normals, normal_force, torch.tensor(0.4), SMOOTHING)
    previous = torch.randn(batch, vertices, 3, generator=generator, dtype=torch.float64)
    current = torch.randn(batch, vertices, 3, generator=generator, dtype=torch.float64)
    for state in (previous, current):  # slips of 0–4 ε from x_n
        scale = 4 * SMOOTHING * torch.rand(batch, count, 1, generator=generator, dtype=torch.float64)
        state[:, state_vertices[:, 0]] = start + scale * torch.nn.functional.normalize(
            state[:, state_vertices[:, 0]], dim=-1
        )
    expected = term.curvature_hint(previous, current)
    assert 0 < int(expected.sum()) < int((normal_force > 0).sum())  # some marked, not all
    (hint,) = curvature_hints([term], previous, current)
    assert torch.equal(hint, expected)


def test_a_vertex_pulled_back_into_its_static_zone_rests_where_the_force_balance_says():
    # inertia k = m/h² pulling towards a = 0.6 mm against μλ = 10 N (k a = 6 N < μλ): the vertex
    # sticks at the root below ε of k(u − a) + μλ(2u/ε − u²/ε²) = 0. From a start sliding 2–10 mm
    # away, Newton's exact model sends it through the static zone to slide the other way
    mass, dt, weight, target = 1.0, 0.01, 10.0, 0.6e-3
    stiffness = mass / dt**2
    a, b, c = weight / SMOOTHING**2, -(stiffness + 2 * weight / SMOOTHING), stiffness * target
    rest = (-b - math.sqrt(b * b - 4 * a * c)) / (2 * a)
    for start in (2e-3, -3e-3, 1e-2):
        friction = one_vertex_friction(weight)
        inertia = Inertia(
            torch.tensor([mass], dtype=torch.float64),
            dt,
            torch.tensor([[[target, 0.0, 0.0]]], dtype=torch.float64),
        )
        objective = Objective([inertia, friction], torch.tensor([True]), torch.tensor([dt / mass]))
        x0 = torch.tensor([[[start, 0.0, 0.0]]], dtype=torch.float64)
        result = es.NewtonCG(tol=1e-9).minimize(objective, x0)
        assert result.converged
        assert float(result.x[0, 0, 0]) == pytest.approx(rest, rel=1e-9)
        assert result.iterations <= 10


def test_a_tumbling_drop_with_friction_ends_where_the_exact_blocks_end_it_in_fewer_iterations():
    # a tilted cube thrown down and sideways onto μ = 0.5 ground: its corners reverse their slip as
    # it tumbles. The hint changes the path to each step's minimiser, not the minimiser.
    mesh = es.TetMesh.box(size=(0.2, 0.2, 0.2), cells=(2, 2, 2))
    angle = 0.3
    rotation = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0.0, 0.0, 1.0]],
        dtype=torch.float64,
    )
    centre = torch.tensor([0.1, 0.1, 0.1], dtype=torch.float64)
    x0 = (mesh.vertices - centre) @ rotation.T + centre + torch.tensor([0.0, 0.05, 0.0], dtype=torch.float64)

    def run(hint: bool) -> tuple[int, torch.Tensor]:
        scene = es.Scene(
            mesh, density=1000.0, dt=1 / 60, gravity=(0.0, -9.81, 0.0), solver=es.NewtonCG(tol=1e-6)
        )
        scene.add(es.NeoHookean(1e5, 0.3))
        scene.add(es.Ground(0.0, friction=0.5))
        state = scene.initial_state(x0, torch.tensor([1.0, -2.0, 0.0]).expand_as(x0))
        iterations = 0
        original = LaggedFriction.has_curvature_hint
        LaggedFriction.has_curvature_hint = hint
        try:
            for _ in range(60):
                result = es.step(scene, state)
                state, iterations = result.state, iterations + result.stats.iterations
        finally:
            LaggedFriction.has_curvature_hint = original
        return iterations, scene.split_state(state)[0]

    hinted, hinted_end = run(True)
    exact, exact_end = run(False)
    # each step is solved to 1e-6 m/s: the ends differ by the solves' errors, carried over 60 steps
    assert float((hinted_end - exact_end).abs().max()) < 1e-6
    assert hinted < exact


def test_a_row_that_backtracks_alone_gets_the_hint_of_where_its_search_ended():
    # four entries of one vertex, slipping +3ε from x_n. Entries 1–3 step to the inertia's anchor at
    # −2ε and take the step (their slip reversed and still slides: marked). Entry 0's direction is
    # 1000ε long; its anchor at +2.9ε, on the side it started from, is where its search must come back
    # to: it backtracks alone, and its mark is that of where it stopped (not reversed), not that of
    # the trial it refused (reversed far beyond ε). The compiled trial gives the others' marks
    from energysim.solvers.line_search import line_step

    batch, dt = 4, 0.01
    anchor = torch.zeros(batch, 1, 3, dtype=torch.float64)
    anchor[0, 0, 0], anchor[1:, 0, 0] = 2.9 * SMOOTHING, -2.0 * SMOOTHING
    weights = torch.full((batch, 1), 0.1, dtype=torch.float64)  # μλ, in N: the inertia dominates

    def objective_of(rows: torch.Tensor) -> Objective:
        inertia = Inertia(torch.tensor([1.0], dtype=torch.float64), dt, anchor[rows])
        friction = LaggedFriction(
            torch.tensor([[0]]),
            torch.zeros(len(rows), 1, 3, dtype=torch.float64),
            torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(len(rows), 1, 3),
            weights[rows],
            torch.tensor(1.0, dtype=torch.float64),
            SMOOTHING,
        )
        objective = Objective([inertia, friction], torch.tensor([True]), torch.tensor([dt]))
        objective.compiled = True
        return objective

    restricted = []

    def restrict(rows: torch.Tensor) -> Objective:
        restricted.append(rows.tolist())
        return objective_of(rows)

    objective = objective_of(torch.arange(batch))
    x = torch.zeros(batch, 1, 3, dtype=torch.float64)
    x[:, 0, 0] = 3.0 * SMOOTHING
    direction = torch.zeros_like(x)
    direction[0, 0, 0], direction[1:, 0, 0] = -1000.0 * SMOOTHING, -5.0 * SMOOTHING
    energy, gradient = objective.energy_and_gradient(x)
    result = line_step(objective, x, energy, gradient, direction, restrict=restrict)
    assert restricted == [[0]]
    assert 0 < float(result.step[0]) < 1e-3 and result.step[1:].tolist() == [1.0, 1.0, 1.0]
    friction = objective.terms[1]
    assert result.hints is not None
    (hint,) = result.hints
    assert torch.equal(hint, friction.curvature_hint(x, result.x))
    assert hint.tolist() == [[False], [True], [True], [True]]
