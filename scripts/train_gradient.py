"""Train a soft creature's controller by backpropagating the return through the simulator.

The controller is an open-loop periodic gait: actuator j gets

    a_j(t) = tanh(s_j sin 2πft + c_j cos 2πft + b_j [+ MLP(observation)_j]),

a sine of amplitude √(s_j² + c_j²) and phase atan2(c_j, s_j) about b_j, squashed into [−1, 1], at the
creature's suggested frequency f (or a learned one, `--learn-frequency`), optionally plus a small MLP
on the env's observation (`--hidden N`; its last layer starts at zero, so training starts from the
gait). The objective is the env's own reward, forward centre-of-mass velocity − ctrl_cost_weight·‖a‖²,
summed over a window of `--window` env steps of `--num-envs` creatures simulated as one batch by
`es.timestep` (implicit gradients: one adjoint solve per step). Each window's mean reward is
maximised by one Adam step; the state then carries on, detached, into the next window (truncated
backpropagation through time), and every `--episode-steps` steps the creatures are reset (episode e,
entry i from seed (seed, e, i)). Evaluation, learning curve, checkpoints and outputs are those of
`train_ppo.py` (see `_training.py`), so the two curves compare directly.

Run:  python scripts/train_gradient.py                      # worm, about 15 min on 2 cores
      python scripts/train_gradient.py --total-steps 240 --eval-every 120 --eval-episodes 2 --out /tmp/g
      python scripts/train_gradient.py --resume             # continue an interrupted run's curve
      python scripts/train_gradient.py --compile            # compiled physics: faster steps after compiling
Writes to --out: curve.csv, checkpoint.pt, training.png, rollout/frame_*.vtu + frame.pvd, NAME.gif.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _training import (
    CHECKPOINT_NAME,
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
from torch import Tensor, nn
from tqdm import tqdm

import energysim as es
from energysim.solvers import ConvergenceError

METHOD = "gradient"


class GaitPolicy(nn.Module):
    """a(t, o) = tanh(s sin 2πft + c cos 2πft + b + MLP(o)), one entry per actuator (module docstring).

    Args:
        num_actuators: a.
        frequency: initial f in Hz (> 0).
        learn_frequency: whether f is trained (as log f).
        init_amplitude: every actuator starts with amplitude `init_amplitude` and a phase drawn
            uniformly from `generator`; 0: the gait starts at rest.
        observation_size: length of the env's observation (used with `hidden` > 0).
        hidden: width of the MLP's two hidden layers; 0: no MLP (pure open loop).
        generator: draws the initial phases and MLP weights.
    """

    def __init__(
        self,
        num_actuators: int,
        frequency: float,
        *,
        learn_frequency: bool = False,
        init_amplitude: float = 0.5,
        observation_size: int = 0,
        hidden: int = 0,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        check_integer(num_actuators, "num_actuators", 1)
        check_number(frequency, "frequency", 0.0, strict=True)
        check_number(init_amplitude, "init_amplitude", 0.0)
        check_integer(hidden, "hidden", 0)
        phase = 2 * math.pi * torch.rand(num_actuators, generator=generator, dtype=torch.float64)
        self.log_frequency = nn.Parameter(
            torch.tensor(math.log(frequency), dtype=torch.float64), requires_grad=learn_frequency
        )
        self.sine = nn.Parameter(init_amplitude * torch.cos(phase))
        self.cosine = nn.Parameter(init_amplitude * torch.sin(phase))
        self.bias = nn.Parameter(torch.zeros(num_actuators, dtype=torch.float64))
        self.mlp: nn.Sequential | None = None
        if hidden:
            check_integer(observation_size, "observation_size", 1)
            layers = [nn.Linear(observation_size, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh()]
            last = nn.Linear(hidden, num_actuators)
            self.mlp = nn.Sequential(*layers, last).to(torch.float64)
            with torch.no_grad():
                for layer in layers[::2]:
                    bound = 1 / math.sqrt(layer.in_features)
                    layer.weight.uniform_(-bound, bound, generator=generator)
                    layer.bias.zero_()
                last.weight.zero_()
                last.bias.zero_()

    @property
    def frequency(self) -> float:
        """f in Hz."""
        return float(self.log_frequency.exp())

    def forward(self, times: Tensor, observations: Tensor | None = None) -> Tensor:
        """Actions `[B, a]` in (−1, 1) at `times` `[B]` (s) and, with an MLP, `observations` `[B, o]`."""
        angle = 2 * math.pi * self.log_frequency.exp() * times[:, None]
        drive = self.sine * torch.sin(angle) + self.cosine * torch.cos(angle) + self.bias
        if self.mlp is not None:
            if observations is None:
                raise ValueError("this policy has an MLP: give the observations")
            drive = drive + self.mlp(observations)
        return torch.tanh(drive)


@dataclass(frozen=True)
class Settings(RunSettings):
    """One gradient training run (the command line's flags; module docstring)."""

    window: int = 20
    frequency: float | None = None
    learn_frequency: bool = False
    init_amplitude: float = 0.5
    hidden: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_integer(self.window, "window", 1)
        if self.frequency is not None:
            check_number(self.frequency, "frequency", 0.0, strict=True)
        check_number(self.init_amplitude, "init_amplitude", 0.0)
        check_integer(self.hidden, "hidden", 0)


def window_return(
    simulation: Any,
    policy: GaitPolicy,
    state: Tensor,
    activation: Tensor,
    start_step: int,
    steps: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Sum over `steps` env steps of the env's reward, per entry, differentiable in the policy.

    Args:
        simulation: the task's `CreatureSimulation` (its scene, reward weights and observation).
        policy: the controller.
        state: start states `[B, 2·n·d]` (detached: the window's gradient stops here).
        activation: the last activations `[B, a]` (for the observation).
        start_step: env steps into the episode at `state` (the gait's time is start_step · Δt).

    Returns:
        the returns `[B]`, the final states and the final activations (both still in the graph).
    """
    config = simulation.config
    scene = simulation.scene
    total = state.new_zeros(state.shape[0])
    for k in range(steps):
        times = torch.full((state.shape[0],), (start_step + k) * simulation.frame_seconds, dtype=state.dtype)
        observations = simulation.observe(state, activation) if policy.mlp is not None else None
        activation = policy(times, observations)
        x_before = simulation.x_position(state)
        for _ in range(config.frame_skip):
            state = es.timestep(scene, state, activation)
        x_velocity = (simulation.x_position(state) - x_before) / simulation.frame_seconds
        total = total + config.forward_reward_weight * x_velocity
        total = total - config.ctrl_cost_weight * activation.square().sum(dim=1)
    return total, state, activation


def controller(policy: GaitPolicy) -> Any:
    """The evaluation controller: the policy without gradients, on numpy observations and times."""

    def act(observations: np.ndarray, times: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            o = torch.from_numpy(observations).to(torch.float64) if policy.mlp is not None else None
            return policy(torch.from_numpy(times).to(torch.float64), o).numpy()

    return act


def episode_start(simulation: Any, seed: int, episode: int, batch: int) -> Tensor:
    """Start states `[B, 2·n·d]` of training episode `episode`: entry i from seed (seed, episode, i)."""
    return simulation.reset([np.random.default_rng([seed, episode, i]) for i in range(batch)])


def train(settings: Settings, out: Path, *, resume: bool = False, progress: bool = True) -> list[CurvePoint]:
    """Train, evaluating and checkpointing every `eval_every` env steps; returns the curve.

    With `resume`, continue from ``out/checkpoint.pt`` (same settings, except total_steps), so the
    curve continues exactly as an uninterrupted run's would.
    """
    task = settings.task
    simulation = task.simulation()
    evaluation_env = make_vec_env(task, settings.eval_episodes)
    torch.manual_seed(settings.seed)
    generator = torch.Generator().manual_seed(settings.seed)
    policy = GaitPolicy(
        simulation.num_actuators,
        settings.frequency or simulation.creature.gait_frequency,
        learn_frequency=settings.learn_frequency,
        init_amplitude=settings.init_amplitude,
        observation_size=simulation.layout.size,
        hidden=settings.hidden,
        generator=generator,
    )
    optimizer = torch.optim.Adam(
        [p for p in policy.parameters() if p.requires_grad], lr=settings.learning_rate
    )
    fixed = checkpoint_settings(METHOD, settings)
    curve: list[CurvePoint] = []
    env_steps = updates = episode = step_in_episode = failures = 0
    wall = 0.0
    state = episode_start(simulation, settings.seed, episode, settings.num_envs)
    activation = torch.zeros(settings.num_envs, simulation.num_actuators, dtype=state.dtype)
    if resume:
        saved, curve = load_run(out, fixed, policy, optimizer)
        env_steps, updates, wall = saved["env_steps"], saved["updates"], saved["wall_seconds"]
        episode, step_in_episode, failures = saved["episode"], saved["step_in_episode"], saved["failures"]
        state, activation = saved["state"], saved["activation"]

    def checkpoint_and_log(result: Evaluation, seconds: float) -> None:
        point = CurvePoint.of(METHOD, env_steps, updates, wall, result, seconds)
        counters = {
            "env_steps": env_steps,
            "updates": updates,
            "wall_seconds": wall,
            "episode": episode,
            "step_in_episode": step_in_episode,
            "failures": failures,
            "state": state,
            "activation": activation,
        }
        log_evaluation(out, curve, point, (fixed, policy, optimizer, counters), progress)

    if not curve:
        checkpoint_and_log(*timed_evaluation(evaluation_env, controller(policy)))
    next_evaluation = curve[-1].env_steps + settings.eval_every
    bar = progress_bar(METHOD, settings, env_steps, progress)
    while env_steps < settings.total_steps:
        steps = min(settings.window, task.episode_steps - step_in_episode)
        start = time.perf_counter()
        optimizer.zero_grad()
        try:
            returns, new_state, new_activation = window_return(
                simulation, policy, state, activation, step_in_episode, steps
            )
            loss = -returns.mean() / steps
            loss.backward()
            optimizer.step()
            updates += 1
            state, activation = new_state.detach(), new_activation.detach()
            step_in_episode += steps
        except ConvergenceError as error:
            # a failed solve ends the episode; the window's gradient is dropped
            failures += 1
            tqdm.write(f"{METHOD}: numerical failure, episode {episode} restarted: {error}")
            step_in_episode = task.episode_steps
        env_steps += steps * settings.num_envs
        if step_in_episode >= task.episode_steps:
            episode, step_in_episode = episode + 1, 0
            state = episode_start(simulation, settings.seed, episode, settings.num_envs)
            activation = torch.zeros_like(activation)
        wall += time.perf_counter() - start
        bar.update(steps * settings.num_envs)
        if env_steps >= next_evaluation or env_steps >= settings.total_steps:
            checkpoint_and_log(*timed_evaluation(evaluation_env, controller(policy)))
            next_evaluation = env_steps + settings.eval_every
    bar.close()
    return curve


def outputs(settings: Settings, out: Path, curve: list[CurvePoint], render: bool = True) -> list[Path]:
    """The learning-curve PNG and VTK frames (+ GIF) of the trained policy from the checkpoint."""
    task = settings.task
    simulation = task.simulation()
    saved = torch.load(out / CHECKPOINT_NAME, weights_only=True)
    policy = GaitPolicy(
        simulation.num_actuators,
        settings.frequency or simulation.creature.gait_frequency,
        learn_frequency=settings.learn_frequency,
        observation_size=simulation.layout.size,
        hidden=settings.hidden,
    )
    policy.load_state_dict(saved["policy"])
    venv = make_vec_env(task, 1)
    result = evaluate(venv, controller(policy), record=True)
    written = [plot_curves(curve, out / "training.png", f"{task.creature}: gradient through the simulator")]
    written += write_policy_outputs(venv.env.simulation.scene, result, out, task.creature, render=render)
    return written


def make_parser() -> argparse.ArgumentParser:
    """The shared training flags and this method's own."""
    parser = common_parser(__doc__, Settings(), METHOD)
    add = parser.add_argument
    add("--window", type=int, default=Settings.window, help="env steps per truncated-backpropagation window")
    add("--frequency", type=float, default=None, help="gait frequency in Hz (default: the creature's)")
    add("--learn-frequency", action="store_true", help="train the frequency too")
    add("--init-amplitude", type=float, default=Settings.init_amplitude, help="initial gait amplitude")
    add("--hidden", type=int, default=Settings.hidden, help="MLP width on the observation; 0: none")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Command line entry point (module docstring); returns 0."""
    return script_main(argv, make_parser(), Settings, train, outputs, METHOD)


if __name__ == "__main__":
    sys.exit(main())
