"""The Gymnasium environments of the shipped creatures: API conformance, seeding, the reward against an
independent simulation, batched against single environments, autoreset, numerical failures, bad input,
and the optional first-order activation dynamics.

Heavy tests run a short form on CI (the 2D crawler, a tiny time step for the API checks) and the full
form with ENERGYSIM_HEAVY=1 (every creature at the registered defaults, the worm in 3D).
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

gymnasium = pytest.importorskip("gymnasium")

from conftest import random_rotation  # noqa: E402
from gymnasium.utils.env_checker import check_env  # noqa: E402

import energysim as es  # noqa: E402
import energysim.envs as envs  # noqa: E402
from energysim.creatures import CREATURES, load_creature, resting_state  # noqa: E402
from energysim.envs import CreatureEnv, CreatureVectorEnv, ObservationLayout  # noqa: E402
from energysim.envs.observation import (  # noqa: E402
    best_fit_rotation,
    farthest_point_markers,
    orientation_features,
)

FULL = os.environ.get("ENERGYSIM_HEAVY") == "1"
ROOT = Path(__file__).resolve().parents[1]
# the batched solve may sum in another order than a single one: equal to rounding, far inside this
BATCH_TOLERANCE = 1e-8
FLOAT32_TOLERANCE = 1e-6


pytestmark = pytest.mark.usefixtures("one_thread")


def centre_of_mass_x(scene: es.Scene, state: torch.Tensor) -> float:
    """Mass-weighted mean x of a state `[2·n·d]`, from the masses as numpy: an independent reduction."""
    x = state[: scene.num_dofs].reshape(scene.num_vertices, scene.dim).numpy()
    mass = scene.vertex_mass.numpy()
    return float(mass @ x[:, 0] / mass.sum())


def test_import_energysim_does_not_import_gymnasium() -> None:
    code = "import sys, energysim; print('gymnasium' in sys.modules)"
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True
    )
    assert result.stdout.strip() == "False"


def test_every_creature_is_registered_with_both_entry_points() -> None:
    assert set(envs.ENV_IDS) == set(CREATURES)
    assert envs.ENV_IDS["worm"] == "energysim/Worm-v0"
    assert envs.ENV_IDS["crawler2d"] == "energysim/Crawler2d-v0"
    for creature, env_id in envs.ENV_IDS.items():
        spec = gymnasium.spec(env_id)
        assert spec.entry_point == "energysim.envs.creature_env:CreatureEnv"
        assert spec.vector_entry_point == "energysim.envs.vector_env:CreatureVectorEnv"
        assert spec.kwargs == {"creature": creature}
        assert spec.max_episode_steps == envs.MAX_EPISODE_STEPS == 300


def test_make_and_make_vec_build_the_single_and_the_batched_env() -> None:
    env = gymnasium.make("energysim/Crawler2d-v0")
    assert isinstance(env.unwrapped, CreatureEnv)
    assert env.spec.max_episode_steps == 300
    vector = gymnasium.make_vec("energysim/Crawler2d-v0", num_envs=3, vectorization_mode="vector_entry_point")
    assert isinstance(vector.unwrapped, CreatureVectorEnv)
    assert vector.num_envs == 3
    # make_vec hands the registration's episode length to the vector env, which truncates itself
    assert vector.unwrapped.config.max_episode_steps == 300
    assert vector.single_observation_space == env.observation_space
    assert vector.single_action_space == env.action_space
    assert vector.observation_space.shape == (3, *env.observation_space.shape)
    assert vector.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    # crawler2d: height 1, velocity 2, 12 markers x 2 x 2, orientation 2, 10 actuators
    assert env.observation_space.shape == (1 + 2 + 48 + 2 + 10,)
    assert env.observation_space.dtype == np.float32
    assert env.action_space.shape == (10,)
    assert (env.action_space.low == -1).all() and (env.action_space.high == 1).all()


@pytest.mark.heavy
@pytest.mark.parametrize("creature", CREATURES)
def test_gymnasium_env_checker_passes(creature: str) -> None:
    # the checker tests the API (spaces, seeding, determinism, returned data); CI takes tiny steps
    # (h = 1 ms) so that the checker's random full-range activations cost a few Newton iterations
    options = {} if FULL else {"dt": 1e-3}
    render_mode = "rgb_array" if creature in ("worm", "crawler2d") else None
    env = gymnasium.make(envs.ENV_IDS[creature], render_mode=render_mode, **options)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # positions and velocities have no natural bounds; Gymnasium's MuJoCo envs are unbounded too
        warnings.filterwarnings("ignore", message=".*Box observation space m.*infinity")
        check_env(env.unwrapped)


def test_gymnasium_env_checker_passes_with_activation_dynamics() -> None:
    # the activation is state the env carries between steps: reset must clear it for determinism
    env = gymnasium.make("energysim/Crawler2d-v0", activation_time_constant=0.05, dt=1e-3)
    assert env.unwrapped.config.activation_time_constant == 0.05
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message=".*Box observation space m.*infinity")
        check_env(env.unwrapped)
    vector = gymnasium.make_vec(
        "energysim/Crawler2d-v0",
        num_envs=2,
        vectorization_mode="vector_entry_point",
        activation_time_constant=0.05,
    )
    assert vector.unwrapped.config.activation_time_constant == 0.05


@pytest.mark.parametrize("time_constant", [None, 0.05])
def test_same_seed_gives_the_same_rollout_and_another_seed_another_start(time_constant: float | None) -> None:
    actions = np.random.default_rng(0).uniform(-0.5, 0.5, size=(3, 10)).astype(np.float32)

    def rollout(seed: int) -> list[np.ndarray]:
        env = CreatureEnv("crawler2d", activation_time_constant=time_constant)
        observation, _ = env.reset(seed=seed)
        records = [observation]
        for action in actions:
            observation, reward, *_ = env.step(action)
            records += [observation, np.array([reward])]
        return records

    first, second = rollout(5), rollout(5)
    assert all(np.array_equal(a, b) for a, b in zip(first, second, strict=True))
    assert not np.array_equal(rollout(6)[0], first[0])


def test_reset_noise_keeps_the_body_just_above_the_ground() -> None:
    scale = 2e-3
    env = CreatureEnv("worm", reset_noise_scale=scale)
    env.reset(seed=3)
    scene = env.simulation.scene
    x, v = (part[0] for part in scene.split_state(env.state))
    d_hat = env.simulation.ground.barrier_distance
    # the lowest vertex is at d̂/2: in contact (inside the barrier's reach), outside the ground
    assert float(x[:, 1].min()) == pytest.approx(0.5 * d_hat, rel=1e-12)
    offset = x - scene.rest_positions
    lift = offset[:, 1].mean()
    assert float(offset[:, [0, 2]].abs().max()) <= scale
    assert float((offset[:, 1] - lift).abs().max()) <= 2 * scale
    assert 0 < float(v.abs().max()) <= scale
    # no noise: exactly the resting state the walking scripts start from
    quiet = CreatureEnv("worm", reset_noise_scale=0.0)
    quiet.reset(seed=3)
    assert torch.equal(quiet.state[0], resting_state(quiet.simulation.scene))


def _bare_scene_apart(env: CreatureEnv) -> es.Scene:
    """The crawler's bare body (no viscosity) built apart from `env`, with the env's solver settings
    and ground: what the env's physics steps must match."""
    return load_creature("crawler2d").scene(
        env.config.dt,
        friction=env.config.friction,
        solver=es.NewtonCG(tol=env.config.solver_tol, indefinite="shift"),
        friction_smoothing=env.config.friction_smoothing,
        barrier_distance=env.simulation.ground.barrier_distance,
    )


