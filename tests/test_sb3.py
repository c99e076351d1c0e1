"""stable-baselines3 on the creature envs: the env checkers, the `SB3VecEnv` adapter against SB3's own
`DummyVecEnv` of single envs, PPO's save/load round trip and `SubprocVecEnv`.

The envs run the explicit (leapfrog) physics: no solver tolerance, so batched and single envs agree
to rounding, and steps are cheap.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

gymnasium = pytest.importorskip("gymnasium")
pytest.importorskip("stable_baselines3")

import energysim.envs  # noqa: E402,F401 - registers the ids
from energysim.envs import CreatureVectorEnv, SB3VecEnv  # noqa: E402

ID = "energysim/Worm-v0"
OPTIONS = {"integrator": "leapfrog"}
STEPS = 3  # episode length


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _single_env():
    return gymnasium.make(ID, max_episode_steps=STEPS, **OPTIONS)


def _actions(rng: np.random.Generator, num_envs: int) -> np.ndarray:
    return rng.uniform(-1.0, 1.0, (num_envs, 10)).astype(np.float32)


def test_single_env_passes_gymnasium_and_sb3_env_checkers() -> None:
    from gymnasium.utils.env_checker import check_env as gymnasium_check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    gymnasium_check_env(gymnasium.make(ID, **OPTIONS).unwrapped, skip_render_check=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any complaint of SB3's checker fails the test
        sb3_check_env(_single_env(), warn=True)


def test_adapter_matches_sb3_dummy_vec_env_of_single_envs() -> None:
    # SB3's reference VecEnv (DummyVecEnv: same-step autoreset of gymnasium.make envs with TimeLimit)
    # against the adapter over one batched env, from the same seeds and actions
    from stable_baselines3.common.vec_env import DummyVecEnv

    num_envs = 2
    adapter = SB3VecEnv(
        gymnasium.make_vec(
            ID, num_envs, vectorization_mode="vector_entry_point", max_episode_steps=STEPS, **OPTIONS
        )
    )
    reference = DummyVecEnv([_single_env for _ in range(num_envs)])
    assert adapter.observation_space == reference.observation_space
    assert adapter.action_space == reference.action_space
    assert adapter.num_envs == reference.num_envs == num_envs
    assert adapter.seed(5) == reference.seed(5) == [5, 6]
    observations, expected = adapter.reset(), reference.reset()
    assert observations.dtype == np.float32 and observations.shape == (num_envs, 92)
    np.testing.assert_allclose(observations, expected, rtol=1e-6, atol=1e-7)
    rng = np.random.default_rng(0)
    ended = 0
    for k in range(2 * STEPS + 1):
        actions = _actions(rng, num_envs)
        observations, rewards, dones, infos = adapter.step(actions)
        expected, expected_rewards, expected_dones, expected_infos = reference.step(actions)
        assert rewards.dtype == np.float32 and rewards.shape == (num_envs,)
        assert dones.dtype == np.bool_ and dones.tolist() == expected_dones.tolist()
        assert dones.tolist() == [(k + 1) % STEPS == 0] * num_envs
        # after an end, the returned observation is already the reset one, in both
        np.testing.assert_allclose(observations, expected, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(rewards, expected_rewards, rtol=1e-5, atol=1e-7)
        for info, expected_info in zip(infos, expected_infos, strict=True):
            assert info["x_position"] == pytest.approx(expected_info["x_position"], abs=1e-9)
            if "terminal_observation" in expected_info:
                ended += 1
                assert info["TimeLimit.truncated"] is expected_info["TimeLimit.truncated"] is True
                np.testing.assert_allclose(
                    info["terminal_observation"], expected_info["terminal_observation"], rtol=1e-6, atol=1e-7
                )
                assert info["episode"]["l"] == STEPS
            else:
                assert "terminal_observation" not in info and "episode" not in info
    assert ended == 2 * num_envs


def test_adapter_episode_return_attributes_render_and_errors() -> None:
    num_envs = 2
    adapter = SB3VecEnv(
        CreatureVectorEnv(num_envs, max_episode_steps=STEPS, **OPTIONS), render_mode="rgb_array"
    )
    adapter.seed(1)
    adapter.reset()
    rng = np.random.default_rng(1)
    total = np.zeros(num_envs)
    for _ in range(STEPS):
        _, _, dones, infos = adapter.step(_actions(rng, num_envs))
        total += adapter.rewards
    assert dones.all()
    np.testing.assert_allclose([info["episode"]["r"] for info in infos], total, rtol=1e-12)
    assert adapter.get_attr("elapsed_steps") == [0, 0]  # reset at once
    states = adapter.get_attr("states", indices=[1])
    assert len(states) == 1 and torch.equal(states[0], adapter.env.states[1])
    assert adapter.get_attr("render_mode") == ["rgb_array"] * num_envs
    assert adapter.env_method("reset", seed=3)[0][0].shape == (num_envs, 92)
    image = adapter.render()
    single = adapter.get_images()[0]
    assert image.dtype == np.uint8 and image.shape == (2 * single.shape[0], single.shape[1], 3)
    with pytest.raises(TypeError, match="SB3VecEnv wraps a CreatureVectorEnv"):
        SB3VecEnv(_single_env())
    with pytest.raises(ValueError, match="render_mode must be None or one of"):
        SB3VecEnv(adapter.env, render_mode="human")
    with pytest.raises(ValueError, match="indices must select all of them"):
        adapter.env_method("reset", indices=[0])
    with pytest.raises(IndexError, match=r"indices \[5\] out of range for 2 entries"):
        adapter.get_attr("states", indices=5)
    with pytest.raises(RuntimeError, match="step_async"):
        adapter.step_wait()
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 10\)"):
        adapter.step(np.zeros((2, 3)))


def test_ppo_learns_then_save_load_round_trip_gives_identical_actions(tmp_path: Path) -> None:
    from stable_baselines3 import PPO

    adapter = SB3VecEnv(CreatureVectorEnv(4, max_episode_steps=10, **OPTIONS))
    model = PPO("MlpPolicy", adapter, n_steps=16, batch_size=32, n_epochs=2, seed=0, device="cpu")
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.learn(128)
    assert model.num_timesteps == 128 and len(model.ep_info_buffer) == 4 * 128 // (4 * 10)
    assert any(not torch.equal(before[k], v) for k, v in model.policy.state_dict().items())
    model.save(tmp_path / "worm")
    loaded = PPO.load(tmp_path / "worm.zip", env=adapter, device="cpu")
    adapter.seed(9)
    observations = adapter.reset()
    for deterministic in (True, False):
        torch.manual_seed(3)
        actions, _ = model.predict(observations, deterministic=deterministic)
        torch.manual_seed(3)
        again, _ = loaded.predict(observations, deterministic=deterministic)
        np.testing.assert_array_equal(again, actions)


def test_subproc_vec_env_matches_dummy_vec_env() -> None:
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    factories = [_single_env for _ in range(2)]
    subproc = SubprocVecEnv(factories, start_method="spawn")
    try:
        dummy = DummyVecEnv(factories)
        subproc.seed(11)
        dummy.seed(11)
        np.testing.assert_array_equal(subproc.reset(), dummy.reset())
        rng = np.random.default_rng(2)
        for k in range(STEPS + 1):
            actions = _actions(rng, 2)
            observations, rewards, dones, infos = subproc.step(actions)
            expected, expected_rewards, expected_dones, expected_infos = dummy.step(actions)
            # the same computation in another process: equal to rounding
            np.testing.assert_allclose(observations, expected, rtol=1e-6, atol=1e-7)
            np.testing.assert_allclose(rewards, expected_rewards, rtol=1e-6, atol=1e-8)
            assert dones.tolist() == expected_dones.tolist() == [k + 1 == STEPS] * 2
            if k + 1 == STEPS:
                for info, expected_info in zip(infos, expected_infos, strict=True):
                    np.testing.assert_allclose(
                        info["terminal_observation"],
                        expected_info["terminal_observation"],
                        rtol=1e-6,
                        atol=1e-7,
                    )
    finally:
        subproc.close()
