"""The trajectory-optimisation examples, each at a small size, must pass their own physical checks."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import identify_material  # noqa: E402
import optimize_control  # noqa: E402
import throw_to_target  # noqa: E402


def test_throw_to_target_lands_on_the_target():
    scene = throw_to_target.build_scene(resolution=2)
    result = throw_to_target.run(scene, steps=20)
    throw_to_target.check(result)
    assert len(result.distances) < 25


def test_identify_material_recovers_youngs_modulus_and_poissons_ratio():
    result = identify_material.run(steps=12, iterations=40, resolution=1)
    identify_material.check(result)
    assert abs(result.youngs_modulus / identify_material.TRUE_YOUNGS - 1) < 0.01
    assert abs(result.poissons_ratio / identify_material.TRUE_POISSON - 1) < 0.01


def test_optimize_control_reaches_the_target():
    scene = optimize_control.build_scene(resolution=1, dt=0.1)
    result = optimize_control.run(scene, steps=10, iterations=60, lr=0.2)
    optimize_control.check(result)
    assert result.distances[-1] < 1e-2  # m, from a start about 10 cm away
    assert result.distances[0] > 0.05
