"""Train a soft creature's controller with PPO (stable-baselines3) on the batched env.

The `--num-envs` creatures are one `CreatureVectorEnv` (one batched solve per env step), seen by SB3
through `_training.CreatureVecEnv`. The policy (SB3's MlpPolicy, Gaussian, two tanh layers of 64)
sees the env's observation plus clock features (sin 2πft, cos 2πft) at the creature's suggested gait
frequency f, and its output is an excitation that the muscles' activation follows with time constant
`--action-tau` (first-order activation dynamics, see `_training.py`): the gradient method's gaits
depend on time too, and jumping activations in [−1, 1] at every step cost the solver about three
times as many Newton iterations (docs/training.md). `--no-clock` and `--action-tau 0` turn these off.

Every `--eval-every` env steps (a multiple of num_envs × n_steps): the deterministic policy is
evaluated on the fixed evaluation seeds, a row is added to ``curve.csv`` and a checkpoint is written
(policy, optimizer, global RNG states, counters, the curve so far). The training envs are then reset
with seeds derived from (seed, evaluation index): the env's state is not saved, and an uninterrupted
run re-seeds at the same points, so `--resume` continues the very same curve.

Run:  python scripts/train_ppo.py                       # worm, about 15 min on 2 cores
      python scripts/train_ppo.py --total-steps 256 --eval-every 128 --num-envs 4 --n-steps 32 --out /tmp/p
      python scripts/train_ppo.py --resume              # continue an interrupted run's curve
      python scripts/train_ppo.py --compile             # compiled physics: faster steps after compiling
Writes to --out: curve.csv, checkpoint.pt, training.png, rollout/frame_*.vtu + frame.pvd, NAME.gif.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _training import (
    CHECKPOINT_NAME,
    CreatureVecEnv,
    CurvePoint,
    Evaluation,
    RunSettings,
    check_integer,
    check_number,
    checkpoint_settings,
    common_parser,
    evaluate,
    load_run,
    log_evaluation,
    make_vec_env,
    plot_curves,
    progress_bar,
    script_main,
    timed_evaluation,
    write_policy_outputs,
)

METHOD = "ppo"


@dataclass(frozen=True)
class Settings(RunSettings):
    """One PPO training run (the command line's flags; module docstring)."""

    num_envs: int = 8
    total_steps: int = 3840
    learning_rate: float = 3e-4
    eval_every: int = 960
    n_steps: int = 60
    batch_size: int = 120
    n_epochs: int = 10
    gamma: float = 0.98
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    log_std_init: float = -1.0
    hidden: int = 64
    clock: bool = True
    action_tau: float = 0.1

    def __post_init__(self) -> None:
        super().__post_init__()
        check_integer(self.n_steps, "n_steps", 1)
        check_integer(self.batch_size, "batch_size", 2)
        check_integer(self.n_epochs, "n_epochs", 1)
        for name in ("gamma", "gae_lambda"):
            value = check_number(getattr(self, name), name, 0.0)
            if value > 1:
                raise ValueError(f"{name} must lie in [0, 1], got {value}")
        check_number(self.clip_range, "clip_range", 0.0, strict=True)
        check_number(self.ent_coef, "ent_coef", 0.0)
        check_number(self.log_std_init, "log_std_init")
        check_integer(self.hidden, "hidden", 1)
        check_number(self.action_tau, "action_tau", 0.0)
        rollout = self.num_envs * self.n_steps
        if self.eval_every % rollout:
            raise ValueError(
                f"eval_every must be a multiple of num_envs × n_steps = {rollout} (PPO updates after each "
                f"{rollout} env steps), got {self.eval_every}"
            )
        if self.batch_size > rollout:
            raise ValueError(
                f"batch_size must be at most num_envs × n_steps = {rollout}, got {self.batch_size}"
            )


def vec_env(settings: Settings, num_envs: int) -> CreatureVecEnv:
    """The SB3 view of `num_envs` creatures with the run's clock and activation dynamics."""
    from energysim.creatures import load_creature

    frequency = load_creature(settings.creature).gait_frequency if settings.clock else None
    return make_vec_env(settings.task, num_envs, frequency, settings.action_tau)


def build_model(settings: Settings, venv: CreatureVecEnv) -> Any:
    """A fresh SB3 PPO on `venv` with the run's hyperparameters (seeded with `settings.seed`), and a
    logger that writes nothing: the run's own curve and checkpoints are its record."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import Logger

    model = PPO(
        "MlpPolicy",
        venv,
        n_steps=settings.n_steps,
        batch_size=min(settings.batch_size, venv.num_envs * settings.n_steps),
        n_epochs=settings.n_epochs,
        learning_rate=settings.learning_rate,
        gamma=settings.gamma,
        gae_lambda=settings.gae_lambda,
        clip_range=settings.clip_range,
        ent_coef=settings.ent_coef,
        policy_kwargs={"log_std_init": settings.log_std_init, "net_arch": [settings.hidden, settings.hidden]},
        seed=settings.seed,
        device="cpu",
        verbose=0,
    )
    # SB3's default logger makes a fresh folder under the system temp directory on every learn()
    # call, even with no output format, and leaves it there empty
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def controller(model: Any) -> Any:
    """The evaluation controller: the policy's mean action."""

    def act(observations: np.ndarray, times: np.ndarray) -> np.ndarray:
        actions, _ = model.predict(observations, deterministic=True)
        return actions

    return act


def training_seed(seed: int, chunk: int, num_envs: int) -> int:
    """Seed of the training envs from evaluation `chunk` on (entry i gets this + i): distinct for
    every (seed, chunk) and far from the evaluation seeds."""
    return (seed * 100_003 + chunk) * num_envs


def train(settings: Settings, out: Path, *, resume: bool = False, progress: bool = True) -> list[CurvePoint]:
    """Train, evaluating and checkpointing every `eval_every` env steps; returns the curve.

    With `resume`, continue from ``out/checkpoint.pt`` (same settings, except total_steps), so the
    curve continues exactly as an uninterrupted run's would.
    """
    from stable_baselines3.common.callbacks import BaseCallback

    venv = vec_env(settings, settings.num_envs)
    evaluation_env = vec_env(settings, settings.eval_episodes)
    model = build_model(settings, venv)
    fixed = checkpoint_settings(METHOD, settings)
    curve: list[CurvePoint] = []
    wall = 0.0
    if resume:
        saved, curve = load_run(out, fixed, model.policy, model.policy.optimizer)
        model.num_timesteps, model._n_updates = saved["env_steps"], saved["updates"]
        wall = saved["wall_seconds"]

    def checkpoint_and_log(result: Evaluation, seconds: float) -> None:
        updates = model._n_updates // settings.n_epochs
        point = CurvePoint.of(METHOD, model.num_timesteps, updates, wall, result, seconds)
        counters = {"env_steps": model.num_timesteps, "updates": model._n_updates, "wall_seconds": wall}
        log_evaluation(out, curve, point, (fixed, model.policy, model.policy.optimizer, counters), progress)

    if not curve:
        checkpoint_and_log(*timed_evaluation(evaluation_env, controller(model)))
    bar = progress_bar(METHOD, settings, model.num_timesteps, progress)

    class Progress(BaseCallback):
        def _on_step(self) -> bool:
            bar.update(settings.num_envs)
            return True

    while model.num_timesteps < settings.total_steps:
        chunk = len(curve)  # evaluations so far: the training envs' seeds follow it
        venv.seed(training_seed(settings.seed, chunk, settings.num_envs))
        model._last_obs = None  # learn() resets the envs with those seeds
        steps = min(settings.eval_every, settings.total_steps - model.num_timesteps)
        steps = -(-steps // (settings.num_envs * settings.n_steps)) * settings.num_envs * settings.n_steps
        start = time.perf_counter()
        model.learn(steps, callback=Progress(), reset_num_timesteps=False)
        wall += time.perf_counter() - start
        checkpoint_and_log(*timed_evaluation(evaluation_env, controller(model)))
    bar.close()
    return curve


def outputs(settings: Settings, out: Path, curve: list[CurvePoint], render: bool = True) -> list[Path]:
    """The learning-curve PNG and VTK frames (+ GIF) of the trained policy from the checkpoint."""
    venv = vec_env(settings, 1)
    model = build_model(settings, venv)
    model.policy.load_state_dict(torch.load(out / CHECKPOINT_NAME, weights_only=True)["policy"])
    result = evaluate(venv, controller(model), record=True)
    written = [plot_curves(curve, out / "training.png", f"{settings.creature}: PPO")]
    written += write_policy_outputs(venv.env.simulation.scene, result, out, settings.creature, render=render)
    return written


def make_parser() -> argparse.ArgumentParser:
    """The shared training flags and this method's own."""
    parser = common_parser(__doc__, Settings(), METHOD)
    add = parser.add_argument
    add("--n-steps", type=int, default=Settings.n_steps, help="env steps per entry between PPO updates")
    add("--batch-size", type=int, default=Settings.batch_size, help="PPO minibatch size")
    add("--n-epochs", type=int, default=Settings.n_epochs, help="PPO epochs per update")
    add("--gamma", type=float, default=Settings.gamma, help="discount")
    add("--log-std-init", type=float, default=Settings.log_std_init, help="initial log std of the policy")
    add("--hidden", type=int, default=Settings.hidden, help="width of the two hidden layers")
    add("--no-clock", dest="clock", action="store_false", help="no clock features in the observation")
    tau_help = "activation time constant in s; 0: none"
    add("--action-tau", type=float, default=Settings.action_tau, help=tau_help)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Command line entry point (module docstring); returns 0."""
    return script_main(argv, make_parser(), Settings, train, outputs, METHOD)


if __name__ == "__main__":
    sys.exit(main())
