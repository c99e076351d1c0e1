"""Many steps at once, differentiable, with optional checkpointing for long horizons."""

from __future__ import annotations

import logging
import operator
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from energysim.integrators.step import timestep
from energysim.model.scene import Scene

logger = logging.getLogger(__name__)

# Without tqdm, `progress=True` logs about this many lines over a rollout (and always the last step).
_LOG_LINES = 10

ProgressCallback = Callable[[int, int], object]


def _count(value: object, name: str, *, allow_none: bool = False) -> int | None:
    """`value` as an integer >= 0 (None passes where allowed); bools and fractions are refused."""
    if value is None and allow_none:
        return None
    try:
        count = None if isinstance(value, bool) else operator.index(value)
    except TypeError:
        count = None
    if count is None or count < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
    return count


def rollout(
    scene: Scene,
    state: Tensor,
    actions: Tensor | None = None,
    steps: int | None = None,
    *,
    checkpoint_every: int = 0,
    grad_mode: str = "implicit",
    progress: bool | ProgressCallback = False,
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
        grad_mode: "implicit" or "unrolled" (see `energysim.integrators.step`).
        progress: False: silent. True: a tqdm progress bar on stderr when tqdm is installed, else an
            INFO line through `logging` about every tenth of the run and at the last step. A callable
            `progress(step, total)` is called after each step with the number of steps done (1 … T) and
            T; an exception it raises ends the rollout. Reporting reads only step counts, so the states,
            gradients and checkpointing are the same with or without it; steps solved again during a
            checkpointed backward are not reported again.
    """
    steps = _count(steps, "steps", allow_none=True)
    checkpoint_every = _count(checkpoint_every, "checkpoint_every")
    if actions is not None:
        if not isinstance(actions, Tensor):
            actions = torch.as_tensor(actions)
        if actions.ndim not in (2, 3):
            raise ValueError(f"actions must have shape [T, a] or [T, B, a], got {tuple(actions.shape)}")
        if steps is not None and steps != actions.shape[0]:
            raise ValueError(f"steps={steps} but actions has {actions.shape[0]} rows")
        steps = actions.shape[0]
    if steps is None:
        raise ValueError("give `steps` (>= 0) or `actions`")
    if not (isinstance(progress, bool) or callable(progress)):
        raise TypeError(f"progress must be True, False or a callable progress(step, total), got {progress!r}")
    with _reporter(progress, steps) as report:
        return _run(scene, state, actions, steps, checkpoint_every, grad_mode, report)


def _run(
    scene: Scene,
    state: Tensor,
    actions: Tensor | None,
    steps: int,
    checkpoint_every: int,
    grad_mode: str,
    report: Callable[[int], None],
) -> Tensor:
    """The rollout proper, with `report(step)` called once per step done, in order."""
    reported = 0

    def advance(current: Tensor, first: int, count: int, segment_actions: Tensor | None) -> list[Tensor]:
        nonlocal reported
        out = []
        for k in range(count):
            action = None if segment_actions is None else segment_actions[k]
            current = timestep(scene, current, action, grad_mode=grad_mode)
            out.append(current)
            # a checkpointed backward runs `advance` again for steps already reported
            if first + k + 1 > reported:
                reported = first + k + 1
                report(reported)
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


@contextmanager
def _reporter(progress: bool | ProgressCallback, total: int) -> Iterator[Callable[[int], None]]:
    """`report(step)` for `progress`, valid inside the block; a progress bar is closed on leaving it."""
    if progress is False:
        yield lambda step: None
    elif progress is True:
        try:
            from tqdm import tqdm
        except ImportError:
            every = max(1, -(-total // _LOG_LINES))

            def log(step: int) -> None:
                if step % every == 0 or step == total:
                    logger.info("rollout: step %d/%d", step, total)

            yield log
        else:
            with tqdm(total=total, desc="rollout", unit="step") as bar:
                yield lambda step: bar.update(step - bar.n)
    else:
        yield lambda step: progress(step, total)
