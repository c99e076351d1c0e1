"""scripts/policy_transfer.py: a train_ppo.py policy evaluated on its own and on the other integrator's env.

Checked on a tiny untrained checkpoint written by `train_ppo.train` itself: the own env at the
defaults reproduces the run's own evaluation (the curve's return), the other env is the env the
training scripts build for that integrator, a deterministic evaluation repeats exactly, the retention
ratio is the other return over the own one, and bad input raises errors that name it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("gymnasium")
pytest.importorskip("stable_baselines3")

from conftest import script_module  # noqa: E402

EPISODE_STEPS = 3




training = script_module("_training")
train_ppo = script_module("train_ppo")
transfer = script_module("policy_transfer")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained train_ppo.py checkpoint of the explicit worm env (its first evaluation only)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        out = tmp_path_factory.mktemp("ppo")
        settings = train_ppo.Settings(
            integrator="leapfrog", total_steps=0, episode_steps=EPISODE_STEPS, eval_episodes=1,
            num_envs=1, n_steps=2, batch_size=2, eval_every=2,
        )
        train_ppo.train(settings, out, progress=False)
    finally:
        torch.set_num_threads(threads)
    return out / train_ppo.MODEL_NAME


def test_own_env_reproduces_the_runs_evaluation_and_repeats(checkpoint: Path) -> None:
    policy = transfer.load_policy(checkpoint)
    assert policy.integrator == "leapfrog"
    curve = training.read_curve(checkpoint.parent / training.CURVE_NAME)
    own = transfer.default_settings(policy, "leapfrog")
    first, _ = transfer.evaluate_transfer(policy, [own], 1, EPISODE_STEPS)
    again, _ = transfer.evaluate_transfer(policy, [own], 1, EPISODE_STEPS)
    # the run's own evaluation of the same policy on the same episode: the same env, clock and filter
    assert first[0].mean_return == pytest.approx(curve[-1].eval_return, rel=1e-9, abs=1e-12)
    assert first[0].distance == pytest.approx(curve[-1].eval_distance, rel=1e-9, abs=1e-12)
    # deterministic policy, fixed seeds: the same return twice
    assert again[0].mean_return == first[0].mean_return
    if first[0].mean_return > 0:
        assert first[0].retention == 1.0
    else:
        assert math.isnan(first[0].retention)


def test_other_env_is_the_training_scripts_env_of_that_integrator(checkpoint: Path) -> None:
    policy = transfer.load_policy(checkpoint)
    other = transfer.default_settings(policy, "implicit_euler")
    rows, traces = transfer.evaluate_transfer(policy, [other], 1, EPISODE_STEPS)
    # the same policy evaluated by the training scripts' own env of the implicit task
    task = training.Task(episode_steps=EPISODE_STEPS, integrator="implicit_euler")
    frequency = transfer.transfer_env(policy, other, 1, EPISODE_STEPS).clock_frequency
    venv = training.make_vec_env(task, 1, frequency, policy.settings["action_tau"])
    reference = training.evaluate(venv, train_ppo.controller(policy.model))
    assert rows[0].mean_return == pytest.approx(reference.mean_return, rel=1e-9, abs=1e-12)
    assert rows[0].newton_per_env_step == pytest.approx(reference.solver_iterations)
    # the trace starts at rest on the ground and follows the evaluation's distance
    assert [t.step for t in traces] == list(range(EPISODE_STEPS + 1))
    assert traces[-1].x - traces[0].x == pytest.approx(rows[0].distance, rel=1e-9, abs=1e-12)
    assert 0.0 < traces[0].height < 0.1


def _row(env: str, settings: str, mean_return: float) -> object:
    return transfer.TransferRow(
        trained_on="leapfrog", env=env, settings=settings, dt=1 / 60, frame_skip=1, substeps=0,
        solver_tol=1e-4, episodes=2, episode_steps=120, mean_return=mean_return, return_stderr=0.0,
        distance=0.0, failures=0, newton_per_env_step=0.0, retention=math.nan, seconds=0.0,
    )


def test_retention_is_the_other_return_over_the_own_at_the_same_settings() -> None:
    rows = transfer.with_retention(
        [
            _row("leapfrog", "default", 150.0),
            _row("implicit_euler", "default", 30.0),
            _row("leapfrog", "converged", 160.0),
            _row("implicit_euler", "converged", 120.0),
        ]
    )
    assert [row.retention for row in rows] == [1.0, 0.2, 1.0, 0.75]
    transfer.check(rows)
    # no gain on the own env: no ratio
    lost = [_row("leapfrog", "default", -1.0), _row("implicit_euler", "default", 2.0)]
    assert np.isnan(transfer.with_retention(lost)[1].retention)


def test_converged_envs_keep_the_env_step_and_a_wrong_one_is_refused(checkpoint: Path) -> None:
    policy = transfer.load_policy(checkpoint)
    for env in transfer.CONVERGED.values():
        venv = transfer.transfer_env(policy, env, 1, EPISODE_STEPS)
        assert venv.frame_seconds == pytest.approx(1 / 60, rel=1e-12)
    explicit = transfer.transfer_env(policy, transfer.CONVERGED["leapfrog"], 1, 1)
    assert explicit.env.simulation.scene.substeps == 128
    wrong = transfer.EnvSettings("implicit_euler", "converged", dt=1 / 240, frame_skip=2)
    with pytest.raises(ValueError, match=r"frame_skip × dt.*2 ×"):
        transfer.transfer_env(policy, wrong, 1, EPISODE_STEPS)
    # `--implicit-frame-skip k`: the converged implicit step is 1/(60·k) s, the env step still 1/60 s
    finer = transfer.cases(policy, True, implicit_frame_skip=64)
    implicit = next(env for env in finer if env.label == "converged" and env.integrator == "implicit_euler")
    assert (implicit.frame_skip, implicit.dt, implicit.solver_tol) == (64, 1 / 3840, 1e-6)
    assert implicit.frame_skip * implicit.dt == pytest.approx(1 / 60, rel=1e-12)
    with pytest.raises(ValueError, match="implicit-frame-skip must be an integer >= 1"):
        transfer.main(["--model", str(checkpoint), "--implicit-frame-skip", "0"])


def test_bad_model_files_are_named(tmp_path: Path, checkpoint: Path) -> None:
    missing = tmp_path / "nothing.zip"
    with pytest.raises(FileNotFoundError, match="nothing.zip"):
        transfer.load_policy(missing)
    junk = tmp_path / "junk.zip"
    junk.write_text("not a model")
    with pytest.raises(ValueError, match="junk.zip"):
        transfer.load_policy(junk)
    # a PPO model file without train_ppo.py's run settings
    from stable_baselines3 import PPO

    plain = tmp_path / "plain.zip"
    model = PPO.load(checkpoint, device="cpu")
    delattr(model, train_ppo.RUN_ATTRIBUTE)
    model.save(plain)
    with pytest.raises(ValueError, match="plain.zip.*not a checkpoint of train_ppo.py"):
        transfer.load_policy(plain)
