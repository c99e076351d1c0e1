"""What one env step of B entries yields: the `Transition` record, its reward (forward speed of the
centre of mass minus a control cost, as in Gymnasium's MuJoCo locomotion tasks), and which entries
the float32 environments can represent.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def control_reward(command: Tensor, ctrl_cost_weight: float) -> Tensor:
    """−`ctrl_cost_weight` × ‖u‖² of each clipped action u `[B, a]`, `[B]` (on the command, as
    MuJoCo's control cost)."""
    return -ctrl_cost_weight * command.square().sum(dim=1)


def forward_reward(
    x_before: Tensor, x_after: Tensor, frame_seconds: float, forward_reward_weight: float
) -> tuple[Tensor, Tensor]:
    """The centre-of-mass x velocity over a frame `[B]` (m/s), from x `[B]` (m) at its start and end
    and its length (s), and the forward reward, `forward_reward_weight` × that velocity, `[B]`."""
    x_velocity = (x_after - x_before) / frame_seconds
    return x_velocity, forward_reward_weight * x_velocity


def representable(observation: Tensor, reward: Tensor) -> Tensor:
    """Which entries' observation `[B, k]` stays finite as float32 (what the envs return) and reward
    `[B]` finite, `[B]` bool."""
    finite = torch.isfinite(observation.to(torch.float32)).all(dim=1)
    return finite & torch.isfinite(reward)


@dataclass(frozen=True)
class Transition:
    """One env step of B entries; tensors on the simulation's device.

    Attributes:
        state: the new states `[B, 2·n·d]`; a failed entry keeps its last good state.
        action: the actions u, clipped to [−1, 1], `[B, a]`.
        activation: the activations of the last physics step each entry attempted, `[B, a]`: `action`
            itself without a time constant, else its filtered value (`CreatureEnvConfig`).
        observation: `[B, layout.size]`, at `state` and `activation`.
        reward: `reward_forward + reward_ctrl`, `[B]`.
        reward_forward: `forward_reward_weight` × `x_velocity`, `[B]`.
        reward_ctrl: −`ctrl_cost_weight` × ‖action‖², `[B]` (on the command, as MuJoCo's control cost).
        x_position: centre-of-mass x at `state`, `[B]`, in m.
        x_velocity: centre-of-mass x displacement over the step / (frame_skip·h), `[B]`, in m/s.
        numerical_failure: which entries failed, `[B]`, bool.
        solver_iterations: Newton iterations of the solves that made `state` (summed over the
            frame; the iterations of the batched solve this entry took part in, which stop once it
            has converged), `[B]`, int64.
        solver_residual: the largest velocity residual in m/s the frame's solves left this entry
            (`SolverResult.residuals`; 0 for the explicit integrator, which solves nothing, and
            where failed), `[B]`.
    """

    state: Tensor
    action: Tensor
    activation: Tensor
    observation: Tensor
    reward: Tensor
    reward_forward: Tensor
    reward_ctrl: Tensor
    x_position: Tensor
    x_velocity: Tensor
    numerical_failure: Tensor
    solver_iterations: Tensor
    solver_residual: Tensor


__all__ = ["Transition", "control_reward", "forward_reward", "representable"]