def test_reward_is_its_terms_and_the_forward_term_is_the_centre_of_mass_velocity() -> None:
    frame_skip, dt, forward_weight, ctrl_weight = 3, 1 / 60, 2.5, 0.1
    env = CreatureEnv(
        "crawler2d",
        frame_skip=frame_skip,
        dt=dt,
        forward_reward_weight=forward_weight,
        ctrl_cost_weight=ctrl_weight,
        activation_time_constant=0.0,  # the bare body, simulated apart below
        viscosity=0.0,
    )
    env.reset(seed=1)
    start = env.state[0].clone()
    action = np.linspace(-1.6, 1.6, 10)  # partly outside [-1, 1]: the env clips
    observation, reward, terminated, truncated, info = env.step(action)
    assert not terminated and not truncated and not info["numerical_failure"]
    clipped = np.clip(action, -1, 1)
    assert reward == pytest.approx(info["reward_forward"] + info["reward_ctrl"], abs=1e-15)
    assert info["reward_ctrl"] == pytest.approx(-ctrl_weight * (clipped**2).sum(), rel=1e-12)
    assert info["reward_forward"] == pytest.approx(forward_weight * info["x_velocity"], rel=1e-12)
    assert np.array_equal(info["activation"], clipped)  # without a time constant, the action

    # the same three steps, simulated apart from the env from its start state, with the env's solver
    scene = _bare_scene_apart(env)
    states = [start]
    for _ in range(frame_skip):
        states.append(es.step(scene, states[-1], torch.from_numpy(clipped)).state)
    assert torch.allclose(states[-1], env.state[0], rtol=0, atol=BATCH_TOLERANCE)
    displacement = centre_of_mass_x(scene, states[-1]) - centre_of_mass_x(scene, start)
    finite_difference = displacement / (frame_skip * dt)
    assert info["x_velocity"] == pytest.approx(finite_difference, rel=1e-7, abs=1e-12)
    assert info["x_position"] == pytest.approx(centre_of_mass_x(scene, states[-1]), abs=1e-12)
    # implicit Euler: v_{k+1} = (x_{k+1} − x_k)/h, so the mean of the sub-steps' centre-of-mass
    # velocities is the same finite difference
    mass = scene.vertex_mass / scene.vertex_mass.sum()
    velocities = [float(mass @ scene.split_state(s)[1][0, :, 0]) for s in states[1:]]
    assert info["x_velocity"] == pytest.approx(np.mean(velocities), rel=1e-7, abs=1e-12)
    # the observation's centre-of-mass velocity is that at the end of the step
    layout = env.simulation.layout
    assert observation[layout.com_velocity][0] == pytest.approx(velocities[-1], abs=FLOAT32_TOLERANCE)
    assert np.allclose(observation[layout.activation], clipped, atol=FLOAT32_TOLERANCE)


