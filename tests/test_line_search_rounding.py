"""The line search's allowance for rounding on stiff, rotated bodies.

The neo-Hookean energy of a rotated element is a sum of terms of size μV|F − I|² that cancel, so at
E = 1e8 Pa the energy of a 0.2 m box carries a rounding noise of 1e-12 J (tilted by 0.5 rad) to 1e-10 J
(rotated by 2.4 rad), whatever the energy itself. A line search that allows only 64 ulps of the step's
objective (1e-16 J for such a drop) refuses steps that did decrease the energy and stalls above a
residual of 1e-5 m/s. These tests hold the solvers to that tolerance on such a body, and check that
what they accept is not a rise of the energy.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest
import torch

import energysim as es
from energysim.solvers.energy_rounding import NOISE_ALLOWANCE, energy_noise

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))
matrix = importlib.import_module("stability_matrix")
# the stability matrix's independent judges: the energy from every term's plain forward, the
# implicit-Euler residual recomputed by autograd
rotation, mechanical_energy, step_residual = matrix.rotation, matrix.mechanical_energy, matrix.step_residual

YOUNGS_MODULUS = 1e8  # Pa
POISSONS_RATIO = 0.3
SIZE = 0.2  # m
DENSITY = 1000.0  # kg/m³
DT = 1 / 60  # s
TOL = 1e-5  # m/s
ANGLES = (1.0, 2.0, 0.5)  # rad about x, then y, then z: far from any symmetry of the box
SHIFT = (3.0, 1.0, -2.0)  # m
GAP = 1e-3  # m between the lowest vertex and the ground at the start
SPEED = 1.0  # m/s downwards at the start
# Relative rounding allowed in the mechanical energy, a sum of terms of up to its magnitude: the
# elastic part alone is uncertain by ~1e-12 J against a magnitude of ~1 J.
ENERGY_ROUNDING = 1e-11


pytestmark = pytest.mark.usefixtures("one_thread")


def rotated_box() -> tuple[es.TetMesh, torch.Tensor]:
    """The box mesh and its rest shape rotated by `ANGLES` about its centre and moved by `SHIFT`, `[n, 3]`."""
    mesh = es.TetMesh.box(size=(SIZE,) * 3, cells=(2, 2, 2))
    centre = mesh.vertices.mean(dim=0)
    x = (mesh.vertices - centre) @ rotation(ANGLES).T + torch.tensor(SHIFT, dtype=torch.float64)
    return mesh, x


def landing() -> tuple[es.Scene, torch.Tensor]:
    """The stiff rotated box `GAP` above frictional ground, falling at `SPEED`: scene and state."""
    mesh, x = rotated_box()
    scene = es.Scene(mesh, density=DENSITY, dt=DT)
    scene.add(es.NeoHookean(YOUNGS_MODULUS, POISSONS_RATIO))
    scene.add(es.Ground(0.0, friction=0.5))
    x = x - torch.tensor([0.0, float(x[:, 1].min()) - GAP, 0.0], dtype=torch.float64)
    v = torch.tensor([0.0, -SPEED, 0.0], dtype=torch.float64).expand_as(x)
    return scene, scene.initial_state(x, v)


def test_the_measured_noise_covers_the_energy_of_a_rigid_rotation() -> None:
    # A rigidly moved body stores no elastic energy: what its computed energy holds is rounding alone.
    # At rest the terms are zero and so is the noise; rotated, they are of size μV|F − I|² and cancel.
    mesh, rotated = rotated_box()
    scene = es.Scene(mesh, density=DENSITY, dt=DT, gravity=None)
    elastic = es.NeoHookean(YOUNGS_MODULUS, POISSONS_RATIO)
    scene.add(elastic)
    objective = es.Objective(terms=[elastic], free=scene.free, residual_scale=DT / scene.vertex_mass)
    eps = torch.finfo(torch.float64).eps
    mu, lam = elastic.lame()
    moduli = float(eps * ((mu + lam) * elastic.rest_volume).sum())  # 1.7e-10 J

    rest = mesh.vertices[None]
    energy = objective.energy(rest)
    assert float(energy.abs()) == 0.0
    assert float(energy_noise(objective, rest, energy)) < 1e-6 * moduli

    x = rotated[None]
    energy = objective.energy(x)
    noise = float(energy_noise(objective, x, energy))
    # the computed energy, exactly 0, is off by 8e-11 J: of the order of eps Σ(μ + λ)V, and 1e13
    # times 64 ulps of itself ...
    assert float(energy.abs()) > 1e-3 * moduli
    # ... and the allowance built from the measured noise covers it
    assert float(energy.abs()) <= NOISE_ALLOWANCE * noise
    assert noise < 10 * moduli


@pytest.mark.parametrize(
    ("solver", "steps"),
    [
        (es.NewtonCG(tol=TOL, strict=True), 4),
        # one step: L-BFGS needs ~150 iterations for it, the next ones take 300 to 500
        (es.LBFGS(tol=TOL, max_iter=500, strict=True), 1),
    ],
    ids=["newton-cg", "lbfgs"],
)
def test_a_stiff_rotated_box_lands_with_every_step_converged(solver: es.Solver, steps: int) -> None:
    # With 64 ulps of |E| as the allowance, Newton–CG stalled at 9.5e-5 m/s in the third of these
    # steps and L-BFGS at 5.4e-3 m/s in the first (after 148 iterations).
    scene, state = landing()
    energy, _ = mechanical_energy(scene, state)
    for _ in range(steps):
        result = es.step(scene, state, solver=solver)  # strict: raises if the tolerance is not reached
        assert result.stats.converged and result.stats.residual < TOL
        residual = step_residual(scene, state, result.state)
        assert float(residual.abs().max()) < 1.01 * TOL
        # implicit Euler only dissipates; an inexact solve may gain at most its residual's work
        _, v = scene.split_state(result.state)
        work = float((scene.vertex_mass[:, None] * v[0] * residual).sum())
        new_energy, scale = mechanical_energy(scene, result.state)
        assert new_energy - energy <= abs(work) + ENERGY_ROUNDING * scale
        x, _ = scene.split_state(result.state)
        assert float(x[0, :, 1].min()) > 0.0  # above the ground
        state, energy = result.state, new_energy


class _Bowl(es.EnergyTerm):
    """E = ½ k ‖x‖², in J: a quadratic, on which one interpolation lands on the minimum exactly."""

    def forward(self, x: torch.Tensor, action: torch.Tensor | None = None) -> torch.Tensor:
        return 0.5 * 4.0 * (x * x).sum(dim=(-1, -2))


def test_backtracking_interpolates_a_far_too_long_step_down_to_the_minimum() -> None:
    # from x = 1 along d = −100: the minimum is at t = 0.01. Halving would stop at t = 1/64
    # (x = −0.56) after 6 refusals; the quadratic through E(0), E'(0), E(t) has its minimiser at
    # t = 0.01 exactly, reached in two safeguarded reductions (t/10 each)
    from energysim.objective.objective import Objective
    from energysim.solvers.line_search import backtracking_line_search

    x = torch.ones(1, 1, 1, dtype=torch.float64)
    objective = Objective([_Bowl()], torch.ones(1, dtype=torch.bool), torch.ones(1, dtype=torch.float64))
    energy, gradient = objective.energy_and_gradient(x)
    direction = -100.0 * torch.ones_like(x)
    no_noise = torch.zeros(1, dtype=torch.float64)  # nothing here is near rounding
    step, new_energy, _ = backtracking_line_search(
        objective, x, energy, gradient, direction, torch.ones(1, dtype=torch.float64), rounding=no_noise
    )
    assert float(step) == pytest.approx(0.01, rel=1e-12)
    assert float(new_energy) == pytest.approx(0.0, abs=1e-20)
    assert objective.energy_evals == 3  # t = 1, 0.1, 0.01


def test_one_solve_measures_the_noise_once_and_still_converges(monkeypatch: pytest.MonkeyPatch) -> None:
    # the noise is that of the energy's terms at the body's scale, which one solve's iterates share:
    # a measurement is handed from one line search to the next instead of being taken again, and
    # taken for the entries whose trial it may decide. Eight randomly driven worms: measured 3 times
    # in their sixth solve when each search measured anew, each time for the whole batch
    import numpy as np

    import energysim.solvers.energy_rounding as energy_rounding
    from energysim.envs.config import CreatureEnvConfig
    from energysim.envs.core import CreatureSimulation

    measured = []
    original = energy_rounding.energy_noise

    def counted(objective, x, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        measured.append(x.shape[0])  # the entries measured
        return original(objective, x, *args, **kwargs)

    monkeypatch.setattr(energy_rounding, "energy_noise", counted)
    simulation = CreatureSimulation(CreatureEnvConfig(creature="worm", solver_tol=1e-4))
    batch = 8
    state = simulation.reset([np.random.default_rng(i) for i in range(batch)])
    generator = torch.Generator().manual_seed(0)
    activation = None
    per_step = []
    for _ in range(6):
        command = torch.rand(batch, simulation.num_actuators, generator=generator, dtype=torch.float64)
        measured.clear()
        transition = simulation.step(state, 2 * command - 1, activation)
        # no entry is measured twice in a solve: at most the batch in all
        assert sum(measured) <= batch, measured
        assert not transition.numerical_failure.any()
        assert float(transition.solver_residual.max()) < 1e-4
        state, activation = transition.state, transition.activation
        per_step.append(sum(measured))
    # and mostly far fewer: the entries whose trial the noise could decide
    assert sum(per_step) < 6 * batch / 2, per_step


def test_only_the_refusing_entries_backtrack_and_on_their_own_objective() -> None:
    # a bowl E = 2‖x‖² from x = 1: entries 1–3 take the exact Newton step (d = −1, t = 1); entry 0's
    # direction is 100× too long, and its search must come down to t = 0.01. Given `restrict`,
    # entry 0 searches again alone, on an objective of its row; the result is the same, the minimum at 0
    from energysim.objective.objective import Objective
    from energysim.solvers.line_search import line_step

    def bowl() -> Objective:
        # the bowl has no data per entry: the objective of some rows is a bowl too
        return Objective([_Bowl()], torch.ones(1, dtype=torch.bool), torch.ones(1, dtype=torch.float64))

    x = torch.ones(4, 1, 1, dtype=torch.float64)
    direction = -torch.ones_like(x)
    direction[0] *= 100.0
    restricted_rows = []

    def restrict(rows: torch.Tensor) -> Objective:
        restricted_rows.append(rows.tolist())
        return bowl()

    results = []
    for given in (None, restrict):
        objective = bowl()
        energy, gradient = objective.energy_and_gradient(x)
        results.append(line_step(objective, x, energy, gradient, direction, restrict=given))
    whole, alone = results
    assert restricted_rows == [[0]]
    assert alone.step.tolist() == pytest.approx([0.01, 1.0, 1.0, 1.0], rel=1e-12)
    for field in ("step", "x", "energy", "gradient", "residual"):
        assert torch.allclose(getattr(alone, field), getattr(whole, field), rtol=0, atol=1e-12), field
    assert float(alone.x.abs().max()) < 1e-12 and float(alone.energy.abs().max()) < 1e-20


def _searched_with_rows_alone(
    term: type[es.EnergyTerm], x: torch.Tensor, direction: torch.Tensor
) -> tuple[torch.Tensor, object, list]:
    """`line_step` from `x` along `direction` on the objective of one `term`, given `restrict`: E at
    `x`, the search's result and the objectives of rows it built (the term has no data per entry,
    so the objective of some rows is a fresh one of the same term)."""
    from energysim.objective.objective import Objective
    from energysim.solvers.line_search import line_step

    def objective_of() -> Objective:
        return Objective([term()], torch.ones(1, dtype=torch.bool), torch.ones(1, dtype=torch.float64))

    parts = []

    def restrict(rows: torch.Tensor) -> Objective:
        parts.append(objective_of())
        return parts[-1]

    objective = objective_of()
    energy, gradient = objective.energy_and_gradient(x)
    return energy, line_step(objective, x, energy, gradient, direction, restrict=restrict), parts


def test_a_refusing_entry_whose_interpolated_step_holds_costs_its_row_one_evaluation() -> None:
    # the bowl E = 2‖x‖² from x = 1 along d = −4 (entry 0) and −1 (entry 1): entry 0 refuses t = 1
    # (x = −3, E = 18 > 2), and the quadratic through E(0) = 2, φ'(0) = −16 and E(1) = 18 has its
    # minimum at t = 0.25, inside the safeguard's [0.1, 0.5]: on a quadratic the interpolation is
    # exact. Its row's search is one trial there, energy and gradient in one evaluation, and lands
    # on the minimum x = 0
    x = torch.ones(2, 1, 1, dtype=torch.float64)
    direction = -torch.tensor([4.0, 1.0], dtype=torch.float64)[:, None, None] * torch.ones_like(x)
    _, result, parts = _searched_with_rows_alone(_Bowl, x, direction)
    assert len(parts) == 1 and parts[0].grad_evals == 1 and parts[0].energy_evals == 0
    assert result.step.tolist() == pytest.approx([0.25, 1.0], rel=1e-12)
    assert float(result.x.abs().max()) < 1e-12 and float(result.gradient.abs().max()) < 1e-11
    assert result.residual.tolist() == pytest.approx(result.gradient.abs().reshape(2).tolist(), abs=0)


class _Quartic(es.EnergyTerm):
    """E = ‖x‖⁴, in J (∇E = 4‖x‖²x): a backtracking search on it ends away from the minimum."""

    def forward(self, x: torch.Tensor, action: torch.Tensor | None = None) -> torch.Tensor:
        return (x * x).sum(dim=(-1, -2)) ** 2


def test_an_entry_searching_alone_twice_refused_gets_the_gradient_where_it_stops() -> None:
    # from x = 1 along d = −37 the search refuses t = 1 (x = −36); the row's own search refuses its
    # first trial t = 0.1 (x = −2.7, evaluated with its gradient) and backtracks on the energy alone to
    # t ≈ 0.011 (x ≈ 0.59, E ≈ 0.12 < 1). The gradient it returns is ∇E = 4x³ there
    x = torch.ones(3, 1, 1, dtype=torch.float64)
    direction = -torch.ones_like(x) * torch.tensor([37.0, 0.2, 0.2], dtype=torch.float64)[:, None, None]
    energy, result, parts = _searched_with_rows_alone(_Quartic, x, direction)
    assert 0.01 <= float(result.step[0]) <= 0.05 and result.step[1:].tolist() == [1.0, 1.0]
    assert float(result.x[0]) == pytest.approx(1.0 - 37.0 * float(result.step[0]), rel=1e-14)
    assert 0.0 < float(result.energy[0]) < float(energy[0])
    assert torch.allclose(result.gradient, 4.0 * result.x**3, rtol=1e-14, atol=0)
    assert torch.allclose(result.energy, result.x.reshape(-1) ** 4, rtol=1e-14, atol=0)
    assert len(parts) == 1 and parts[0].grad_evals == 2 and parts[0].energy_evals == 1


class _RaisedBowl(es.EnergyTerm):
    """E = C + ½ k ‖x‖², in J, with C = 2³⁹ J: its 64 ulps (7.8e-3 J) are the allowance for rounding,
    as a large potential far from its datum makes them (float32's 64 ulps of a worm's 0.18 J are 1.4e-6 J)."""

    def forward(self, x: torch.Tensor, action: torch.Tensor | None = None) -> torch.Tensor:
        return 2.0**39 + 0.5 * 4.0 * (x * x).sum(dim=(-1, -2))


@pytest.mark.parametrize("alone", [False, True])
def test_a_step_that_overshoots_is_refused_though_its_rise_is_within_the_rounding(alone: bool) -> None:
    # from x = 1 along d = −(2 + δ): the minimum is at t ≈ 1/2, and the full step lands at −(1 + δ),
    # E rising by 4δ = 2e-3 J: within the rounding allowance, while the predicted decrease (8 J) is
    # far above it, so the energy judges the step, and the slope at t = 1 (+8 J) says it went past
    # the minimum. Accepted, such steps make no progress: float32 worms among 4,096 driven at random
    # stalled at 0.6-1.6 m/s taking them. Refused, the minimiser of the quadratic through the two
    # slopes lands on the bowl's minimum. Entry 1 takes the exact Newton step.
    from energysim.objective.objective import Objective
    from energysim.solvers.line_search import line_step

    def bowl() -> Objective:
        return Objective([_RaisedBowl()], torch.ones(1, dtype=torch.bool), torch.ones(1, dtype=torch.float64))

    delta = 5e-4
    x = torch.ones(2, 1, 1, dtype=torch.float64)
    direction = -torch.ones_like(x)
    direction[0] *= 2.0 + delta
    objective = bowl()
    energy, gradient = objective.energy_and_gradient(x)
    rise = float(objective.energy(x + direction)[0] - energy[0])
    assert 0 < rise < 64 * torch.finfo(torch.float64).eps * float(energy[0])  # the premise
    restrict = (lambda rows: bowl()) if alone else None
    result = line_step(objective, x, energy, gradient, direction, restrict=restrict)
    assert float(result.step[0]) == pytest.approx(0.5, rel=1e-3)
    assert float(result.x[0].abs().max()) < 1e-3  # at the minimum, not at −(1 + δ)
    assert float(result.step[1]) == 1.0 and float(result.x[1].abs().max()) == 0.0


@pytest.mark.parametrize(("entry", "steps"), [(211, 2), (88, 4)])
def test_float32_worms_that_stalled_on_such_steps_converge(entry: int, steps: int) -> None:
    # two of 4,096 float32 worms driven at random (entry i reset with seed i, the batch's actions drawn
    # from one Box of shape [4096, a] seeded 0), whose solves in the last of these steps had stalled
    # at 0.57 and 1.6 m/s on steps twice the way to the line minimum, as in the test above
    import numpy as np
    from gymnasium import spaces

    from energysim.envs import CreatureVectorEnv

    env = CreatureVectorEnv(1, "worm", frame_skip=1, dt=1 / 60, dtype=torch.float32, solver_tol=1e-2)
    env.reset(seed=entry)
    actions = spaces.Box(-1.0, 1.0, (4096, env.single_action_space.shape[0]), np.float32)
    actions.seed(0)
    for _ in range(steps):
        _, _, terminated, _, info = env.step(actions.sample()[entry : entry + 1])
        assert not terminated[0]
        assert float(info["solver_residual"][0]) < 1e-2


def test_the_noise_measured_in_one_evaluation_of_repeated_rows_is_the_sample_by_sample_noise() -> None:
    # `energy_noise(replicated=...)`: the samples of two of three worms as one evaluation of the
    # objective of their rows repeated (`rows_of`), against one evaluation per sample
    from energysim.creatures import load_creature, resting_state
    from energysim.integrators.adjoint import step_terms
    from energysim.integrators.implicit_stage import rows_of
    from energysim.objective.objective import Objective
    from energysim.solvers.energy_rounding import NOISE_SAMPLES

    scene = load_creature("worm").scene(1 / 60, 0.8)
    x, v = scene.split_state(resting_state(scene).reshape(1, -1).expand(3, -1))
    generator = torch.Generator().manual_seed(4)
    v = v + 0.1 * torch.randn(v.shape, generator=generator, dtype=v.dtype)
    action = torch.rand(3, 10, generator=generator, dtype=x.dtype) * 2 - 1
    terms = step_terms(list(scene.terms), scene.vertex_mass, scene.dt, x, v, scene.free)
    objective = Objective(terms, scene.free, scene.dt / scene.vertex_mass, action)
    rows = torch.tensor([2, 0])
    probe = (x + 1e-5 * torch.randn(x.shape, generator=generator, dtype=x.dtype))[rows]
    part = rows_of(objective, scene.terms, rows)
    energy = part.energy(probe)
    one_by_one = energy_noise(part, probe, energy)
    replicated = rows_of(objective, scene.terms, rows.repeat(NOISE_SAMPLES))
    together = energy_noise(part, probe, energy, replicated=replicated)
    assert bool(torch.isfinite(energy).all() and (one_by_one > 0).all())
    torch.testing.assert_close(together, one_by_one, rtol=1e-9, atol=0.0)
