"""Failures of explicit steps and of env entries, and actions that do not fit the scene.

A leapfrog step that blows up is caught however it shows (an energy gain, an energy or a state
gone non-finite, a vertex left inside the ground), and an env reports it as a numerical failure of
that entry alone, with its last good state and finite values; an action with the wrong number of
entries, or of a type that is not real numbers, is refused with both numbers named.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import torch

import energysim as es
from energysim.creatures import load_creature, resting_state, scene_ground
from energysim.energies.muscles import check_action_width
from energysim.integrators import explicit

gymnasium = pytest.importorskip("gymnasium")

import energysim.envs.core as env_core  # noqa: E402
from energysim.envs import CreatureEnv, CreatureVectorEnv  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

# full alternating activations, instant and undamped, at 32 substeps (the stable step at rest asks
# for 32, the deformed worm for 36): the worm gains energy at every switch until a step blows up
UNSTABLE_WORM = {"integrator": "leapfrog", "activation_time_constant": 0, "viscosity": 0, "substeps": 32}
CTRL_COST_WEIGHT = 1e-3
# the batched leapfrog may sum in another order than a smaller batch: equal to rounding, far inside this
BATCH_TOLERANCE = 1e-8
MAX_STEPS = 8
HEAVY = os.environ.get("ENERGYSIM_HEAVY") == "1"


def alternating(step: int, actuators: int = 10) -> np.ndarray:
    """All muscles at +1 on even steps, −1 on odd ones."""
    return np.full(actuators, 1.0 if step % 2 == 0 else -1.0)


def test_a_leapfrog_blow_up_ends_the_episode_with_the_last_good_state() -> None:
    env = CreatureEnv("worm", **UNSTABLE_WORM)
    observation, _ = env.reset(seed=1)
    for k in range(MAX_STEPS):
        state = env.state.clone()
        previous = observation
        observation, reward, terminated, truncated, info = env.step(alternating(k))
        assert np.isfinite(observation).all() and math.isfinite(reward)
        if terminated:
            break
    else:
        pytest.fail(f"the undamped worm did not blow up within {MAX_STEPS} steps")
    assert k >= 1 and info["numerical_failure"] and not truncated
    # the failed entry keeps its state; its observation is the last good one but for the activation
    assert torch.equal(env.state, state)
    body = slice(0, env.simulation.layout.activation.start)
    assert np.array_equal(observation[body], previous[body])
    # no displacement: the reward is the control cost of |u|² = 10 alone
    assert info["x_velocity"] == 0.0
    assert reward == pytest.approx(-CTRL_COST_WEIGHT * 10.0, rel=1e-12)
    # the state stays admissible: stepping on from it raises nothing and stays finite
    observation, reward, *_ = env.step(alternating(k + 1))
    assert np.isfinite(observation).all() and math.isfinite(reward)


def test_the_step_that_blows_up_raises_instability_naming_what_went_wrong() -> None:
    env = CreatureEnv("worm", **UNSTABLE_WORM)
    env.reset(seed=1)
    for k in range(MAX_STEPS):
        state = env.state.clone()
        if env.step(alternating(k))[2]:
            break
    else:
        pytest.fail(f"the undamped worm did not blow up within {MAX_STEPS} steps")
    given = state.clone()
    action = torch.from_numpy(alternating(k))[None]
    with pytest.raises(explicit.InstabilityError, match=r"leapfrog step blew up.*batch entry 0") as caught:
        es.step(env.simulation.scene, state, action)
    assert "substeps" in str(caught.value)
    assert torch.equal(state, given)  # the step changed nothing it was given


def _worm_scene() -> es.Scene:
    creature = load_creature("worm")
    scene = creature.scene(1 / 60, 0.8, es.NewtonCG())
    scene.integrator = "leapfrog"
    return scene


def test_blown_up_counts_non_finite_energies_gains_and_penetration() -> None:
    scene = _worm_scene()
    ground = scene_ground(scene)
    x = resting_state(scene)[None, : scene.num_dofs].reshape(1, scene.num_vertices, 3)
    x = x.expand(5, -1, -1).clone()
    v = torch.zeros_like(x)
    before = torch.ones(5, dtype=torch.float64)
    # a kinetic energy that overflowed, with an allowance that grew with it: inf <= 1 + inf holds
    after = torch.tensor([1.2, 1.6, math.inf, math.nan, 1.2], dtype=torch.float64)
    allowance = torch.tensor([0.5, 0.5, math.inf, 0.5, 0.5], dtype=torch.float64)
    # entry 4 ends with its lowest vertex 1 cm below the ground
    lowest = int(x[4, :, 1].argmin())
    x[4, lowest, 1] = float(ground.offset) - 0.01
    failed = explicit.blown_up(x, v, [ground], before, after, allowance)
    assert failed.tolist() == [False, True, True, True, True]
    assert explicit.ends_inside([ground], x).tolist() == [False, False, False, False, True]
    # a non-finite position or velocity fails the entry whatever its energies say
    v[0, 0, 0] = math.inf
    x[1, 0, 0] = math.nan
    failed = explicit.blown_up(x, v, [ground], before, before, torch.full_like(before, 0.5))
    assert failed.tolist() == [True, True, False, False, True]
    detail = explicit.describe_blow_up([ground], x[4:5], torch.zeros_like(x[4:5]))
    assert f"vertices [{lowest}] ended inside" in detail and "-0.01 m" in detail


def _run_vector(seeds: list[int], bad: int | None, steps: int, **options: object) -> list[dict]:
    vector = CreatureVectorEnv(len(seeds), "worm", **UNSTABLE_WORM, **options)
    vector.reset(seed=seeds)
    records = []
    for k in range(steps):
        actions = np.zeros((len(seeds), 10))
        if bad is not None:
            actions[bad] = alternating(k)
        observations, rewards, terminated, truncated, info = vector.step(actions)
        records.append(
            {
                "states": vector.states.clone(),
                "observations": observations,
                "rewards": rewards,
                "terminated": terminated,
                "failure": info.get("numerical_failure"),
            }
        )
    return records


@pytest.mark.parametrize(
    "compile_solver",
    [
        False,
        pytest.param(
            True,
            marks=pytest.mark.skipif(
                not HEAVY, reason="compiles the leapfrog for three batch sizes: minutes; ENERGYSIM_HEAVY=1"
            ),
        ),
    ],
    ids=["eager", "compiled"],
)
def test_one_blown_up_entry_leaves_the_others_as_a_batch_without_it(compile_solver: bool) -> None:
    steps = 6
    batch = _run_vector([2, 1, 3], bad=1, steps=steps, solver_compile=compile_solver)
    alone = _run_vector([2, 3], bad=None, steps=steps, solver_compile=compile_solver)
    failed_at = [k for k, record in enumerate(batch) if record["terminated"][1]]
    assert failed_at, "the driven entry did not blow up"
    assert batch[failed_at[0]]["failure"].tolist() == [False, True, False]
    for record, reference in zip(batch, alone, strict=True):
        assert np.isfinite(record["observations"]).all() and np.isfinite(record["rewards"]).all()
        assert not record["terminated"][[0, 2]].any()
        assert torch.allclose(record["states"][[0, 2]], reference["states"], rtol=0, atol=BATCH_TOLERANCE)
        assert np.allclose(record["rewards"][[0, 2]], reference["rewards"], rtol=0, atol=BATCH_TOLERANCE)


def test_a_frame_past_float32_fails_that_entry_only(monkeypatch: pytest.MonkeyPatch) -> None:
    # a step whose result is finite in float64 but whose observation would overflow float32
    real_step = env_core.step

    def runaway_step(scene: es.Scene, state: torch.Tensor, action: torch.Tensor) -> es.StepResult:
        result = real_step(scene, state, action)
        if state.shape[0] < 3:
            return result
        moved = result.state.clone()
        moved[1, scene.num_dofs :] = 1e40
        return es.StepResult(state=moved, stats=result.stats)

    vector = CreatureVectorEnv(3, "worm", integrator="leapfrog")
    vector.reset(seed=0)
    start = vector.states.clone()
    reference = CreatureVectorEnv(3, "worm", integrator="leapfrog")
    reference.reset(seed=0)
    expected, expected_rewards, *_ = reference.step(np.zeros((3, 10)))
    monkeypatch.setattr(env_core, "step", runaway_step)
    observations, rewards, terminated, _, info = vector.step(np.zeros((3, 10)))
    assert terminated.tolist() == [False, True, False]
    assert info["numerical_failure"].tolist() == [False, True, False]
    assert np.isfinite(observations).all() and np.isfinite(rewards).all()
    assert torch.equal(vector.states[1], start[1])
    assert np.array_equal(observations[[0, 2]], expected[[0, 2]])
    assert np.array_equal(rewards[[0, 2]], expected_rewards[[0, 2]])


@pytest.mark.parametrize("width", [13, 9])
def test_a_step_refuses_an_action_that_does_not_fit_the_actuators(width: int) -> None:
    scene = _worm_scene()
    state = resting_state(scene)
    message = rf"action has {width} entries per body, the scene's FibreMuscles have 10 actuators"
    with pytest.raises(ValueError, match=message):
        es.timestep(scene, state, action=torch.zeros(width, dtype=torch.float64))
    with pytest.raises(ValueError, match=message):
        es.step(scene, state[None].expand(2, -1), torch.zeros(2, width, dtype=torch.float64))


def test_action_width_is_the_largest_of_several_actuated_terms_and_none_without_any() -> None:
    springs = es.ActuatedSprings(torch.tensor([[0, 1], [1, 2]]), torch.tensor([0, 3]))
    muscles = es.FibreMuscles(torch.ones(2, 3, dtype=torch.float64), torch.tensor([0, 9]))
    check_action_width([springs, muscles], torch.zeros(1, 10))
    listed = r"has 4 entries per body, the scene.s actuated terms read 10 "
    listed += r"\(ActuatedSprings: 4, FibreMuscles: 10\)"
    with pytest.raises(ValueError, match=listed):
        check_action_width([springs, muscles], torch.zeros(1, 4))
    scene = es.Scene(es.TetMesh.box(size=(1.0, 1.0, 1.0), cells=(1, 1, 1)), dt=0.01)
    scene.add(es.NeoHookean(1e5, 0.3))
    with pytest.raises(ValueError, match="action has 3 entries per body, but the scene has no actuated term"):
        es.timestep(scene, scene.initial_state(), action=torch.zeros(3, dtype=torch.float64))


@pytest.mark.parametrize("dtype", [torch.complex128, torch.bool])
def test_a_step_refuses_an_action_that_is_not_real_numbers(dtype: torch.dtype) -> None:
    scene = _worm_scene()
    with pytest.raises(ValueError, match=r"action must hold real numbers.*dtype"):
        es.timestep(scene, resting_state(scene), action=torch.zeros(10, dtype=dtype))


def test_envs_refuse_actions_of_the_wrong_size_type_or_values() -> None:
    env = CreatureEnv("worm", integrator="leapfrog")
    env.reset(seed=0)
    state = env.state.clone()
    with pytest.raises(ValueError, match=r"action must have shape \(10,\).*got \(13,\)"):
        env.step(np.zeros(13))
    for bad in (np.zeros(10, dtype=complex), np.array(["0.5"] * 10), np.zeros(10, dtype=bool), [None] * 10):
        with pytest.raises(ValueError, match="action must hold real numbers"):
            env.step(bad)
    nan = np.zeros(10)
    nan[3] = math.nan
    with pytest.raises(ValueError, match="non-finite"):
        env.step(nan)
    assert torch.equal(env.state, state)
    vector = CreatureVectorEnv(2, "worm", integrator="leapfrog")
    vector.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 10\).*got \(2, 13\)"):
        vector.step(np.zeros((2, 13)))
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 10\).*got \(3, 10\)"):
        vector.step(np.zeros((3, 10)))
    with pytest.raises(ValueError, match="actions must hold real numbers"):
        vector.step(np.zeros((2, 10), dtype=complex))
    with pytest.raises(ValueError, match=r"non-finite entries in rows \[1\]"):
        vector.step(np.stack([np.zeros(10), np.full(10, math.inf)]))
    simulation = vector.simulation
    with pytest.raises(ValueError, match=r"action must have shape \[B, 10\].*got \[2, 13\]"):
        simulation.step(vector.states, torch.zeros(2, 13, dtype=torch.float64))
    with pytest.raises(ValueError, match="action must hold real numbers"):
        simulation.step(vector.states, torch.zeros(2, 10, dtype=torch.complex128))
    with pytest.raises(ValueError, match=r"state must have shape \[3, 2·n·d\]"):
        simulation.step(vector.states, torch.zeros(3, 10, dtype=torch.float64))