def assert_batched_equals_single(
    creature: str, batch: int, steps: int, seed: int = 11, **options: object
) -> None:
    """Step a vector env and `batch` single envs (seeds seed + i) with the same actions; assert that
    each entry's state agrees with its single env to 1e-8 and its observation, reward and info terms too.

    `options` go to both constructors."""
    vector = CreatureVectorEnv(batch, creature, **options)
    singles = [CreatureEnv(creature, **options) for _ in range(batch)]
    filtered = vector.config.filters_activation
    observations, _ = vector.reset(seed=seed)
    for i, env in enumerate(singles):
        assert np.array_equal(env.reset(seed=seed + i)[0], observations[i])
    gait = load_creature(creature).gait_action(torch.arange(1, steps + 1) / 60).numpy()
    rng = np.random.default_rng(seed)
    for k in range(steps):
        actions = np.clip(gait[k] + rng.uniform(-0.3, 0.3, size=(batch, gait.shape[1])), -1, 1)
        observations, rewards, terminated, truncated, info = vector.step(actions)
        assert not terminated.any() and not truncated.any()
        if not filtered:
            assert np.array_equal(vector.activations.numpy(), actions)
        assert np.array_equal(info["activation"], vector.activations.numpy())
        for i, env in enumerate(singles):
            observation, reward, _, _, single_info = env.step(actions[i])
            assert torch.allclose(vector.states[i], env.state[0], rtol=0, atol=BATCH_TOLERANCE)
            # the filter is elementwise, so batching cannot change it
            assert torch.equal(vector.activations[i], env.activation[0])
            assert np.allclose(observations[i], observation, rtol=0, atol=FLOAT32_TOLERANCE)
            assert abs(rewards[i] - reward) < BATCH_TOLERANCE
            for key in ("x_position", "x_velocity", "reward_forward", "reward_ctrl"):
                assert abs(info[key][i] - single_info[key]) < BATCH_TOLERANCE


@pytest.mark.heavy
@pytest.mark.parametrize("options", [{}, {"activation_time_constant": 0.05, "frame_skip": 2}])
def test_batched_step_equals_single_env_steps(options: dict[str, object]) -> None:
    # one batched solve of B entries gives each entry what its own env gives (CI: the 2D crawler)
    if FULL:
        assert_batched_equals_single("worm", batch=4, steps=3, **options)
    else:
        assert_batched_equals_single("crawler2d", batch=3, steps=2, **options)


def test_activation_dynamics_are_the_exact_step_response() -> None:
    # from rest under a constant command u, ȧ = (u − a)/τ gives a(t) = u (1 − e^{−t/τ}) exactly: the
    # per-step update u + (a − u) e^{−h/τ} must reproduce it after k physics steps, to rounding
    frame_skip, dt, tau, ctrl_weight = 3, 1 / 60, 0.05, 0.1
    env = CreatureEnv(
        "crawler2d",
        frame_skip=frame_skip,
        dt=dt,
        activation_time_constant=tau,
        ctrl_cost_weight=ctrl_weight,
        viscosity=0.0,  # the bare body, simulated apart below
    )
    observation, _ = env.reset(seed=2)
    layout = env.simulation.layout
    assert (observation[layout.activation] == 0).all() and torch.equal(env.activation, torch.zeros(1, 10))
    start = env.state[0].clone()
    action = np.linspace(-1.5, 1.5, 10)  # partly outside [-1, 1]: the command is clipped first
    command = np.clip(action, -1, 1)
    for step in (1, 2):
        observation, reward, terminated, _, info = env.step(action)
        assert not terminated
        expected = command * (1 - np.exp(-step * frame_skip * dt / tau))
        assert np.abs(info["activation"] - expected).max() < 1e-12
        assert np.abs(env.activation[0].numpy() - expected).max() < 1e-12
        assert np.allclose(observation[layout.activation], expected, rtol=0, atol=FLOAT32_TOLERANCE)
        # the control cost is on the command, as MuJoCo's
        assert info["reward_ctrl"] == pytest.approx(-ctrl_weight * (command**2).sum(), rel=1e-12)
        assert reward == pytest.approx(info["reward_forward"] + info["reward_ctrl"], abs=1e-15)

    # the physics saw the filtered activation of every physics step, not the command
    scene = _bare_scene_apart(env)
    state = start
    for k in range(1, 2 * frame_skip + 1):
        activation = torch.from_numpy(command * (1 - np.exp(-k * dt / tau)))
        state = es.step(scene, state, activation).state
    assert torch.allclose(state, env.state[0], rtol=0, atol=BATCH_TOLERANCE)

    # a reset puts the muscles back at rest
    observation, _ = env.reset(seed=2)
    assert (observation[layout.activation] == 0).all() and not env.activation.any()


