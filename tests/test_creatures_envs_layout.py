"""The creature and environment packages keep one idea per module and every name they export.

`energysim.creatures` and `energysim.envs.core` are read by scripts, tests and users under the
names below; each must stay importable there and be the very object its defining module holds.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import pytest

import energysim.creatures as creatures

ROOT = Path(__file__).resolve().parents[1] / "energysim"
MAX_MODULE_LINES = 400

CREATURE_NAMES = {
    "creature": ["Creature", "STANDARD_GRAVITY"],
    "loading": ["load_creature"],
    "resting": ["resting_state", "scene_ground"],
    "shipped_files": [
        "ASSETS_FOLDER",
        "ASSETS_PACKAGE",
        "CREATURES",
        "MAKE_SCRIPT",
        "MESHES_ENV",
        "default_meshes_dir",
        "shipped_meshes_dir",
    ],
}
ENV_CORE_NAMES = {
    "actions": ["as_action_array"],
    "config": ["CreatureEnvConfig", "LEAPFROG_ACTIVATION_TIME_CONSTANT", "LEAPFROG_VISCOSITY"],
    "core": ["CreatureSimulation"],
    "transition": ["Transition"],
}


def _sources(package: str) -> list[Path]:
    return sorted((ROOT / package).glob("*.py"))


@pytest.mark.parametrize("package", ["creatures", "envs"])
def test_every_module_holds_at_most_400_lines(package: str) -> None:
    lengths = {path.name: len(path.read_text(encoding="utf-8").splitlines()) for path in _sources(package)}
    assert len(lengths) > 1
    assert {name: n for name, n in lengths.items() if n > MAX_MODULE_LINES} == {}


def test_creature_names_are_the_defining_modules_objects() -> None:
    exported = set(creatures.__all__)
    for module_name, names in CREATURE_NAMES.items():
        module = importlib.import_module(f"energysim.creatures.{module_name}")
        for name in names:
            assert name in exported
            assert getattr(creatures, name) is getattr(module, name)
    assert exported == {name for names in CREATURE_NAMES.values() for name in names}


def test_env_core_names_are_the_defining_modules_objects() -> None:
    pytest.importorskip("gymnasium")
    env_core = importlib.import_module("energysim.envs.core")
    envs = importlib.import_module("energysim.envs")
    assert set(env_core.__all__) == {name for names in ENV_CORE_NAMES.values() for name in names}
    for module_name, names in ENV_CORE_NAMES.items():
        module = importlib.import_module(f"energysim.envs.{module_name}")
        for name in names:
            assert getattr(env_core, name) is getattr(module, name)
    for name in envs.__all__:
        assert hasattr(envs, name)
    assert envs.CreatureEnvConfig is env_core.CreatureEnvConfig
    assert envs.Transition is env_core.Transition


def test_a_loaded_creature_holds_its_sidecars_numbers() -> None:
    # the JSON read by the standard library alone, against the checked reading of it
    from energysim.creatures.sidecar import SUGGESTED_NUMBERS

    worm = creatures.load_creature("worm")
    raw = json.loads(creatures.shipped_meshes_dir().joinpath("worm.json").read_text(encoding="utf-8"))
    assert worm.num_actuators == raw["num_actuators"] == 10
    assert worm.gait_phases == tuple(float(phase) for phase in raw["gait_phases"])
    assert worm.actuator_names == tuple(raw["actuator_names"])
    assert len(SUGGESTED_NUMBERS) == 7
    for key, _, _ in SUGGESTED_NUMBERS:
        assert getattr(worm, key) == float(raw[key])
