"""Train a soft creature's controller with PPO (stable-baselines3) on the batched env.

The `--num-envs` creatures are one `CreatureVectorEnv` (one batched solve per env step), seen by SB3
through `_training.CreatureVecEnv` (the public `energysim.envs.SB3VecEnv` plus the controller's clock).
The policy (SB3's MlpPolicy, Gaussian, two tanh layers of 64)
sees the env's observation plus clock features (sin 2πft, cos 2πft) at the creature's suggested gait
frequency f, and its output is an excitation that the muscles' activation follows with time constant
`--action-tau` (first-order activation dynamics, see `_training.py`): the gradient method's gaits
depend on time too, and jumping activations in [−1, 1] at every step cost the solver about three
times as many Newton iterations (docs/training.md). `--no-clock` and `--action-tau 0` turn these off.

Every `--eval-every` env steps (a multiple of num_envs × n_steps) an SB3 callback evaluates the
deterministic policy on the fixed evaluation seeds, logs it to SB3's logger, adds a row to
``curve.csv`` and saves ``model.zip`` with SB3's `model.save` (`PPO.load` reads it), carrying the
run's settings, curve and global RNG states. The training envs are then reset
with seeds derived from (seed, evaluation index): the env's state is not saved, and an uninterrupted
run re-seeds at the same points, so `--resume` continues the very same curve.

Run:  python scripts/train_ppo.py                       # worm, about 15 min on 2 cores
      python scripts/train_ppo.py --total-steps 256 --eval-every 128 --num-envs 4 --n-steps 32 --out /tmp/p
      python scripts/train_ppo.py --resume              # continue an interrupted run's curve
      python scripts/train_ppo.py --compile             # compiled physics: faster steps after compiling
Writes to --out: curve.csv, model.zip, logs/N/progress.csv (+ TensorBoard events when installed),
training.png, rollout/frame_*.vtu + frame.pvd, NAME.gif.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _training import (
    CURVE_NAME,
    CreatureVecEnv,
    CurvePoint,
    RunSettings,
    atomic_write,
    check_integer,
    check_number,
    check_settings,
    checkpoint_settings,
    common_parser,
    evaluate,
    make_vec_env,
    plot_curves,
    progress_bar,
    report_evaluation,
    rng_state,
    script_main,
    set_rng_state,
    timed_evaluation,
    write_curve,
    write_policy_outputs,
)
from stable_baselines3.common.callbacks import BaseCallback

METHOD = "ppo"
# the checkpoint: an SB3 model file (`PPO.load` reads it) that also carries the run's state
MODEL_NAME = "model.zip"
# the model attribute that holds the run's state (settings, curve, global random states, wall time)
RUN_ATTRIBUTE = "training_run"
# SB3's logs, one folder per training session
LOG_FOLDER = "logs"


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
    """A fresh SB3 PPO on `venv` with the run's hyperparameters, seeded with `settings.seed`."""
    from stable_baselines3 import PPO

    return PPO(
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


def run_logger(out: Path) -> Any:
    """SB3's logger for one training session: CSV, and TensorBoard when it is installed, in a fresh
    folder ``out/logs/N`` (N = 1, 2, ... per session, so a resumed run keeps the logs before it)."""
    from stable_baselines3.common.logger import configure

    formats = ["csv"]
    if importlib.util.find_spec("tensorboard") is not None:
        formats.append("tensorboard")
    logs = out / LOG_FOLDER
    session = 1 + max((int(p.name) for p in logs.glob("*") if p.name.isdigit()), default=0)
    return configure(str(logs / str(session)), formats)


def save_model(model: Any, path: Path) -> Path:
    """`model.save` to a temporary file beside `path`, then renamed: the checkpoint is whole or absent."""
    return atomic_write(path, lambda temporary: model.save(temporary))


def load_model(path: Path, fixed: dict[str, Any], venv: CreatureVecEnv) -> Any:
    """`PPO.load` of a checkpoint written with the settings `fixed`, on `venv`, with the global random
    states restored to the checkpoint's.

    Raises:
        FileNotFoundError: there is no checkpoint at `path`.
        ValueError: it was written with other settings (named).
    """
    from stable_baselines3 import PPO

    if not path.is_file():
        raise FileNotFoundError(f"--resume: no checkpoint at {path}; run without --resume to start afresh")
    model = PPO.load(path, env=venv, device="cpu")
    run = getattr(model, RUN_ATTRIBUTE, None)
    if not isinstance(run, dict) or "settings" not in run:
        raise ValueError(f"--resume: {path} is a PPO model but not a checkpoint of train_ppo.py")
    check_settings(path, run["settings"], fixed)
    # PPO.load seeds the global generators with the model's seed; continue from the checkpoint's
    set_rng_state(run["rng"])
    return model


class EvaluateAndCheckpoint(BaseCallback):
    """Every `eval_every` env steps (at the start of the rollout after the update that reached it) and
    at the end of training: evaluate the deterministic policy, log it to SB3's logger ("eval/..."),
    add a row to ``curve.csv`` and save the model with the run's state (settings, curve, global random
    states, training wall time) to ``model.zip``; then re-seed and reset the training envs.

    Args:
        settings: the run's settings.
        out: the output folder.
        evaluation_env: the env of the evaluation episodes.
        curve: the curve so far (appended to).
        wall: training wall time so far, in s.
        progress: print each evaluation above the progress bar.
    """

    def __init__(
        self,
        settings: Settings,
        out: Path,
        evaluation_env: CreatureVecEnv,
        curve: list[CurvePoint],
        wall: float,
        progress: bool,
    ) -> None:
        super().__init__()
        self.settings = settings
        self.out = out
        self.evaluation_env = evaluation_env
        self.curve = curve
        self.wall = wall
        self.progress = progress
        self.fixed = checkpoint_settings(METHOD, settings)
        self._since = time.perf_counter()

    def evaluate_and_checkpoint(self) -> None:
        """Evaluate, log, save; training time stops counting meanwhile."""
        self.wall += time.perf_counter() - self._since
        model = self.model
        result, seconds = timed_evaluation(self.evaluation_env, controller(model))
        updates = model._n_updates // self.settings.n_epochs
        point = CurvePoint.of(METHOD, model.num_timesteps, updates, self.wall, result, seconds)
        self.curve.append(point)
        for key, value in (
            ("return", point.eval_return),
            ("return_stderr", point.eval_return_stderr),
            ("distance", point.eval_distance),
            ("failures", point.eval_failures),
            ("solver_iterations", point.eval_solver_iterations),
        ):
            self.logger.record(f"eval/{key}", value)
        self.logger.dump(model.num_timesteps)
        run = {
            "settings": self.fixed,
            "curve": [asdict(p) for p in self.curve],
            "rng": rng_state(),
            "wall_seconds": self.wall,
        }
        setattr(model, RUN_ATTRIBUTE, run)
        save_model(model, self.out / MODEL_NAME)
        write_curve(self.out / CURVE_NAME, self.curve)
        if self.progress:
            report_evaluation(point)
        self._since = time.perf_counter()

    def _on_training_start(self) -> None:
        self._since = time.perf_counter()

    def _on_rollout_start(self) -> None:
        due = self.num_timesteps % self.settings.eval_every == 0
        if due and self.num_timesteps > self.curve[-1].env_steps:
            self.evaluate_and_checkpoint()
            reseed(self.model, self.settings, len(self.curve))
            self.model._last_obs = self.model.env.reset()
            self.model._last_episode_starts = np.ones(self.model.env.num_envs, dtype=bool)

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        if self.num_timesteps > self.curve[-1].env_steps:
            self.evaluate_and_checkpoint()


class ProgressBar(BaseCallback):
    """A tqdm bar over the run's env steps."""

    def __init__(self, settings: Settings, done: int, progress: bool) -> None:
        super().__init__()
        self.bar = progress_bar(METHOD, settings, done, progress)
        self.step = settings.num_envs

    def _on_step(self) -> bool:
        self.bar.update(self.step)
        return True

    def _on_training_end(self) -> None:
        self.bar.close()


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


def reseed(model: Any, settings: Settings, chunk: int) -> None:
    """Seed the next reset of `model`'s training envs for evaluation `chunk` (`training_seed`)."""
    model.env.seed(training_seed(settings.seed, chunk, settings.num_envs))


def train(
    settings: Settings,
    out: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    callback: Any = None,
) -> list[CurvePoint]:
    """Train with one `model.learn`, evaluating and checkpointing every `eval_every` env steps (an SB3
    callback, `EvaluateAndCheckpoint`); returns the curve.

    With `resume`, continue from ``out/model.zip`` (same settings, except total_steps and
    solver_compile), so the curve continues exactly as an uninterrupted run's would. `callback`: SB3
    callbacks (one or a list) to run besides the run's own.
    """
    from stable_baselines3.common.callbacks import CallbackList

    out = Path(out)
    venv = vec_env(settings, settings.num_envs)
    evaluation_env = vec_env(settings, settings.eval_episodes)
    fixed = checkpoint_settings(METHOD, settings)
    if resume:
        model = load_model(out / MODEL_NAME, fixed, venv)
        run = getattr(model, RUN_ATTRIBUTE)
        curve, wall = [CurvePoint(**row) for row in run["curve"]], float(run["wall_seconds"])
    else:
        model = build_model(settings, venv)
        curve, wall = [], 0.0
    model.set_logger(run_logger(out))
    evaluation = EvaluateAndCheckpoint(settings, out, evaluation_env, curve, wall, progress)
    if not curve:
        evaluation.init_callback(model)
        evaluation.evaluate_and_checkpoint()
    extra = [] if callback is None else callback if isinstance(callback, list) else [callback]
    callbacks = CallbackList([evaluation, ProgressBar(settings, model.num_timesteps, progress), *extra])
    remaining = settings.total_steps - model.num_timesteps
    if remaining > 0:
        reseed(model, settings, len(curve))
        model._last_obs = None  # learn() resets the envs with those seeds
        model.learn(remaining, callback=callbacks, reset_num_timesteps=False)
    return curve


def outputs(settings: Settings, out: Path, curve: list[CurvePoint], render: bool = True) -> list[Path]:
    """The learning-curve PNG and VTK frames (+ GIF) of the trained policy from the checkpoint."""
    from stable_baselines3 import PPO

    venv = vec_env(settings, 1)
    model = PPO.load(Path(out) / MODEL_NAME, device="cpu")
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