def test_no_time_constant_is_todays_env_bit_for_bit() -> None:
    # 0 switches the dynamics off: the action is the activation, with no arithmetic on it; None is
    # the body model's τ, with every integrator
    actions = np.random.default_rng(3).uniform(-1.2, 1.2, size=(3, 10))

    def rollout(**options: object) -> list[np.ndarray]:
        env = CreatureEnv("crawler2d", frame_skip=2, **options)
        observation, _ = env.reset(seed=9)
        records = [observation]
        for action in actions:
            observation, reward, _, _, info = env.step(action)
            records += [observation, np.array([reward]), env.state[0].numpy(), info["activation"]]
        return records

    instant = rollout(activation_time_constant=0.0)
    assert instant[-1].tolist() == np.clip(actions[-1], -1, 1).tolist()
    default = rollout()
    for records in (rollout(activation_time_constant=None), rollout(activation_time_constant=0.05)):
        assert all(np.array_equal(a, b) for a, b in zip(default, records, strict=True))
    assert not np.array_equal(default[1], instant[1])


def test_autoreset_is_next_step_like_gymnasiums_sync_vector_env() -> None:
    def single() -> CreatureEnv:
        return CreatureEnv("crawler2d", max_episode_steps=2)

    mode = gymnasium.vector.AutoresetMode.NEXT_STEP
    reference = gymnasium.vector.SyncVectorEnv([single, single], autoreset_mode=mode)
    vector = CreatureVectorEnv(2, "crawler2d", max_episode_steps=2)
    first, _ = vector.reset(seed=4)
    assert np.array_equal(first, reference.reset(seed=4)[0])
    actions = np.random.default_rng(1).uniform(-0.3, 0.3, size=(4, 2, 10))
    for k, action in enumerate(actions):
        got = vector.step(action)
        expected = reference.step(action)
        assert np.allclose(got[0], expected[0], rtol=0, atol=FLOAT32_TOLERANCE)
        assert np.allclose(got[1], expected[1], rtol=0, atol=BATCH_TOLERANCE)
        assert np.array_equal(got[2], expected[2]) and np.array_equal(got[3], expected[3])
        info, expected_info = got[4], expected[4]
        # the same keys and masks; the same values but the iteration count and the residual (a
        # batched solve reports those of its slowest entry)
        assert info.keys() == expected_info.keys()
        for key, value in info.items():
            if key.startswith("_"):
                assert np.array_equal(value, expected_info[key])
            elif key not in ("solver_iterations", "solver_residual"):
                assert np.allclose(value, expected_info[key], rtol=0, atol=BATCH_TOLERANCE)
        if k == 1:  # the second step reaches max_episode_steps
            assert got[3].all()
        if k == 2:  # ...so the third resets: reward 0, a fresh start from each entry's generator
            assert (got[1] == 0).all() and not got[3].any()
            assert "reward_forward" not in info and info["_x_position"].all()
            assert not np.allclose(got[0], first)
        if k == 3:
            assert info["_reward_forward"].all() and (vector.elapsed_steps == 1).all()


def test_numerical_failure_terminates_with_the_last_good_observation() -> None:
    # with at most 20 Newton iterations, resting needs about 5 but switching every muscle to −1
    # at once needs about 50: a real ConvergenceError from the strict solver. Instant activations:
    # the body model's τ would take the jump out
    instant = {"activation_time_constant": 0.0, "viscosity": 0.0}
    env = CreatureEnv("crawler2d", solver_max_iter=20, reset_noise_scale=0.0, **instant)
    before, _ = env.reset(seed=0)
    state = env.state.clone()
    observation, reward, terminated, truncated, info = env.step(-np.ones(10))
    assert terminated and info["numerical_failure"] and not truncated
    assert np.isfinite(observation).all() and np.isfinite(reward)
    assert torch.equal(env.state, state)
    layout = env.simulation.layout
    body = slice(0, layout.activation.start)
    assert np.array_equal(observation[body], before[body])
    assert info["x_velocity"] == 0.0 and info["solver_iterations"] == 0
    calm = CreatureEnv("crawler2d", solver_max_iter=20, reset_noise_scale=0.0, **instant)
    calm.reset(seed=0)
    assert not calm.step(np.zeros(10))[2]


