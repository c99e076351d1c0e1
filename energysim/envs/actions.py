"""Actions as the environments take them: real numbers only, one activation per actuator, finite,
clipped to [−1, 1]. Every refusal is a ValueError that names the action and what it must be.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def as_action_array(action: object, name: str = "action") -> np.ndarray:
    """`action` as a float64 numpy array, refusing what is not real numbers: a bool, complex, string
    or object array would otherwise be converted without a word (complex losing its imaginary part).

    Raises:
        ValueError: naming `name` and the dtype it has.
    """
    array = np.asarray(action.detach().cpu() if isinstance(action, Tensor) else action)
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold real numbers (activations in [-1, 1]), got dtype {array.dtype}")
    return array.astype(np.float64)


def checked_action(
    action: object, num_actuators: int, creature: str, device: torch.device, dtype: torch.dtype
) -> Tensor:
    """`action` `[B, a]` as a finite tensor on `device` in `dtype`, clipped to [−1, 1].

    Args:
        action: a tensor or array-like of shape `[B, a]`.
        num_actuators: a, the actuators of `creature`.
        creature: the creature's name, for the messages.

    Raises:
        ValueError: an action that is not real numbers, not of shape `[B, a]`, or not finite
            (naming the batch entries).
    """
    if not isinstance(action, Tensor):
        action = as_action_array(action)
    elif action.dtype == torch.bool or action.is_complex():
        raise ValueError(f"action must hold real numbers (activations in [-1, 1]), got dtype {action.dtype}")
    action = torch.as_tensor(action, device=device).to(dtype)
    if action.ndim != 2 or action.shape[1] != num_actuators:
        raise ValueError(
            f"action must have shape [B, {num_actuators}] (one activation per actuator of the "
            f"{creature}), got {list(action.shape)}"
        )
    if not torch.isfinite(action).all():
        bad = torch.nonzero(~torch.isfinite(action).all(dim=1)).flatten().tolist()
        raise ValueError(f"action has non-finite entries in batch entries {bad}")
    return action.clamp(-1.0, 1.0)


__all__ = ["as_action_array", "checked_action"]
