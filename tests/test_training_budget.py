"""The training scripts' Newton budget (`--solver-budget`): it reaches the implicit env, bad values are
refused with errors that name `solver_budget`, a checkpoint records it and policy_transfer.py rebuilds
the run's env with it (its converged case still solved to its tolerance), and plot_training_curves.py
draws labelled curves.

The env step under a budget of k takes at most k Newton iterations (what the env reports), and the
rebuilt own env reproduces the run's own evaluation of the checkpoint.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("gymnasium")
pytest.importorskip("stable_baselines3")

from conftest import script_module  # noqa: E402

EPISODE_STEPS = 2
BUDGET = 2




training = script_module("_training")
train_ppo = script_module("train_ppo")
transfer = script_module("policy_transfer")
curves = script_module("plot_training_curves")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained train_ppo.py checkpoint of the implicit worm env under a budget (its first
    evaluation only)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        out = tmp_path_factory.mktemp("ppo_budget")
        settings = train_ppo.Settings(
            solver_budget=BUDGET, total_steps=0, episode_steps=EPISODE_STEPS, eval_episodes=1,
            num_envs=1, n_steps=2, batch_size=2, eval_every=2,
        )
        train_ppo.train(settings, out, progress=False)
    finally:
        torch.set_num_threads(threads)
    return out / train_ppo.MODEL_NAME


def test_the_flag_reaches_the_env_and_limits_its_newton_iterations() -> None:
    args = train_ppo.make_parser().parse_args(["--solver-budget", "3"])
    assert args.solver_budget == 3
    settings = train_ppo.Settings(solver_budget=3)
    assert settings.task.solver_budget == 3
    assert training.checkpoint_settings("ppo", settings)["solver_budget"] == 3
    assert training.Task(solver_budget=3).simulation().config.solver_budget == 3
    budgeted = training.Task(solver_budget=1, episode_steps=1).vector_env(2)
    converged = training.Task(episode_steps=1).vector_env(2)
    assert budgeted.config.solver_budget == 1
    assert converged.config.solver_budget is None
    infos = []
    for env in (budgeted, converged):
        env.reset(seed=0)
        actions = np.ones((2, env.single_action_space.shape[0]), dtype=np.float32)
        infos.append(env.step(actions)[-1])
    # a full contraction from rest takes several Newton iterations to solve; the budget allows one
    assert np.all(infos[1]["solver_iterations"] > 1)
    assert np.all(infos[0]["solver_iterations"] == 1)
    assert np.all(infos[0]["solver_residual"] > infos[1]["solver_residual"])


@pytest.mark.parametrize("bad", [0, -2, 2.5, "4", True])
def test_a_bad_budget_is_refused_naming_it(bad: object) -> None:
    with pytest.raises(ValueError, match="solver_budget must be an integer >= 1"):
        training.Task(solver_budget=bad)
    with pytest.raises(ValueError, match="solver_budget"):
        train_ppo.Settings(solver_budget=bad)


def test_a_budget_on_the_explicit_env_is_refused() -> None:
    with pytest.raises(ValueError, match="solver_budget = 4 is for integrator='implicit_euler'"):
        training.Task(solver_budget=4, integrator="leapfrog")


def test_the_command_line_refuses_a_bad_budget_before_training(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="solver_budget must be an integer >= 1, got 0"):
        train_ppo.main(["--solver-budget", "0", "--out", str(tmp_path / "run"), "--quiet"])
    assert not (tmp_path / "run").exists()


def test_policy_transfer_rebuilds_the_runs_budgeted_env(checkpoint: Path) -> None:
    policy = transfer.load_policy(checkpoint)
    assert policy.settings["solver_budget"] == BUDGET
    own = transfer.default_settings(policy, "implicit_euler")
    assert own.solver_budget == BUDGET
    assert transfer.transfer_env(policy, own, 1, EPISODE_STEPS).env.config.solver_budget == BUDGET
    # the run's own evaluation of the same policy on the same episode, in the same env
    curve = training.read_curve(checkpoint.parent / training.CURVE_NAME)
    rows, _ = transfer.evaluate_transfer(policy, [own], 1, EPISODE_STEPS)
    assert rows[0].solver_budget == BUDGET
    assert rows[0].mean_return == pytest.approx(curve[-1].eval_return, rel=1e-9, abs=1e-12)
    assert rows[0].newton_per_env_step <= BUDGET
    # the converged case solves to its own tolerance with no budget; the explicit env has none
    converged = transfer.transfer_env(policy, transfer.CONVERGED["implicit_euler"], 1, 1).env.config
    assert converged.solver_budget is None and converged.solver_tol == 1e-6
    assert transfer.default_settings(policy, "leapfrog").solver_budget is None


def test_a_checkpoint_without_a_budget_or_with_a_bad_one(checkpoint: Path) -> None:
    policy = transfer.load_policy(checkpoint)
    settings = {key: value for key, value in policy.settings.items() if key != "solver_budget"}
    older = transfer.Policy(policy.model, settings, policy.path)
    assert transfer.default_settings(older, "implicit_euler").solver_budget is None
    broken = transfer.Policy(policy.model, {**settings, "solver_budget": 0}, policy.path)
    with pytest.raises(ValueError, match=r"model\.zip: solver_budget must be an integer >= 1, got 0"):
        transfer.default_settings(broken, "implicit_euler")


def _curve(path: Path, returns: list[float]) -> Path:
    points = [
        training.CurvePoint("ppo", 100 * k, k, 10.0 * k, value, 0.1, 0.01 * k, 2, 0, 3.0, 1.0)
        for k, value in enumerate(returns)
    ]
    return training.write_curve(path, points)


def test_plot_training_curves_labels_each_run(tmp_path: Path) -> None:
    first = _curve(tmp_path / "a.csv", [0.0, 1.0, 5.0])
    second = _curve(tmp_path / "b.csv", [0.0, 0.5])
    out = tmp_path / "curves.png"
    points = curves.run([("explicit", first), ("implicit", second)], out)
    assert [p.method for p in points] == ["explicit"] * 3 + ["implicit"] * 2
    assert [p.eval_return for p in points] == [0.0, 1.0, 5.0, 0.0, 0.5]
    curves.check(points)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="--curve must be LABEL=PATH.*'nolabel.csv'"):
        curves.parse_curve("nolabel.csv")
    with pytest.raises(FileNotFoundError, match="curve 'x': no file at .*missing.csv"):
        curves.load_curves([("x", tmp_path / "missing.csv")])
    with pytest.raises(ValueError, match=r"\['a'\] given more than once"):
        curves.load_curves([("a", first), ("a", second)])