def test_one_failing_entry_does_not_stop_the_others() -> None:
    instant = {"activation_time_constant": 0.0, "viscosity": 0.0}  # see the test above
    vector = CreatureVectorEnv(3, "crawler2d", solver_max_iter=20, reset_noise_scale=0.0, **instant)
    vector.reset(seed=0)
    actions = np.zeros((3, 10))
    actions[1] = -1.0
    observations, rewards, terminated, _, info = vector.step(actions)
    assert terminated.tolist() == [False, True, False]
    assert info["numerical_failure"].tolist() == [False, True, False]
    assert np.isfinite(observations).all() and np.isfinite(rewards).all()
    calm = CreatureEnv("crawler2d", solver_max_iter=20, reset_noise_scale=0.0, **instant)
    calm.reset(seed=0)
    calm.step(np.zeros(10))
    for i in (0, 2):
        assert torch.allclose(vector.states[i], calm.state[0], rtol=0, atol=BATCH_TOLERANCE)
    # the next call resets the failed entry and steps the others
    _, rewards, terminated, _, info = vector.step(np.zeros((3, 10)))
    assert rewards[1] == 0 and not terminated.any()
    assert info["_reward_forward"].tolist() == [True, False, True]


def test_markers_are_well_spread_surface_vertices_chosen_deterministically() -> None:
    mesh = load_creature("worm").mesh
    surface = mesh.surface_vertices()
    markers = farthest_point_markers(mesh.vertices, surface, 12)
    assert torch.equal(markers, farthest_point_markers(mesh.vertices, surface, 12))
    assert len(set(markers.tolist())) == 12 and set(markers.tolist()) <= set(surface.tolist())
    # farthest-point sampling spreads them: no two of the 12 closer than a tenth of the body's diagonal
    points = mesh.vertices[markers]
    gaps = torch.cdist(points, points) + torch.eye(12, dtype=points.dtype) * 1e9
    low, high = mesh.bounding_box()
    assert float(gaps.min()) > 0.1 * float((high - low).norm())
    # the two ends of the worm are markers
    assert float(points[:, 0].min()) == float(low[0]) and float(points[:, 0].max()) == float(high[0])


@pytest.mark.parametrize("dim", [2, 3])
def test_orientation_recovers_a_rigid_rotation(dim: int) -> None:
    creature = load_creature("worm" if dim == 3 else "crawler2d")
    rest = creature.mesh.vertices
    mass = torch.rand(rest.shape[0], dtype=torch.float64) + 0.5
    generator = torch.Generator().manual_seed(2)
    rotations = torch.stack([random_rotation(dim, generator) for _ in range(4)])
    moved = rest @ rotations.mT + torch.randn(4, 1, dim, dtype=torch.float64)
    assert torch.allclose(best_fit_rotation(moved, rest, mass), rotations, atol=1e-12)
    identity = orientation_features(torch.eye(dim, dtype=torch.float64)[None])
    expected = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0] if dim == 3 else [1.0, 0.0]
    assert identity[0].tolist() == expected


def test_observation_of_a_rigidly_moved_body() -> None:
    env = CreatureEnv("worm", reset_noise_scale=0.0)
    simulation = env.simulation
    scene = simulation.scene
    rest = scene.rest_positions
    rotation = random_rotation(3, torch.Generator().manual_seed(5))
    spin = torch.tensor([0.0, 0.7, 0.0], dtype=torch.float64)  # rad/s about y
    offset = torch.tensor([0.3, 0.05, -0.2], dtype=torch.float64)
    x = rest @ rotation.T + offset
    mass = scene.vertex_mass / scene.vertex_mass.sum()
    com = mass @ x
    drift = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    v = torch.linalg.cross(spin.expand_as(x), x - com) + drift
    state = torch.cat([x.flatten(), v.flatten()])[None]
    activation = torch.linspace(-1, 1, 10, dtype=torch.float64)[None]
    observation = simulation.observe(state, activation)[0]
    layout: ObservationLayout = simulation.layout
    assert layout.size == observation.numel() == 1 + 3 + 36 + 36 + 6 + 10
    assert float(observation[layout.com_height]) == pytest.approx(float(com[1]), abs=1e-14)
    assert torch.allclose(observation[layout.com_velocity], drift, atol=1e-14)
    markers = simulation.markers
    rest_com = mass @ rest
    expected = (rest[markers] - rest_com) @ rotation.T
    assert torch.allclose(observation[layout.marker_positions], expected.flatten(), atol=1e-14)
    relative = torch.linalg.cross(spin.expand(markers.numel(), 3), x[markers] - com)
    assert torch.allclose(observation[layout.marker_velocities], relative.flatten(), atol=1e-14)
    assert torch.allclose(observation[layout.orientation], rotation[:, :2].T.flatten(), atol=1e-12)
    assert torch.equal(observation[layout.activation], activation[0])


