"""The creature env on Ray: RLlib PPO on a local two-runner cluster, and a Tune sweep in parallel.

Skipped without the optional `ray` extra. The cluster is a local `ray.init(num_cpus=2)`.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ray.rllib")
pytest.importorskip("gymnasium")


from energysim.envs.rllib import (  # noqa: E402
    make_vector_env,
    ppo_config,
)
from energysim.envs.vector_env import CreatureVectorEnv  # noqa: E402

EPISODE_STEPS = 20
SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
FULL = os.environ.get("ENERGYSIM_HEAVY") == "1"
FULL_ITERATIONS = 25


def _script(name: str):
    # scripts/ is not a package: its modules are imported as top-level modules
    if str(SCRIPTS) not in sys.path:
        sys.path.insert(0, str(SCRIPTS))
    return importlib.import_module(name)


def test_importing_energysim_and_its_envs_does_not_import_ray():
    code = "import sys, energysim, energysim.envs; sys.exit('ray' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_runner_entries_are_seeded_apart_and_bad_arguments_are_named():
    # RLlib seeds runner w with seed + w; entry i of runner w must start from (seed + w)·B + i, as
    # CreatureVectorEnv's own entry seeded that way does
    config = {"num_envs": 2, "creature": "worm", "integrator": "leapfrog", "max_episode_steps": 3}
    first, second = make_vector_env(config), make_vector_env(config)
    obs_first, _ = first.reset(seed=1)
    obs_second, _ = second.reset(seed=2)
    reference = CreatureVectorEnv(4, "worm", integrator="leapfrog")
    obs_reference, _ = reference.reset(seed=2)
    np.testing.assert_array_equal(obs_first, obs_reference[:2])
    np.testing.assert_array_equal(obs_second, obs_reference[2:])
    with pytest.raises(ValueError, match="num_envs"):
        make_vector_env({"creature": "worm"})
    with pytest.raises(ValueError, match="creature"):
        ppo_config("snail")
    with pytest.raises(ValueError, match="num_envs_per_runner"):
        ppo_config("worm", num_envs_per_runner=0)
    with pytest.raises(ValueError, match="lr"):
        ppo_config("worm", lr=float("nan"))
    with pytest.raises(ValueError, match="gamma"):
        ppo_config("worm", gamma=1.5)
    with pytest.raises(ValueError, match="initial_log_std"):
        ppo_config("worm", initial_log_std=float("nan"))


@pytest.mark.heavy
def test_ppo_on_two_env_runners_learns_to_go_forward():
    # two runner actors, each stepping one batch of 16 worms on 60-step (1 s) episodes.
    # CI: 10 iterations (19,200 env steps). The greedy policy still stands still at this budget (its
    # distance changes sign from one evaluation to the next), so the check is on the exploring
    # policy, whose mean episode return rises by more than 2, i.e. 3.3 cm/s more forward speed
    # (measured +0.26 -> +5.1; random actions score -0.9).
    # Full (ENERGYSIM_HEAVY=1): the documented run (docs/scale-out.md); the greedy policy must go
    # forward, and farther than uniform random actions on the same episodes, by 3 s.e., and beat
    # their return by 3 s.e.
    ray_ppo = _script("ray_ppo")
    iterations, episodes = (FULL_ITERATIONS, 64) if FULL else (10, 32)
    result = ray_ppo.run(iterations=iterations, episodes=episodes)
    # a runner samples at least its 16 × 60 steps per iteration (more where an entry failed and restarted)
    assert result.env_steps >= iterations * 2 * 16 * 60
    first, last = result.exploring_returns[0], result.exploring_returns[-1]
    assert last > first + 2.0, result.exploring_returns
    if FULL:
        ray_ppo.check(result)


def test_tune_sweep_runs_two_trials_at_once(tmp_path):
    ray_tune_sweep = _script("ray_tune_sweep")
    lrs = [1e-4, 1e-3]
    rows = ray_tune_sweep.run(lrs, iterations=2, num_envs=16, episode_steps=EPISODE_STEPS)
    ray_tune_sweep.check(rows, lrs, iterations=2)
    assert [row.lr for row in rows] == lrs
    # two 1-CPU trials on two CPUs: each trained while the other did
    assert rows[0].start < rows[1].end and rows[1].start < rows[0].end
    assert all(row.env_steps == 2 * 16 * EPISODE_STEPS for row in rows)
    ray_tune_sweep.write(rows, tmp_path)
    assert (tmp_path / "sweep.csv").read_text().count("\n") == 3
