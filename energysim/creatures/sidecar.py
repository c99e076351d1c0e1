"""A creature's JSON sidecar (``NAME.json``), read and checked: its description, dimension,
actuators, suggested material, muscle and gait. Every refusal is a `MeshFileError` that names the
file and the key, and says what the key must hold.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from energysim.creatures.shipped_files import MAKE_SCRIPT
from energysim.mesh.io import MeshFileError

# the suggested numbers of a creature (`Creature` fields of the same names): what each must be
SUGGESTED_NUMBERS: tuple[tuple[str, str, Callable[[float], bool]], ...] = (
    ("youngs_modulus", "a number > 0 (Pa)", lambda v: v > 0),
    ("poissons_ratio", "a number in (-1, 0.5)", lambda v: -1 < v < 0.5),
    ("density", "a number > 0 (kg/m^3)", lambda v: v > 0),
    ("muscle_stiffness", "a number >= 0 (Pa)", lambda v: v >= 0),
    ("max_contraction", "a number in (0, 1)", lambda v: 0 < v < 1),
    ("gait_frequency", "a number >= 0 (Hz)", lambda v: v >= 0),
    ("gait_amplitude", "a number in [0, 1]", lambda v: 0 <= v <= 1),
)


@dataclass(frozen=True)
class CreatureSidecar:
    """The checked contents of a creature's JSON sidecar.

    Attributes:
        dim: spatial dimension d, 2 or 3.
        num_actuators: a ≥ 1.
        description: what the creature is and how its actuators are laid out.
        actuator_names: a name per actuator, a of them.
        gait_phases: phase φ_j of each actuator in rad, a of them, finite.
        suggested: the `SUGGESTED_NUMBERS` by name (E in Pa, ν, ρ in kg/m³, k in Pa, c, f in Hz, A).
    """

    dim: int
    num_actuators: int
    description: str
    actuator_names: tuple[str, ...]
    gait_phases: tuple[float, ...]
    suggested: dict[str, float]


def read_creature_sidecar(path: Path) -> CreatureSidecar:
    """Read and check the JSON sidecar at `path`.

    Raises:
        MeshFileError: naming `path`, when it is not UTF-8 JSON holding an object, or a key is missing
            or ill-typed (naming the key and what it must be).
    """
    metadata = _read_json_object(path)
    dim = _integer(metadata, "dim", path, "2 or 3", lambda d: d in (2, 3))
    num_actuators = _integer(metadata, "num_actuators", path, "an integer >= 1", lambda a: a >= 1)
    phases = _sequence(metadata, "gait_phases", path, num_actuators, "finite numbers (rad)", _is_number)
    names = _sequence(
        metadata, "actuator_names", path, num_actuators, "strings", lambda v: isinstance(v, str)
    )
    description = _entry(metadata, "description", path, "a string")
    if not isinstance(description, str):
        raise MeshFileError(path, f"key 'description' must be a string, got {_describe(description)}")
    suggested = {
        key: _number(metadata, key, path, expected, valid) for key, expected, valid in SUGGESTED_NUMBERS
    }
    return CreatureSidecar(
        dim=dim,
        num_actuators=num_actuators,
        description=description,
        actuator_names=tuple(names),
        gait_phases=tuple(float(phase) for phase in phases),
        suggested=suggested,
    )


def _describe(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:60] + "..."


def _read_json_object(path: Path) -> dict[str, Any]:
    """The JSON object in `path`; MeshFileError naming `path` when it is not UTF-8 JSON holding an object."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise MeshFileError(
            path, f"cannot be read as UTF-8 text ({type(error).__name__}: {error})"
        ) from error
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise MeshFileError(
            path, f"is not valid JSON ({error.msg} at line {error.lineno}, column {error.colno})"
        ) from error
    except RecursionError as error:
        raise MeshFileError(path, "is not valid JSON (nested too deeply)") from error
    if not isinstance(data, dict):
        raise MeshFileError(path, f"must hold a JSON object, got {type(data).__name__}")
    return data


def _entry(data: dict[str, Any], key: str, path: Path, expected: str) -> Any:
    if key not in data:
        raise MeshFileError(path, f"missing key {key!r} ({expected}); rebuild it with {MAKE_SCRIPT}")
    return data[key]


def _is_number(value: object) -> bool:
    # bool is an int in Python, but `true` is no number in a JSON file.
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _number(
    data: dict[str, Any], key: str, path: Path, expected: str, valid: Callable[[float], bool]
) -> float:
    value = _entry(data, key, path, expected)
    if not (_is_number(value) and valid(float(value))):
        raise MeshFileError(path, f"key {key!r} must be {expected}, got {_describe(value)}")
    return float(value)


def _integer(data: dict[str, Any], key: str, path: Path, expected: str, valid: Callable[[int], bool]) -> int:
    value = _entry(data, key, path, expected)
    if not (isinstance(value, int) and not isinstance(value, bool) and valid(value)):
        raise MeshFileError(path, f"key {key!r} must be {expected}, got {_describe(value)}")
    return value


def _sequence(
    data: dict[str, Any], key: str, path: Path, length: int, item: str, valid: Callable[[object], bool]
) -> list[Any]:
    expected = f"a list of {length} {item}"
    value = _entry(data, key, path, expected)
    if not isinstance(value, list) or len(value) != length:
        raise MeshFileError(path, f"key {key!r} must be {expected}, got {_describe(value)}")
    bad = [index for index, entry in enumerate(value) if not valid(entry)]
    if bad:
        raise MeshFileError(
            path,
            f"key {key!r} must be {expected}; entries {bad[:10]} are not, e.g. {_describe(value[bad[0]])}",
        )
    return value


__all__ = ["SUGGESTED_NUMBERS", "CreatureSidecar", "read_creature_sidecar"]