@pytest.mark.parametrize("creature", ["worm", "walker2d"])
def test_render_draws_the_body_on_the_ground(creature: str) -> None:
    env = CreatureEnv(creature, render_mode="rgb_array")
    assert env.render() is None  # nothing to draw before reset
    env.reset(seed=0)
    image = env.render()
    assert image.shape == (270, 480, 3) and image.dtype == np.uint8
    ground_row = int(np.ceil(270 * 0.8))
    sky, ground = image[:ground_row], image[ground_row:]
    body = (sky != sky[0, 0]).any(axis=-1)
    # the ground is tiled (light and dark), the body drawn above it in its own blue
    assert body.any() and len(np.unique(ground.reshape(-1, 3), axis=0)) > 2
    assert (ground[..., 2] <= ground[..., 0]).all() and (sky[body][:, 2] > sky[body][:, 0]).all()
    rows, columns = np.nonzero(body)
    # the body stands on the ground, centred, one third of the view wide at most
    assert rows.max() == ground_row - 1
    assert abs(columns.mean() - 240) < 40 and columns.max() - columns.min() <= 480 / 3 + 2


def test_bad_arguments_raise_clear_errors() -> None:
    with pytest.raises(ValueError, match="num_envs must be an integer >= 1"):
        CreatureVectorEnv(0, "worm")
    with pytest.raises(ValueError, match="frame_skip must be an integer >= 1"):
        CreatureEnv("worm", frame_skip=0)
    with pytest.raises(ValueError, match="unknown creature 'dragon'"):
        CreatureEnv("dragon")
    with pytest.raises(ValueError, match="dt must be a finite number"):
        CreatureEnv("worm", dt=-0.01)
    with pytest.raises(ValueError, match="reset_noise_scale"):
        CreatureEnv("worm", reset_noise_scale=float("nan"))
    with pytest.raises(ValueError, match="max_episode_steps"):
        CreatureEnv("worm", max_episode_steps=0)
    with pytest.raises(ValueError, match="num_markers must be at most"):
        CreatureEnv("worm", num_markers=10_000)
    for tau in (-0.01, float("nan"), float("inf"), "0.05", True):
        with pytest.raises(ValueError, match="activation_time_constant must be a finite number >= 0.0 s"):
            CreatureEnv("worm", activation_time_constant=tau)
    with pytest.raises(ValueError, match="activation_time_constant"):
        CreatureVectorEnv(2, "worm", activation_time_constant=-1.0)
    with pytest.raises(ValueError, match="activation_time_constant"):
        envs.CreatureEnvConfig(activation_time_constant=float("nan"))
    with pytest.raises(ValueError, match="solver_compile must be True or False"):
        envs.CreatureEnvConfig(solver_compile="yes")
    with pytest.raises(ValueError, match="render_mode"):
        CreatureEnv("worm", render_mode="ascii")
    env = CreatureEnv("worm")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(10))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must have shape \(10,\)"):
        env.step(np.zeros(9))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.full(10, np.nan))
    vector = CreatureVectorEnv(2, "worm")
    vector.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 10\)"):
        vector.step(np.zeros((3, 10)))
    with pytest.raises(ValueError, match="seed must be None, an int or a list of 2 seeds"):
        vector.reset(seed=[1, 2, 3])


