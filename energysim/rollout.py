"""Many steps at once, differentiable, with optional checkpointing for long horizons."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from energysim.scene import Scene
from energysim.step import timestep


def rollout(
    scene: Scene,
    state: Tensor,
    actions: Tensor | None = None,
    steps: int | None = None,
    *,
    checkpoint_every: int = 0,
    grad_mode: str = "implicit",
) -> Tensor:
    """Step `state` forward and return every state, shape `[T + 1, *state.shape]`.

    Each implicit step keeps only its inputs and solution for backward, O(state) memory. With
    `checkpoint_every = k > 0` (and grad enabled) even that is kept only every k steps; the steps
    in between are solved again during backward, one more forward solve per step.

    Args:
        scene: the model.
        state: shape `[2·num_dofs]` or `[B, 2·num_dofs]`.
        actions: one action per step, shape `[T, a]` or `[T, B, a]`, or None.
        steps: T when `actions` is None.
        checkpoint_every: steps per checkpointed segment; 0 keeps every step's tensors.
        grad_mode: "implicit" or "unrolled" (see `energysim.step`).
    """
    if actions is not None:
        if steps is not None and steps != actions.shape[0]:
            raise ValueError(f"steps={steps} but actions has {actions.shape[0]} rows")
        steps = actions.shape[0]
    if steps is None or steps < 0:
        raise ValueError("give `steps` (>= 0) or `actions`")
    if checkpoint_every < 0:
        raise ValueError(f"checkpoint_every must be >= 0, got {checkpoint_every}")

    def advance(current: Tensor, first: int, count: int, segment_actions: Tensor | None) -> list[Tensor]:
        out = []
        for k in range(count):
            action = None if segment_actions is None else segment_actions[k]
            current = timestep(scene, current, action, grad_mode=grad_mode)
            out.append(current)
        return out

    states = [state]
    use_checkpoints = checkpoint_every > 0 and torch.is_grad_enabled()
    start = 0
    while start < steps:
        count = min(checkpoint_every, steps - start) if checkpoint_every > 0 else steps - start
        segment_actions = None if actions is None else actions[start : start + count]
        if use_checkpoints:
            produced = checkpoint(
                lambda s, a, start=start, count=count: torch.stack(advance(s, start, count, a)),
                states[-1],
                segment_actions,
                use_reentrant=False,
            )
            states.extend(produced.unbind(0))
        else:
            states.extend(advance(states[-1], start, count, segment_actions))
        start += count
    return torch.stack(states)
