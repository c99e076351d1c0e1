"""A fixed Newton budget per physics step in the creature envs (`solver_budget`): the gait it walks
against the converged solves', its reported residual, and its refusals."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

pytest.importorskip("gymnasium")

from energysim.envs import CreatureEnv  # noqa: E402
from energysim.solvers import ConvergenceWarning  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

BUDGET = 4
STEPS = 60  # 1 s of the crawler's suggested gait


def _gait(**options: object) -> tuple[float, list[int], list[float], np.ndarray]:
    """Distance (m), Newton iterations and residuals per env step, and the final state."""
    env = CreatureEnv("crawler2d", reset_noise_scale=0.0, **options)
    _, info = env.reset(seed=0)
    start = info["x_position"]
    iterations, residuals = [], []
    for k in range(STEPS):
        _, _, terminated, _, info = env.step(env.simulation.creature.gait_action(k / 60).numpy())
        assert not terminated
        iterations.append(info["solver_iterations"])
        residuals.append(info["solver_residual"])
    return info["x_position"] - start, iterations, residuals, env.state[0].numpy()


def test_a_budget_walks_the_converged_gait_and_reports_what_it_leaves() -> None:
    converged, converged_iterations, converged_residuals, _ = _gait(solver_tol=1e-6)
    assert max(converged_residuals) < 1e-6
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)  # unconverged by design: no warning
        budgeted, iterations, residuals, state = _gait(solver_budget=BUDGET)
    assert max(iterations) <= BUDGET < max(converged_iterations)
    # the budget leaves residuals far above the tolerance, and says so
    assert max(residuals) > 1e-2 and all(np.isfinite(residuals))
    # measured: 0.07809 against 0.07810 m; implicit Euler's own time error at h = 1/60 s is ~10 %
    assert budgeted == pytest.approx(converged, rel=0.02)
    # every iterate stays inside the CCD limit: above the ground
    positions = torch.from_numpy(state[: state.size // 2]).reshape(-1, 2)
    assert float(positions[:, 1].min()) > 0.0


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "4"])
def test_a_bad_budget_is_refused_naming_it(bad: object) -> None:
    with pytest.raises(ValueError, match="solver_budget"):
        CreatureEnv("crawler2d", solver_budget=bad)


def test_a_budget_for_the_explicit_integrator_is_refused() -> None:
    with pytest.raises(ValueError, match="solver_budget = 4 is for the implicit integrators"):
        CreatureEnv("crawler2d", integrator="leapfrog", solver_budget=4)


def test_bench_env_times_a_budget_against_a_reference_solved_to_the_tolerance(tmp_path) -> None:  # noqa: ANN001
    from conftest import script_module

    (row,) = script_module("bench_env").main(
        ["--creatures", "crawler2d", "--batch-sizes", "2", "--steps", "2", "--warmup", "0", "--no-plot"]
        + ["--device", "cpu", "--out", str(tmp_path), "--solver-budget", "2", "--gait-seconds", "0.2"]
    )
    assert row.solver_budget == 2 and row.newton_iterations <= 2
    # two iterations leave a residual far above the tolerance, and the table shows it
    assert row.solver_residual > 1e-3
    # the gait's reference is solved to the tolerance at h/4: a finite, small difference
    assert 0 < row.gait_distance_error < 0.01
    assert "fixed budget of at most 2 Newton iterations" in (tmp_path / "bench_env.md").read_text()


def test_each_entry_reports_its_own_iterations_when_solved_to_the_tolerance() -> None:
    # a driven crawler and a resting one, solved to 1e-4 m/s: the resting one converges sooner and
    # stops costing; its count is its own, not the batched solve's
    from energysim.envs import CreatureVectorEnv

    env = CreatureVectorEnv(2, "crawler2d", activation_time_constant=0.0)
    env.reset(seed=0)
    action = np.zeros((2, env.single_action_space.shape[0]), dtype=np.float32)
    action[0] = 1.0
    # the first steps settle both bodies onto the ground from the reset's lifted rest shape (7 and 7
    # iterations, then 6 and 5); by the fourth the resting one needs far fewer (measured: 4 against 2)
    for _ in range(4):
        _, _, _, _, info = env.step(action)
    iterations, residual = info["solver_iterations"], info["solver_residual"]
    assert 1 <= iterations[1] < iterations[0]
    assert residual.max() < 1e-4


def test_each_entry_reports_its_own_residual() -> None:
    # a batch of two: one worm driven hard, one left at rest, whose solve converges at once
    from energysim.envs import CreatureVectorEnv

    env = CreatureVectorEnv(2, "crawler2d", solver_budget=2, activation_time_constant=0.0)
    env.reset(seed=0)
    action = np.zeros((2, env.single_action_space.shape[0]), dtype=np.float32)
    action[0] = 1.0
    # the first step settles both onto the ground from the reset's lifted rest shape; in the second,
    # two iterations leave both unconverged, the driven one far worse (measured: 32 against 1.4 m/s);
    # a batch-wide figure would give both the larger
    for _ in range(2):
        _, _, _, _, info = env.step(action)
    residual = info["solver_residual"]
    assert residual[0] > 2 * residual[1] > 0


def test_a_one_iteration_budget_stays_bounded_under_instant_random_activations() -> None:
    # the hardest actions (every muscle jumps at every step, no activation dynamics) with one Newton
    # iteration a step: each iterate is a descent step inside the CCD limit, so nothing blows up or
    # passes through the ground (measured over 120 steps of 8 worms: kinetic energy at most 0.008 J)
    from energysim.envs import CreatureVectorEnv

    env = CreatureVectorEnv(4, "worm", solver_budget=1, activation_time_constant=0.0)
    env.reset(seed=0)
    env.action_space.seed(0)
    scene = env.simulation.scene
    for _ in range(40):
        _, _, _, _, info = env.step(env.action_space.sample())
        assert not info["numerical_failure"].any()
        x, v = scene.split_state(env.states)
        kinetic = 0.5 * (scene.vertex_mass[:, None] * v**2).sum(dim=(-1, -2))
        assert float(kinetic.max()) < 0.5  # J; the worm weighs 0.48 kg
        assert float(x[..., 1].min()) > 0.0


def test_a_one_iteration_budget_lands_a_20_m_per_s_drop() -> None:
    from energysim.envs.config import CreatureEnvConfig
    from energysim.envs.core import CreatureSimulation

    simulation = CreatureSimulation(CreatureEnvConfig(creature="worm", solver_budget=1))
    scene = simulation.scene
    x = scene.rest_positions + torch.tensor([0.0, 0.05, 0.0], dtype=torch.float64)
    v = torch.zeros_like(x)
    v[:, 1] = -20.0
    state = torch.cat([x.reshape(1, -1), v.reshape(1, -1)], dim=1)
    start = 0.5 * float(scene.vertex_mass.sum()) * 20.0**2
    activation = None
    for _ in range(30):
        rest = torch.zeros(1, simulation.num_actuators, dtype=torch.float64)
        transition = simulation.step(state, rest, activation)
        assert not transition.numerical_failure.any()
        state, activation = transition.state, transition.activation
        positions, velocities = scene.split_state(state)
        assert float(positions[..., 1].min()) > 0.0  # never through the ground
    kinetic = 0.5 * float((scene.vertex_mass[:, None] * velocities[0] ** 2).sum())
    # implicit Euler only dissipates: after 0.5 s the 96 J of the fall are gone
    assert kinetic < 1e-6 * start
