"""Vertex, element and actuator indices taken from a user, checked once and alike everywhere.

Indices arrive as lists, NumPy arrays or tensors of any integer dtype. A float that holds an
integer (`2.0`) is taken as that integer; a fractional one (`1.7`) is refused rather than
truncated, and so are bools mixed with integers (`[True, 2]` would otherwise read as `[1, 2]`). A
boolean mask is accepted only where a caller says so (`allow_mask`), and it must have one entry per
item: it selects the items where it is True, never items 0 and 1.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import torch
from torch import Tensor


def _listed(indices: Tensor, limit: int = 10) -> str:
    values = indices.reshape(-1).tolist()
    text = "[" + ", ".join(str(v) for v in values[:limit]) + "]"
    return text + (f" and {len(values) - limit} more" if len(values) > limit else "")


def _leaves(value: Any) -> Iterable[Any]:
    if isinstance(value, (list, tuple)):
        for item in value:
            yield from _leaves(item)
    else:
        yield value


def _as_tensor(value: Any, name: str) -> Tensor:
    if isinstance(value, Tensor):
        return value.detach()
    if isinstance(value, (list, tuple)):
        kinds = {isinstance(leaf, (bool, np.bool_)) for leaf in _leaves(value)}
        if kinds == {True, False}:
            raise ValueError(f"{name} mixes bools with integers: give integer indices or a boolean mask")
    try:
        array = np.asarray(value)
    except ValueError as error:  # ragged nesting
        raise ValueError(f"{name} must be a rectangular array of indices: {error}") from None
    if array.dtype == object or array.dtype.kind not in "biuf":
        raise TypeError(f"{name} must hold integer indices, got {array.dtype} values")
    return torch.from_numpy(np.array(array, dtype=np.bool_ if array.dtype.kind == "b" else array.dtype))


def as_indices(
    value: Any,
    name: str,
    count: int | None = None,
    *,
    allow_mask: bool = False,
    lowest: int = 0,
    what: str = "vertex",
) -> Tensor:
    """`value` as int64 indices (same shape), checked.

    Args:
        value: integers (list, NumPy array or tensor of any integer dtype, or floats that are whole
            numbers); with `allow_mask`, a boolean mask of shape `[count]`, which gives the indices
            where it is True (a 1-D result).
        name: the argument's name, for error messages.
        count: indices must lie in [`lowest`, `count`); None: no upper bound.
        allow_mask: accept a boolean mask.
        lowest: the smallest index allowed (-1 where -1 means "none").
        what: what one index numbers, for error messages ("vertex", "actuator").

    Raises:
        ValueError: fractional or non-finite values, bools mixed with integers, a mask where none is
            taken or of the wrong length, indices out of range; each names the offending entries.
        TypeError: values that are not numbers.
    """
    tensor = _as_tensor(value, name)
    if tensor.dtype == torch.bool:
        if not allow_mask:
            raise ValueError(
                f"{name} must hold integer indices, got a boolean array of shape {tuple(tensor.shape)} "
                "(for the indices where a mask is True: numpy.flatnonzero(mask))"
            )
        if count is not None and tuple(tensor.shape) != (count,):
            raise ValueError(
                f"{name} is a boolean mask of shape {tuple(tensor.shape)}; a mask needs one entry per "
                f"{what}, shape [{count}]"
            )
        return torch.nonzero(tensor.reshape(-1)).reshape(-1)
    if tensor.is_complex():
        raise TypeError(f"{name} must hold integer indices, got {tensor.dtype} values")
    if tensor.is_floating_point():
        fractional = ~torch.isfinite(tensor) | (tensor != torch.round(tensor))
        if fractional.any():
            where = torch.nonzero(fractional.reshape(-1)).reshape(-1)
            raise ValueError(
                f"{name} must hold whole numbers (indices are never rounded); entries {_listed(where)} "
                f"are {_listed(tensor.reshape(-1)[where])}"
            )
    indices = tensor.to(torch.int64)
    outside = indices < lowest
    if count is not None:
        outside = outside | (indices >= count)
    if outside.any():
        bound = f"[{lowest}, {count})" if count is not None else f">= {lowest}"
        raise ValueError(f"{name} names {what} indices {_listed(indices[outside])} outside {bound}")
    return indices