def bench_env_script() -> Any:
    """scripts/bench_env.py as a module."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import bench_env
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    return bench_env


def test_bench_env_writes_its_table(tmp_path: Path) -> None:
    bench_env = bench_env_script()
    rows = bench_env.main(
        ["--creatures", "crawler2d", "--batch-sizes", "1", "2", "--steps", "1", "--warmup", "0", "--no-plot"]
        + ["--device", "cpu", "--out", str(tmp_path), "--no-gait"]
    )
    assert [row.batch for row in rows] == [1, 2]
    for row in rows:
        assert row.failures == 0 and row.newton_iterations >= 1
        assert row.env_steps_per_second == pytest.approx(row.batch / (1e-3 * row.ms_per_call))
    table = (tmp_path / "bench_env.md").read_text()
    assert "| crawler2d | 2 |" in table and (tmp_path / "bench_env.csv").exists()
    # without the gait, the caption says so and its cells stay blank rather than "nan"
    assert "The gait was not walked" in table and "nan" not in table
    assert "took turns" not in table  # one env ran: nothing to take turns with
    # the env's body model by default
    assert "τ = 0.05 s" in table and rows[0].activation_time_constant == 0.05
    # the activation time constant reaches the env and is recorded in both files
    rows = bench_env.main(
        ["--creatures", "crawler2d", "--batch-sizes", "1", "--steps", "1", "--warmup", "0", "--no-plot"]
        + ["--device", "cpu", "--out", str(tmp_path), "--activation-time-constant", "0", "--no-gait"]
    )
    assert rows[0].activation_time_constant == 0.0
    assert "no activation dynamics" in (tmp_path / "bench_env.md").read_text()
    assert "activation_time_constant" in (tmp_path / "bench_env.csv").read_text().splitlines()[0]


def test_bench_env_times_the_leapfrog_env_with_its_gait_error(tmp_path: Path) -> None:
    bench_env = bench_env_script()
    rows = bench_env.main(
        ["--creatures", "crawler2d", "--batch-sizes", "2", "--steps", "1", "--warmup", "0", "--no-plot"]
        + ["--device", "cpu", "--out", str(tmp_path), "--integrator", "leapfrog", "--gait-seconds", "0.1"]
    )
    (row,) = rows
    assert row.integrator == "leapfrog" and row.substeps > 1 and row.activation_time_constant == 0.05
    # the reference is the same model at 4× the substeps: close, but not the same numbers
    assert 0 < row.gait_distance_error < 1e-3
    table = (tmp_path / "bench_env.md").read_text()
    assert "explicit leapfrog substeps" in table and "gait error" in table


def test_bench_env_sets_both_envs_side_by_side_with_the_residual(tmp_path: Path) -> None:
    bench_env = bench_env_script()
    rows = bench_env.main(
        ["--creatures", "crawler2d", "--batch-sizes", "2", "--steps", "3", "--warmup", "0", "--no-plot"]
        + ["--device", "cpu", "--out", str(tmp_path), "--integrator", "both", "--no-gait", "--turns", "2"]
    )
    assert [row.integrator for row in rows] == ["implicit_euler", "leapfrog"]
    implicit, explicit = rows
    # the implicit solves reached the env's tolerance, and said so; the explicit step solves nothing
    assert 0 < implicit.solver_residual <= 1e-4 and np.isnan(explicit.solver_residual)
    ratio = explicit.env_steps_per_second / implicit.env_steps_per_second
    # two turns (two calls, then one), each turn's median step time recorded per env
    slow, fast = ([float(ms) for ms in row.turn_ms_per_call.split()] for row in rows)
    assert len(slow) == len(fast) == 2
    turn_ratios = sorted(s / f for s, f in zip(slow, fast, strict=True))
    assert bench_env.turn_ratio_range(implicit, explicit) == pytest.approx(turn_ratios, rel=1e-12)
    table = (tmp_path / "bench_env.md").read_text()
    low, high = turn_ratios
    expected = f"the explicit env is {ratio:.2f}× the implicit env's rate ({low:.2f}–{high:.2f}× turn by"
    assert expected in table
    assert "took turns, 2 each" in table
    assert "turn_ms_per_call" in (tmp_path / "bench_env.csv").read_text().splitlines()[0]
    with pytest.raises(SystemExit):
        bench_env.main(["--turns", "0", "--no-plot", "--out", str(tmp_path)])


def test_bench_env_iterations_varies_one_thing_at_a_time(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import bench_env_iterations
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    rows = bench_env_iterations.main(
        ["--creature", "crawler2d", "--batch-size", "2", "--steps", "1", "--warmup", "0", "--eager"]
        + ["--no-gait", "--no-plot", "--out", str(tmp_path)]
    )
    by_name = {row.variant: row for row in rows}
    assert list(by_name) == [variant.name for variant in bench_env_iterations.VARIANTS]
    # each solve met its own tolerance: the default's, and the loosened one's
    assert by_name["default"].solver_residual <= 1e-4 < by_name["tol 1e-2"].solver_residual <= 1e-2
    # without contact the same actions need clearly fewer Newton iterations (5 against 8.5 here)
    assert by_name["no contact"].newton_iterations < by_name["default"].newton_iterations - 1
    text = (tmp_path / "bench_env_iterations.md").read_text()
    assert "| no contact |" in text and "log10(d_n+1 / d_n)" in text
    # a subset, in the order asked for; the Ground's default barrier range is a third of the env's
    rows = bench_env_iterations.main(
        ["--creature", "crawler2d", "--batch-size", "2", "--steps", "1", "--warmup", "0", "--eager"]
        + ["--no-gait", "--no-plot", "--out", str(tmp_path), "--variants", "d_hat 1e-3 diag", "default"]
    )
    assert [row.variant for row in rows] == ["d_hat 1e-3 diag", "default"]
    narrow = bench_env_iterations.VARIANTS[1].options_for("crawler2d")["barrier_distance"]
    assert narrow == pytest.approx(CreatureEnv("crawler2d").simulation.ground.barrier_distance / 3, rel=1e-12)


def test_bench_env_solves_to_the_tolerance_it_is_given(tmp_path: Path) -> None:
    bench_env = bench_env_script()
    (row,) = bench_env.main(
        ["--creatures", "crawler2d", "--batch-sizes", "2", "--steps", "2", "--warmup", "0", "--no-plot"]
        + ["--device", "cpu", "--out", str(tmp_path), "--solver-tol", "1e-2", "--no-gait"]
    )
    # the residual a solve left stays below the tolerance asked for, not the env's default
    assert row.solver_tol == 1e-2 and 0 < row.solver_residual <= 1e-2
    assert "tol 0.01 m/s" in (tmp_path / "bench_env.md").read_text()
    with pytest.raises(SystemExit):
        bench_env.main(["--solver-tol", "0", "--no-plot", "--out", str(tmp_path)])


@pytest.mark.parametrize("creature", ["worm", "crawler2d"])
def test_leapfrog_envs_pass_the_checker_and_batch_exactly(creature: str) -> None:
    # the explicit env: substeps from the Courant limit at rest, τ = 0.05 s by default
    env = gymnasium.make(envs.ENV_IDS[creature], integrator="leapfrog")
    config = env.unwrapped.config
    assert config.time_constant == envs.core.LEAPFROG_ACTIVATION_TIME_CONSTANT
    if creature == "worm":
        # at rest 2/ω_max = 0.71 ms and, with η = 30 Pa·s, 1/γ_max = 0.70 ms
        assert env.unwrapped.simulation.scene.substeps == 32
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message=".*Box observation space m.*infinity")
        check_env(env.unwrapped)
    assert_batched_equals_single(creature, batch=3, steps=3, integrator="leapfrog")


def test_leapfrog_env_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="integrator must be one of"):
        envs.CreatureEnvConfig(integrator="rk4")
    with pytest.raises(ValueError, match="substeps = 8 is for integrator='leapfrog'"):
        envs.CreatureEnvConfig(substeps=8)
    with pytest.raises(ValueError, match="substeps must be an integer >= 1"):
        envs.CreatureEnvConfig(integrator="leapfrog", substeps=0)
    # τ = 0 keeps instant activations on the explicit env too
    assert envs.CreatureEnvConfig(integrator="leapfrog", activation_time_constant=0.0).time_constant == 0.0
    # one body model: the implicit env has the explicit env's τ and η unless told otherwise
    assert envs.CreatureEnvConfig().time_constant == envs.config.ACTIVATION_TIME_CONSTANT == 0.05
    assert envs.CreatureEnvConfig().body_viscosity == envs.config.BODY_VISCOSITY == 30.0
    assert envs.CreatureEnvConfig(viscosity=0.0).body_viscosity == 0.0


def test_friction_smoothing_reaches_the_implicit_ground_and_bad_values_are_refused() -> None:
    from energysim.creatures import scene_ground
    from energysim.envs.config import FRICTION_SMOOTHING

    default = CreatureEnv("crawler2d")
    assert scene_ground(default.simulation.scene).friction_smoothing == FRICTION_SMOOTHING
    chosen = CreatureEnv("crawler2d", friction_smoothing=2e-3)
    assert scene_ground(chosen.simulation.scene).friction_smoothing == 2e-3
    for bad in (0.0, -1e-3, float("nan"), "0.01"):
        with pytest.raises(ValueError, match="friction_smoothing"):
            CreatureEnv("crawler2d", friction_smoothing=bad)


def test_the_implicit_grounds_barrier_range_is_the_envs_fraction_of_the_body_or_the_one_given() -> None:
    from energysim.envs.config import GROUND_BARRIER_DISTANCE_FRACTION

    default = CreatureEnv("crawler2d")
    low, high = default.simulation.creature.mesh.bounding_box()
    diagonal = float((high - low).norm())
    assert default.simulation.ground.barrier_distance == pytest.approx(
        GROUND_BARRIER_DISTANCE_FRACTION * diagonal, rel=1e-12
    )
    # the leapfrog's contact is at the surface: its ground keeps the `Ground` default (1e-3 × diagonal)
    explicit = CreatureEnv("crawler2d", integrator="leapfrog")
    assert explicit.simulation.ground.barrier_distance == pytest.approx(1e-3 * diagonal, rel=1e-12)
    d_hat = 2e-4
    chosen = CreatureVectorEnv(2, "crawler2d", barrier_distance=d_hat, activation_time_constant=0.0)
    assert chosen.simulation.ground.barrier_distance == d_hat
    # the reset rests each body on the chosen barrier, its lowest vertex at d̂/2; held still for
    # 10 steps it stays on it: above the ground and inside the barrier's range
    chosen.reset(seed=0)
    lowest = chosen.simulation.scene.split_state(chosen.states)[0][..., 1].amin(dim=-1)
    assert torch.allclose(lowest, torch.full_like(lowest, 0.5 * d_hat), rtol=1e-9, atol=0)
    for _ in range(10):
        chosen.step(np.zeros(chosen.action_space.shape, dtype=np.float32))
    lowest = chosen.simulation.scene.split_state(chosen.states)[0][..., 1].amin(dim=-1)
    assert bool(((lowest > 0) & (lowest < d_hat)).all()), lowest
    for bad in (0.0, -1e-3, float("inf"), "1e-3"):
        with pytest.raises(ValueError, match="barrier_distance"):
            CreatureEnv("crawler2d", barrier_distance=bad)
