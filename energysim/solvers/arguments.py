"""Checks of solver settings at construction: a wrong type or value is named where it is given,
not found later by a step that fails deep inside the solve.

Each check raises `TypeError` for a value of the wrong kind (a string tolerance, a fractional
iteration count, a bool where a number is meant) and `ValueError` for one of the right kind out of
range (non-finite, non-positive), naming the solver, the argument, the value received and what was
expected.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from numbers import Integral, Real


def _received(value: object) -> str:
    return f"{value!r} ({type(value).__name__})"


def require_integer(owner: str, name: str, value: object, *, minimum: int) -> int:
    """`value` as an int, if it is an integer (not a bool) of at least `minimum`.

    Raises:
        TypeError: `value` is not an integer.
        ValueError: `value` is below `minimum`.
    """
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise TypeError(f"{owner}: {name} must be an integer >= {minimum}, got {_received(value)}")
    if value < minimum:
        raise ValueError(f"{owner}: {name} must be an integer >= {minimum}, got {value}")
    return int(value)


def require_real(
    owner: str,
    name: str,
    value: object,
    *,
    unit: str = "",
    above: float | None = None,
    at_least: float | None = None,
    below: float | None = None,
) -> float:
    """`value` as a float, if it is a finite real number (not a bool) in the given range.

    Args:
        owner, name: the solver and the argument, for the message.
        unit: the argument's unit, for the message ("m/s", "m").
        above, at_least, below: the range: value > above, value >= at_least, value < below.

    Raises:
        TypeError: `value` is not a real number.
        ValueError: `value` is not finite or out of the range.
    """
    bounds = []
    if above is not None:
        bounds.append(f"> {above:g}")
    if at_least is not None:
        bounds.append(f">= {at_least:g}")
    if below is not None:
        bounds.append(f"< {below:g}")
    expected = "a finite real number" + (f" of {unit}" if unit else "")
    if bounds:
        expected += " " + " and ".join(bounds)
    if isinstance(value, bool) or not isinstance(value, Real):
        raise TypeError(f"{owner}: {name} must be {expected}, got {_received(value)}")
    number = float(value)
    if (
        not math.isfinite(number)
        or (above is not None and not number > above)
        or (at_least is not None and not number >= at_least)
        or (below is not None and not number < below)
    ):
        raise ValueError(f"{owner}: {name} must be {expected}, got {value!r}")
    return number


def require_bool(owner: str, name: str, value: object) -> bool:
    """`value`, if it is a bool (an int or a string such as "false" is refused, not guessed at).

    Raises:
        TypeError: `value` is not a bool.
    """
    if not isinstance(value, bool):
        raise TypeError(f"{owner}: {name} must be True or False, got {_received(value)}")
    return value


def require_choice(owner: str, name: str, value: object, choices: Sequence[str]) -> str:
    """`value`, if it is one of the strings `choices`.

    Raises:
        TypeError: `value` is not a string.
        ValueError: `value` is not one of them.
    """
    listed = ", ".join(repr(choice) for choice in choices)
    if not isinstance(value, str):
        raise TypeError(f"{owner}: {name} must be one of {listed}, got {_received(value)}")
    if value not in choices:
        raise ValueError(f"{owner}: {name} must be one of {listed}, got {_received(value)}")
    return value
