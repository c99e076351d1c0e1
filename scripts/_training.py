"""What the training scripts share: the task, the controller's view of the batched env (an
`energysim.envs.SB3VecEnv`), evaluation, the learning curve, checkpoints and plots.

`train_ppo.py` (stable-baselines3 PPO) and `train_gradient.py` (backpropagation through the simulator)
train controllers for the same task and log the same curve, so their curves can be drawn on one plot:

    python scripts/_training.py --curves out/train_ppo/curve.csv out/train_gradient/curve.csv \\
        --out docs/benchmarks

writes ``training.csv`` (both curves), ``training.md`` (a table) and ``training.png``.

The task (`Task`): a shipped creature in `CreatureVectorEnv` with the env's physics, reward and
defaults, episodes of `episode_steps` env steps. Evaluation (`evaluate`) runs the deterministic
controller on the fixed seeds `EVAL_SEED`, `EVAL_SEED` + 1, ... (the same episodes for every method
and every evaluation) and reports the mean undiscounted return and the forward distance of the
centre of mass.

A controller sees the env's observation and the time t = k · frame_skip · h of the state it acts on
(k env steps into the episode). Two optional pieces belong to the controller, not to the physics
(`CreatureVecEnv`):
- clock features (sin 2πft, cos 2πft) appended to the observation at a fixed frequency f;
- first-order activation dynamics: the controller's output u is an excitation, and the activation
  sent to the env follows it with time constant τ, a_k = a_{k−1} + (1 − e^{−Δt/τ})(u_k − a_{k−1}),
  a_{−1} = 0, as MuJoCo's muscle ``dyntype="filter"``. The env's observation already holds the last
  activation, so the controller stays Markov.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import random
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from energysim.cpu import configure as configure_cpu
from energysim.envs import SB3VecEnv
from energysim.envs.config import check_integer, check_number

# the evaluation episodes' seeds: EVAL_SEED + i, the same for every method, run and evaluation
EVAL_SEED = 1_000_000
CURVE_NAME = "curve.csv"
CHECKPOINT_NAME = "checkpoint.pt"
# the env's per-entry info that CreatureVecEnv passes on
INFO_KEYS = (
    "x_position",
    "x_velocity",
    "reward_forward",
    "reward_ctrl",
    "solver_iterations",
    "numerical_failure",
)

# controller: (observation [B, o] float32, time of the state [B] in s) -> action [B, a] in [-1, 1]
Controller = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Task:
    """The task both training methods solve and are evaluated on.

    Attributes:
        creature: a name in `energysim.creatures.CREATURES`.
        episode_steps: env steps per episode (training and evaluation), each frame_skip · h long.
        frame_skip: physics steps per env step.
        solver_tol: the env's Newton–CG velocity-residual tolerance in m/s.
        solver_compile: the env evaluates its step objective by compiled functions
            (`CreatureEnvConfig.solver_compile`): faster steps after a compilation of 15 s to a minute.
        integrator: the env's physics, "implicit_euler" or "leapfrog" (`CreatureEnvConfig`). Either
            way the env itself filters no activation: the controllers do (PPO's `--action-tau`,
            the gradient method's smooth gaits), as they did before the envs could.
        solver_budget: None: every implicit step is solved to `solver_tol`. An integer k >= 1: at
            most k Newton iterations per physics step, the last iterate kept
            (`CreatureEnvConfig.solver_budget`). Only with the implicit integrator: an explicit
            step solves nothing.
    """

    creature: str = "worm"
    episode_steps: int = 120
    frame_skip: int = 1
    solver_tol: float = 1e-4
    solver_compile: bool = False
    integrator: str = "implicit_euler"
    solver_budget: int | None = None

    def __post_init__(self) -> None:
        from energysim.creatures import CREATURES

        if self.creature not in CREATURES:
            raise ValueError(f"unknown creature {self.creature!r}; choose one of {CREATURES}")
        check_integer(self.episode_steps, "episode_steps", 1)
        check_integer(self.frame_skip, "frame_skip", 1)
        check_number(self.solver_tol, "solver_tol", 0.0, strict=True)
        if not isinstance(self.solver_compile, bool):
            raise ValueError(f"solver_compile must be True or False, got {self.solver_compile!r}")
        if self.integrator not in ("implicit_euler", "leapfrog"):
            raise ValueError(f"integrator must be 'implicit_euler' or 'leapfrog', got {self.integrator!r}")
        if self.solver_budget is not None:
            check_integer(self.solver_budget, "solver_budget", 1)
            if self.integrator != "implicit_euler":
                raise ValueError(
                    f"solver_budget = {self.solver_budget} is for integrator='implicit_euler' (Newton "
                    f"iterations per step); integrator={self.integrator!r} solves nothing"
                )

    def _env_options(self) -> dict[str, Any]:
        # the env filters no activation: the controllers do (see the module docstring)
        return dict(
            creature=self.creature,
            frame_skip=self.frame_skip,
            solver_tol=self.solver_tol,
            solver_budget=self.solver_budget,
            solver_compile=self.solver_compile,
            max_episode_steps=self.episode_steps,
            integrator=self.integrator,
            activation_time_constant=0.0,
        )

    def vector_env(self, num_envs: int) -> Any:
        """A `CreatureVectorEnv` of `num_envs` creatures for this task (float64, CPU)."""
        from energysim.envs import CreatureVectorEnv

        return CreatureVectorEnv(check_integer(num_envs, "num_envs", 1), **self._env_options())

    def simulation(self) -> Any:
        """The batched `CreatureSimulation` of this task (what `vector_env` steps)."""
        from energysim.envs import CreatureEnvConfig, CreatureSimulation

        return CreatureSimulation(CreatureEnvConfig(**self._env_options()))


@dataclass(frozen=True)
class RunSettings:
    """What a run of either training method is given (the flags both scripts take); each script's
    `Settings` adds its method's own fields and may change the defaults."""

    creature: str = "worm"
    num_envs: int = 1
    total_steps: int = 3000
    episode_steps: int = 120
    learning_rate: float = 0.05
    seed: int = 0
    eval_every: int = 600
    eval_episodes: int = 2
    solver_tol: float = 1e-4
    solver_compile: bool = False
    integrator: str = "implicit_euler"
    solver_budget: int | None = None

    def __post_init__(self) -> None:
        self.task  # noqa: B018 - building the task checks its fields
        check_integer(self.num_envs, "num_envs", 1)
        check_integer(self.total_steps, "total_steps", 0)
        check_number(self.learning_rate, "learning_rate", 0.0, strict=True)
        check_integer(self.seed, "seed", 0)
        check_integer(self.eval_every, "eval_every", 1)
        check_integer(self.eval_episodes, "eval_episodes", 1)

    @property
    def task(self) -> Task:
        return Task(
            self.creature,
            self.episode_steps,
            1,
            self.solver_tol,
            self.solver_compile,
            self.integrator,
            self.solver_budget,
        )


def make_vec_env(
    task: Task, num_envs: int, clock_frequency: float | None = None, action_time_constant: float = 0.0
) -> CreatureVecEnv:
    """A `CreatureVecEnv` (stable-baselines3 `VecEnv`) over a fresh `CreatureVectorEnv` of `task`."""
    return CreatureVecEnv(task.vector_env(num_envs), clock_frequency, action_time_constant)


class CreatureVecEnv(SB3VecEnv):
    """`energysim.envs.SB3VecEnv` with the controller's own pieces (module docstring): clock features
    appended to the observation and first-order activation dynamics between the action and the env.

    Everything SB3 sees follows `SB3VecEnv`: same-step autoreset, ``info["terminal_observation"]``
    (with the clock of the episode's last state), ``info["TimeLimit.truncated"]`` and "episode".
    With `autoreset` False (evaluation), ended entries are left to the env's own next-step reset.

    Args:
        env: the batched env; its `max_episode_steps` ends the episodes.
        clock_frequency: f in Hz of the clock features appended to the observation, or None for none.
        action_time_constant: τ in s of the activation dynamics (module docstring); 0: the action is
            the activation.
    """

    def __init__(self, env: Any, clock_frequency: float | None = None, action_time_constant: float = 0.0):
        from gymnasium import spaces

        if clock_frequency is not None:
            check_number(clock_frequency, "clock_frequency", 0.0, strict=True)
        check_number(action_time_constant, "action_time_constant", 0.0)
        super().__init__(env)
        self.clock_frequency = clock_frequency
        self.action_time_constant = float(action_time_constant)
        self.frame_seconds = float(env.simulation.frame_seconds)
        tau = self.action_time_constant
        self.smoothing = 1.0 - math.exp(-self.frame_seconds / tau) if tau > 0 else 1.0
        extra = 0 if clock_frequency is None else 2
        size = env.single_observation_space.shape[0] + extra
        self.observation_space = spaces.Box(-np.inf, np.inf, (size,), dtype=np.float32)
        self.autoreset = True
        self.activation = np.zeros((env.num_envs, env.single_action_space.shape[0]))
        self._ended_lengths = np.zeros(env.num_envs, dtype=np.int64)

    @property
    def times(self) -> np.ndarray:
        """Time of each entry's current state within its episode, `[B]`, in s."""
        return self.episode_lengths * self.frame_seconds

    def _observe(self, observations: np.ndarray, entries: np.ndarray | None = None) -> np.ndarray:
        if self.clock_frequency is None:
            return observations
        times = self.times if entries is None else self.times[entries]
        angle = 2 * math.pi * self.clock_frequency * times
        clock = np.stack([np.sin(angle), np.cos(angle)], axis=-1).astype(np.float32)
        return np.concatenate([observations, clock], axis=-1)

    def reset(self) -> np.ndarray:
        """Reset every entry (with the seeds of `seed`, if given since the last reset)."""
        observations = super().reset()
        self.activation[:] = 0.0
        return self._observe(observations)

    def step_async(self, actions: np.ndarray) -> None:
        """Advance the activation dynamics with the excitations `actions` `[B, a]` (clipped to [−1, 1])
        and hand the activations to the env."""
        actions = np.asarray(actions, dtype=np.float64)
        if actions.shape != self.activation.shape:
            raise ValueError(f"actions must have shape {self.activation.shape}, got {actions.shape}")
        excitation = np.clip(actions, -1.0, 1.0)
        self.activation = self.activation + self.smoothing * (excitation - self.activation)
        super().step_async(self.activation)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        observations, rewards, done, infos = super().step_wait()
        if self.clock_frequency is not None:
            clocked = self._observe(observations)
            for i in np.flatnonzero(done):
                terminal = infos[i]["terminal_observation"][None]
                infos[i]["terminal_observation"] = self._terminal_observe(terminal, i)
            observations = clocked
        return observations, rewards, done, infos

    def _terminal_observe(self, observation: np.ndarray, entry: int) -> np.ndarray:
        # the entry's clock at the episode's last state: its length before the reset
        angle = 2 * math.pi * self.clock_frequency * self._ended_lengths[entry] * self.frame_seconds
        clock = np.array([[math.sin(angle), math.cos(angle)]], dtype=np.float32)
        return np.concatenate([observation, clock], axis=-1)[0]

    def _reset_ended(self, done: np.ndarray, observations: np.ndarray) -> None:
        self._ended_lengths = self.episode_lengths.copy()
        if not self.autoreset:
            return
        super()._reset_ended(done, observations)
        self.activation[done] = 0.0


@dataclass(frozen=True)
class Evaluation:
    """Deterministic episodes of a controller on the fixed evaluation seeds.

    Attributes:
        returns: undiscounted return of each episode, `[E]`.
        distances: forward (+x) displacement of the centre of mass over each episode, `[E]`, in m.
        failures: episodes ended early by a numerical failure.
        solver_iterations: mean Newton iterations per env step (the env's count: the batched solve's).
        states: with `record`, the states of episode 0, `[T + 1, 2·n·d]`, else None.
        activations: with `record`, the activation of each of its steps, `[T, a]`, else None.
    """

    returns: np.ndarray
    distances: np.ndarray
    failures: int
    solver_iterations: float
    states: Tensor | None = None
    activations: Tensor | None = None

    @property
    def mean_return(self) -> float:
        return float(np.mean(self.returns))

    @property
    def stderr_return(self) -> float:
        """Standard error of the mean return (0 for one episode)."""
        n = len(self.returns)
        return float(np.std(self.returns, ddof=1) / math.sqrt(n)) if n > 1 else 0.0

    @property
    def mean_distance(self) -> float:
        return float(np.mean(self.distances))


def evaluate(venv: CreatureVecEnv, controller: Controller, *, record: bool = False) -> Evaluation:
    """Run one episode per entry of `venv` from the seeds `EVAL_SEED` + i with `controller`.

    Every episode lasts the env's `max_episode_steps` unless a numerical failure ends it first;
    rewards after the end are not counted.
    """
    env = venv.env
    steps = env.config.max_episode_steps
    if steps is None:
        raise ValueError("evaluation needs an env with max_episode_steps")
    venv.autoreset = False
    try:
        venv.seed(EVAL_SEED)
        observations = venv.reset()
        start = env.simulation.x_position(env.states).cpu().numpy()
        finish = start.copy()
        returns = np.zeros(venv.num_envs)
        running = np.ones(venv.num_envs, dtype=bool)
        failures, iterations = 0, []
        states, activations = [env.states[0].clone()], []
        for _ in range(steps):
            venv.step_async(controller(observations, venv.times.copy()))
            observations, _, done, infos = venv.step_wait()
            # the env's float64 rewards, not the float32 copy SB3 is given
            returns[running] += venv.rewards[running]
            finish[running] = np.array([info["x_position"] for info in infos])[running]
            iterations.append(np.mean([infos[i]["solver_iterations"] for i in np.flatnonzero(running)]))
            if record and running[0]:
                states.append(env.states[0].clone())
                activations.append(env.activations[0].clone())
            failures += sum(bool(infos[i]["numerical_failure"]) for i in np.flatnonzero(running & done))
            running &= ~done
            if not running.any():
                break
    finally:
        venv.autoreset = True
    return Evaluation(
        returns=returns,
        distances=finish - start,
        failures=failures,
        solver_iterations=float(np.mean(iterations)) if iterations else float("nan"),
        states=torch.stack(states) if record else None,
        activations=torch.stack(activations) if record else None,
    )


def random_controller(num_actuators: int, seed: int) -> Controller:
    """Uniform random actions in [−1, 1] from a generator seeded with `seed`: the baseline policy."""
    generator = np.random.default_rng(seed)

    def act(observations: np.ndarray, times: np.ndarray) -> np.ndarray:
        return generator.uniform(-1.0, 1.0, (observations.shape[0], num_actuators))

    return act


@dataclass(frozen=True)
class CurvePoint:
    """One evaluation of a training run: a row of ``curve.csv``.

    Attributes:
        method: "ppo" or "gradient".
        env_steps: env steps simulated for training so far (all batch entries; evaluation not counted).
        updates: parameter updates so far.
        wall_seconds: wall time of training so far, in s (evaluations, checkpoints and outputs excluded).
        eval_return: mean undiscounted return of the evaluation episodes.
        eval_return_stderr: its standard error over the episodes.
        eval_distance: mean forward distance of the centre of mass per episode, in m.
        eval_episodes: how many episodes.
        eval_failures: episodes ended by a numerical failure.
        eval_solver_iterations: mean Newton iterations per env step in the evaluation.
        eval_seconds: wall time of this evaluation, in s.
    """

    method: str
    env_steps: int
    updates: int
    wall_seconds: float
    eval_return: float
    eval_return_stderr: float
    eval_distance: float
    eval_episodes: int
    eval_failures: int
    eval_solver_iterations: float
    eval_seconds: float

    @classmethod
    def of(
        cls,
        method: str,
        env_steps: int,
        updates: int,
        wall_seconds: float,
        result: Evaluation,
        seconds: float,
    ) -> CurvePoint:
        """The row for evaluation `result`, which took `seconds`."""
        return cls(
            method=method,
            env_steps=int(env_steps),
            updates=int(updates),
            wall_seconds=float(wall_seconds),
            eval_return=result.mean_return,
            eval_return_stderr=result.stderr_return,
            eval_distance=result.mean_distance,
            eval_episodes=len(result.returns),
            eval_failures=result.failures,
            eval_solver_iterations=result.solver_iterations,
            eval_seconds=float(seconds),
        )


CURVE_FIELDS = tuple(field.name for field in fields(CurvePoint))


def atomic_write(path: Path, write: Callable[[Path], None]) -> Path:
    """Call `write(temporary)` on a temporary file beside `path`, then rename it to `path`: the file
    is written whole or not at all. Returns `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(handle)
    temporary = Path(name)
    try:
        write(temporary)
        # mkstemp makes the file private; give it the permissions a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


def write_curve(path: Path, points: Sequence[CurvePoint]) -> Path:
    """The curve as CSV, one row per evaluation (columns: `CurvePoint`'s fields), atomically."""

    def write(temporary: Path) -> None:
        with open(temporary, "w", newline="") as stream:
            writer = csv.DictWriter(stream, fieldnames=CURVE_FIELDS)
            writer.writeheader()
            for point in points:
                writer.writerow(
                    {
                        key: repr(value) if isinstance(value, float) else value
                        for key, value in asdict(point).items()
                    }
                )

    return atomic_write(path, write)


def read_curve(path: Path) -> list[CurvePoint]:
    """The rows of a curve CSV written by `write_curve` (floats round-trip exactly)."""
    types = {field.name: field.type for field in fields(CurvePoint)}
    convert = {"str": str, "int": int, "float": float}
    with open(path, newline="") as stream:
        rows = list(csv.DictReader(stream))
    if not rows or set(rows[0]) != set(CURVE_FIELDS):
        raise ValueError(f"{path} is not a learning curve: expected the columns {CURVE_FIELDS}")
    return [CurvePoint(**{key: convert[types[key]](row[key]) for key in CURVE_FIELDS}) for row in rows]


def rng_state() -> dict[str, Any]:
    """The global random states training draws from (torch, numpy, Python), as torch.save-able values."""
    name, keys, position, has_gauss, gauss = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": (name, torch.from_numpy(keys.astype(np.int64)), position, has_gauss, gauss),
        "python": random.getstate(),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what `rng_state` returned."""
    torch.set_rng_state(state["torch"])
    name, keys, position, has_gauss, gauss = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), position, has_gauss, gauss))
    random.setstate(state["python"])


# Settings a resumed run may change: how long it trains, and whether the physics is compiled (the
# same equations; the trajectories then agree to the solver's tolerance, not to the last bit).
RESUMABLE_CHANGES = ("total_steps", "solver_compile")


def checkpoint_settings(method: str, settings: Any) -> dict[str, Any]:
    """What a checkpoint of a `method` run with `settings` (a dataclass) records and a resume checks."""
    fixed = {key: value for key, value in asdict(settings).items() if key not in RESUMABLE_CHANGES}
    return {"method": method, **fixed}


def save_checkpoint(path: Path, payload: dict[str, Any]) -> Path:
    """`payload` (tensors, numbers, strings and containers of them) with torch.save, atomically."""
    return atomic_write(path, lambda temporary: torch.save(payload, temporary))


def load_checkpoint(path: Path, settings: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint at `path`, after checking that it was written by a run with the same `settings`.

    Raises:
        FileNotFoundError: there is no checkpoint.
        ValueError: its settings differ (named), so its curve could not be continued.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--resume: no checkpoint at {path}; run without --resume to start afresh")
    payload = torch.load(path, weights_only=True)
    check_settings(path, payload["settings"], settings)
    return payload


def check_settings(path: Path, saved: dict[str, Any], settings: dict[str, Any]) -> None:
    """ValueError naming every setting in which the checkpoint at `path` (written with `saved`)
    differs from the run's `settings`: its curve could not be continued."""
    differ = sorted(key for key in set(saved) | set(settings) if saved.get(key) != settings.get(key))
    if differ:
        detail = ", ".join(
            f"{key}: checkpoint {saved.get(key)!r}, now {settings.get(key)!r}" for key in differ
        )
        raise ValueError(f"--resume: {path} was written with other settings ({detail})")


def timed_evaluation(venv: CreatureVecEnv, controller: Controller) -> tuple[Evaluation, float]:
    """`evaluate(venv, controller)` and its wall time in s."""
    start = time.perf_counter()
    result = evaluate(venv, controller)
    return result, time.perf_counter() - start


def load_run(
    out: Path, fixed: dict[str, Any], policy: Any, optimizer: Any
) -> tuple[dict[str, Any], list[CurvePoint]]:
    """Load ``out/checkpoint.pt`` (written with the settings `fixed`) into `policy`, `optimizer` (both
    torch modules or optimizers) and the global random states; returns the checkpoint and its curve."""
    saved = load_checkpoint(out / CHECKPOINT_NAME, fixed)
    policy.load_state_dict(saved["policy"])
    optimizer.load_state_dict(saved["optimizer"])
    set_rng_state(saved["rng"])
    return saved, [CurvePoint(**row) for row in saved["curve"]]


def log_evaluation(
    out: Path,
    curve: list[CurvePoint],
    point: CurvePoint,
    checkpoint: tuple[dict[str, Any], Any, Any, dict[str, Any]],
    progress: bool,
) -> None:
    """Append `point` to `curve`, then write ``out/checkpoint.pt`` and ``out/curve.csv``, each whole;
    with `progress`, print the evaluation above the progress bar.

    `checkpoint` is (the settings a resume checks, the policy, its optimizer, the method's counters):
    the checkpoint holds them, the global random states and the curve, what `load_run` reads back."""
    curve.append(point)
    fixed, policy, optimizer, counters = checkpoint
    payload = {
        "settings": fixed,
        "policy": policy.state_dict(),
        "optimizer": optimizer.state_dict(),
        "rng": rng_state(),
        "curve": [asdict(p) for p in curve],
        **counters,
    }
    save_checkpoint(out / CHECKPOINT_NAME, payload)
    write_curve(out / CURVE_NAME, curve)
    if progress:
        report_evaluation(point)


def report_evaluation(point: CurvePoint) -> None:
    """Print an evaluation above the progress bar."""
    tqdm.write(
        f"{point.method}: {point.env_steps} env steps, {point.wall_seconds:.0f} s: eval return "
        f"{point.eval_return:+.3f} ± {point.eval_return_stderr:.3f}, distance "
        f"{100 * point.eval_distance:+.2f} cm"
    )


def progress_bar(method: str, settings: RunSettings, done: int, progress: bool) -> tqdm:
    """A bar over the run's `total_steps` env steps, `done` of them already taken."""
    return tqdm(
        total=settings.total_steps,
        initial=min(done, settings.total_steps),
        desc=method,
        unit="step",
        disable=not progress,
        leave=False,
    )


def write_policy_outputs(
    scene: Any, result: Evaluation, out: Path, name: str, *, render: bool = True
) -> list[Path]:
    """VTK frames of the recorded evaluation episode in ``out/rollout`` (``frame.pvd``, activations
    included) and, with `render`, ``out/NAME.gif`` coloured by muscle activation. Returns the paths."""
    from _common import gif_frames
    from _locomotion import vertex_activation

    from energysim.export import export_rollout, render_gif

    if result.states is None or result.activations is None:
        raise ValueError("the evaluation was not recorded (evaluate(..., record=True))")
    states, activations = result.states, result.activations
    written = [export_rollout(scene, states, out / "rollout", actions=activations)]
    if render:
        x = scene.split_state(states)[0]
        per_state = torch.cat([torch.zeros_like(activations[:1]), activations])
        colour = vertex_activation(scene, per_state)
        shown, fps = gif_frames(torch.arange(x.shape[0]), scene.dt)
        written.append(
            render_gif(
                out / f"{name}.gif",
                list(x[shown]),
                scene.mesh.surface(),
                scalars=colour[shown],
                fps=fps,
                window_size=(720, 405),
                ground_height=0.0,
            )
        )
    return written


def plot_curves(
    points: Sequence[CurvePoint],
    path: Path,
    title: str,
    references: Sequence[tuple[str, Evaluation]] = (),
    symlog: bool = False,
) -> Path:
    """Mean evaluation return vs env steps and vs training wall time, one line per method (error bars:
    standard error over the episodes); each (name, evaluation) of `references` (the random policy, a
    fixed gait) as a horizontal line with its standard error shaded. `symlog`: a y axis linear within
    ±0.01 and logarithmic beyond, so that curves of very different sizes both show. Atomic PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    methods = list(dict.fromkeys(point.method for point in points))
    style = {"marker": "o", "ms": 3, "capsize": 2}
    for method in methods:
        rows = [point for point in points if point.method == method]
        y = [p.eval_return for p in rows]
        error = [p.eval_return_stderr for p in rows]
        axes[0].errorbar([p.env_steps for p in rows], y, yerr=error, label=method, **style)
        axes[1].errorbar([p.wall_seconds / 60 for p in rows], y, yerr=error, label=method, **style)
    labels = ("env steps simulated for training", "training wall time (min, evaluations excluded)")
    for axis, label in zip(axes, labels, strict=True):
        for (name, reference), colour, line in zip(references, ("grey", "black"), ("--", ":"), strict=False):
            mean, error = reference.mean_return, reference.stderr_return
            axis.axhline(mean, color=colour, ls=line, lw=1, label=f"{name} (± s.e.)")
            axis.axhspan(mean - error, mean + error, color=colour, alpha=0.15, lw=0)
        if symlog:
            axis.set_yscale("symlog", linthresh=0.01)
        axis.set_xlabel(label)
        axis.grid(alpha=0.3)
    axes[0].set_ylabel("mean evaluation return" + (" (symlog)" if symlog else ""))
    axes[0].legend()
    figure.suptitle(title)
    figure.tight_layout()

    def write(temporary: Path) -> None:
        figure.savefig(temporary, dpi=120, format="png")

    atomic_write(path, write)
    plt.close(figure)
    return path


def common_parser(doc: str, defaults: RunSettings, method: str) -> argparse.ArgumentParser:
    """The flags both training scripts take (their `dest` is the `RunSettings` field they set);
    `defaults` is the script's `Settings()`."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    add = parser.add_argument
    add("--creature", default=defaults.creature, help="a shipped creature")
    add("--num-envs", type=int, default=defaults.num_envs, help="creatures simulated as one batch")
    add("--total-steps", type=int, default=defaults.total_steps, help="env steps to train for (all entries)")
    add("--episode-steps", type=int, default=defaults.episode_steps, help="env steps per episode")
    add("--seed", type=int, default=defaults.seed)
    add("--eval-every", type=int, default=defaults.eval_every, help="env steps between evaluations")
    add("--eval-episodes", type=int, default=defaults.eval_episodes, help="episodes per evaluation")
    add("--solver-tol", type=float, default=defaults.solver_tol, help="Newton–CG tolerance in m/s")
    add(
        "--solver-budget",
        type=int,
        default=defaults.solver_budget,
        help="at most this many Newton iterations per physics step, the last iterate kept (implicit only)",
    )
    add(
        "--compile",
        dest="solver_compile",
        action="store_true",
        help="compiled physics evaluations: faster env steps after 15 s to a minute of compiling",
    )
    add(
        "--integrator",
        default="implicit_euler",
        choices=["implicit_euler", "leapfrog"],
        help="the env's physics (leapfrog: explicit substeps with viscosity, fast with --compile)",
    )
    add("--learning-rate", type=float, default=defaults.learning_rate, help="the optimizer's step size")
    add("--out", type=Path, default=Path("out") / f"train_{method}", help="output folder")
    add("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    add("--threads", type=int, default=1, help="torch intra-op threads")
    add("--no-render", action="store_true", help="no GIF")
    add("--quiet", action="store_true", help="no progress bar")
    return parser


def script_main(
    argv: list[str] | None,
    parser: argparse.ArgumentParser,
    settings_type: type[RunSettings],
    train: Callable[..., list[CurvePoint]],
    outputs: Callable[..., list[Path]],
    method: str,
) -> int:
    """Parse the flags into `settings_type` (field by field; fields without a flag keep their
    defaults), train, write the outputs and print the outcome; returns 0."""
    args = parser.parse_args(argv)
    check_integer(args.threads, "threads", 1)
    flags = vars(args)
    settings = settings_type(**{f.name: flags[f.name] for f in fields(settings_type) if f.name in flags})
    configure_cpu(args.threads)  # the threads, and freed buffers kept for reuse (`energysim.cpu`)
    curve = train(settings, args.out, resume=args.resume, progress=not args.quiet)
    print_outcome(method, outputs(settings, args.out, curve, render=not args.no_render), curve)
    return 0


def print_outcome(method: str, written: Sequence[Path], curve: Sequence[CurvePoint]) -> None:
    """The files written and the first and last evaluation of a training run."""
    for path in written:
        print(f"wrote {path}")
    first, last = curve[0], curve[-1]
    print(
        f"{method}: eval return {first.eval_return:+.3f} -> {last.eval_return:+.3f} "
        f"(distance {100 * first.eval_distance:+.2f} -> {100 * last.eval_distance:+.2f} cm) in "
        f"{last.env_steps} env steps, {last.wall_seconds:.0f} s of training"
    )


def random_baseline(task: Task, episodes: int, seed: int = 0) -> Evaluation:
    """The uniform random policy on the evaluation episodes (actions from a generator seeded `seed`)."""
    venv = make_vec_env(task, episodes)
    return evaluate(venv, random_controller(venv.action_space.shape[0], seed))


def suggested_gait_controller(task: Task) -> Controller:
    """The creature's suggested open-loop gait (`Creature.gait_action`, what walk.py uses, without
    its ramp-in) as a controller: a reference for the trained ones."""
    from energysim.creatures import load_creature

    creature = load_creature(task.creature)

    def act(observations: np.ndarray, times: np.ndarray) -> np.ndarray:
        return creature.gait_action(torch.from_numpy(times)).numpy()

    return act


def expected_random_ctrl_return(task: Task) -> float:
    """E[return] of the uniform random policy's control cost alone: −w_c · a · T / 3 (E[a_j²] = 1/3).

    For a creature that is mirror symmetric front to back (the worm), the random policy's expected
    forward reward is zero, so this is its whole expected return.
    """
    from energysim.creatures import load_creature
    from energysim.envs import CreatureEnvConfig

    weight = CreatureEnvConfig(creature=task.creature).ctrl_cost_weight
    return -weight * load_creature(task.creature).num_actuators * task.episode_steps / 3.0


def comparison_table(points: Sequence[CurvePoint]) -> str:
    """Markdown: every evaluation of every method (references have 0 env steps and updates)."""
    lines = [
        "| method | env steps | updates | training wall time (min) | eval return ± s.e. "
        "| forward distance (cm) | eval Newton iterations/step |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for p in points:
        lines.append(
            f"| {p.method} | {p.env_steps} | {p.updates} | {p.wall_seconds / 60:.1f} | "
            f"{p.eval_return:+.4f} ± {p.eval_return_stderr:.4f} | {100 * p.eval_distance:+.3f} | "
            f"{p.eval_solver_iterations:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Combine learning curves into training.csv, training.md and training.png (module docstring)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add = parser.add_argument
    add("--curves", type=Path, nargs="+", required=True, help="curve.csv of each run")
    add("--out", type=Path, default=Path("docs") / "benchmarks", help="output folder")
    add("--creature", default=Task.creature, help="the runs' creature (for the random policy)")
    add("--episode-steps", type=int, default=Task.episode_steps, help="the runs' episode length")
    add("--random-episodes", type=int, default=4, help="episodes of the random policy; 0: none")
    add("--threads", type=int, default=1, help="torch intra-op threads")
    args = parser.parse_args(argv)
    configure_cpu(check_integer(args.threads, "threads", 1))
    check_integer(args.random_episodes, "random_episodes", 0)
    points = [point for path in args.curves for point in read_curve(path)]
    task = Task(args.creature, args.episode_steps)
    references = [("suggested gait", evaluate(make_vec_env(task, 2), suggested_gait_controller(task)))]
    if args.random_episodes:
        references.insert(0, ("random policy", random_baseline(task, args.random_episodes)))
    rows = [CurvePoint.of(name, 0, 0, 0.0, result, 0.0) for name, result in references] + points
    write_curve(args.out / "training.csv", rows)
    header = (
        f"Learning curves of the {task.creature}, {task.episode_steps}-step episodes of "
        f"{task.frame_skip} × 1/60 s (docs/training.md has the commands). Eval return: "
        "mean undiscounted return of the deterministic policy on the fixed evaluation episodes; forward "
        "distance: of the centre of mass per episode. Wall time: training only, one thread, on a shared "
        "machine (noisy). The random policy draws uniform actions (the expected return of its control "
        f"cost alone is {expected_random_ctrl_return(task):+.3f}); the suggested gait is the creature's "
        "open-loop sine of walk.py, without its ramp-in.\n\n"
    )
    text = header + comparison_table(rows)
    atomic_write(args.out / "training.md", lambda temporary: temporary.write_text(text))
    title = f"{task.creature}: PPO vs gradients through the simulator"
    plot_curves(points, args.out / "training.png", title, references, symlog=True)
    print(text)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.exit(main())
