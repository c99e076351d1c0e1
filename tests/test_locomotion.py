"""The walking scripts at a short duration: every creature goes forward with no NaN and never into the
ground, the checks have teeth, the scripts' gaits are the shipped ones, and the command line writes its
files. The long form (5 s: the worm and the quadruped each travel half a body length) is heavy."""

from __future__ import annotations

import dataclasses
import importlib
import math
import os
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch

from energysim.creatures import CREATURES, load_creature

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))
locomotion = importlib.import_module("_locomotion")

FULL = os.environ.get("ENERGYSIM_HEAVY") == "1"
# Short runs of 30 steps: the check holds them to forward progress, to the script's speed for the
# part after the one-period ramp-in (the quadruped's and the walker's ramps end before 0.5 s), and
# to its backslide tolerance.
SHORT_SECONDS = dict.fromkeys(CREATURES, 0.5)


walk_script = importlib.import_module("walk")


def spec_of(name: str):
    return walk_script.SPECS[name]


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def walks() -> dict[tuple[str, float], tuple]:
    """Walks made on first use and shared by the tests: (name, seconds) -> (scene, gait, rollout)."""
    return {}


def walk(walks: dict, name: str, seconds: float) -> tuple:
    if (name, seconds) not in walks:
        spec = spec_of(name)
        creature = load_creature(name)
        scene = locomotion.build_scene(creature, spec.dt, spec.friction, "newton-cg", spec.tol)
        gait = locomotion.default_gait(spec, creature)
        walks[name, seconds] = (scene, gait, locomotion.run(scene, gait, seconds, progress=False))
    return walks[name, seconds]


def check(name: str, scene, gait, rollout) -> None:
    spec = spec_of(name)
    length = locomotion.body_length(scene)
    locomotion.check(rollout, length, spec.min_speed, spec.max_backslide, settle=gait.ramp)


@pytest.mark.parametrize("name", CREATURES)
def test_short_walk_goes_forward_and_stays_above_the_ground(walks, name: str) -> None:
    scene, gait, rollout = walk(walks, name, SHORT_SECONDS[name])
    # the script's own check: no NaN, min height >= 0 at every step, forward, no backslide
    check(name, scene, gait, rollout)
    figures = locomotion.measure(rollout, locomotion.body_length(scene))
    assert figures["distance (m)"] > 0
    assert figures["unconverged steps"] == 0
    # it starts in contact (d̂/2 above the ground, inside the barrier's reach) and never touches it
    heights = rollout.history["min_height"]
    assert float(heights[0]) == pytest.approx(0.5 * locomotion.ground(scene).barrier_distance, rel=1e-9)
    assert float(heights.min()) > 0


@pytest.mark.heavy
@pytest.mark.parametrize("name", ["worm", "quadruped"])
def test_worm_and_quadruped_walk_half_a_body_length_in_5_s(walks, name: str) -> None:
    # CI runs 1 s (the ramp and a few gait periods) at the script's speed; ENERGYSIM_HEAVY=1 the full 5 s
    seconds = 5.0 if FULL else 1.0
    scene, gait, rollout = walk(walks, name, seconds)
    check(name, scene, gait, rollout)
    figures = locomotion.measure(rollout, locomotion.body_length(scene))
    if FULL:
        assert figures["distance (body lengths)"] >= 0.5
    # sliding backwards: the centre of mass never falls more than the tolerance behind the farthest
    # point it has reached, so it never ends up behind the start either
    com = rollout.history["com"][:, 0]
    assert float((com - com[0]).min()) >= -spec_of(name).max_backslide * locomotion.body_length(scene)


def test_check_has_teeth(walks) -> None:
    # the quadruped's ramp ends at 0.25 s, so the short walk is also held to the script's speed
    scene, gait, rollout = walk(walks, "quadruped", SHORT_SECONDS["quadruped"])
    length = locomotion.body_length(scene)
    spec = spec_of("quadruped")
    locomotion.check(rollout, length, spec.min_speed, spec.max_backslide, settle=gait.ramp)

    def with_history(**changes: torch.Tensor):
        return dataclasses.replace(rollout, history={**rollout.history, **changes})

    def fails(match: str, changed) -> None:
        with pytest.raises(AssertionError, match=match):
            locomotion.check(changed, length, spec.min_speed, spec.max_backslide, settle=gait.ramp)

    com = rollout.history["com"]
    steps = com.shape[0]
    # the same path walked backwards
    fails("went", with_history(com=2 * com[:1] - com))
    # forward in the end, but half-way it slides back 0.1 body lengths for a few steps
    back = torch.zeros_like(com)
    back[steps // 2 : steps // 2 + 3, 0] = 0.1 * length
    fails("slid back", with_history(com=com - back))
    # forward, but too slowly: a tenth of the distance
    fails("went", with_history(com=com[:1] + 0.1 * (com - com[:1])))
    heights = rollout.history["min_height"].clone()
    heights[3] = -1e-6
    fails("into the ground", with_history(min_height=heights))
    finite = rollout.history["finite"].clone()
    finite[-1] = False
    fails("NaN", with_history(finite=finite))


@pytest.mark.parametrize("name", CREATURES)
def test_scripts_default_gaits_are_the_shipped_ones(name: str) -> None:
    creature = load_creature(name)
    spec = spec_of(name)
    phases = np.array(spec.phases(spec.phase_lag))
    difference = np.angle(np.exp(1j * (phases - np.array(creature.gait_phases))))
    np.testing.assert_allclose(difference, 0.0, atol=1e-9)
    steady = dataclasses.replace(locomotion.default_gait(spec, creature), ramp=0.0)
    for time in (0.0, 0.13, 1.7):
        torch.testing.assert_close(steady.action(time), creature.gait_action(time), rtol=0, atol=1e-9)


def test_gait_ramp_eases_the_muscles_in() -> None:
    gait = locomotion.Gait(2.0, 0.8, (math.pi / 2, -math.pi / 2), ramp=0.5)
    full = torch.tensor([0.8, -0.8], dtype=torch.float64)
    torch.testing.assert_close(gait.action(0.0), torch.zeros(2, dtype=torch.float64))
    # half-way through the ramp sin²(π/4) = 1/2, and there sin(2π f t ± π/2) = ∓1
    torch.testing.assert_close(gait.action(0.25), -0.5 * full)
    # after the ramp, full strength: at t = 1.5 s, 3 whole periods, sin(±π/2) = ±1
    torch.testing.assert_close(gait.action(1.5), full)
    with pytest.raises(ValueError, match="amplitude"):
        locomotion.Gait(1.0, 1.5, (0.0,))
    with pytest.raises(ValueError, match="frequency"):
        locomotion.Gait(0.0, 1.0, (0.0,))


def test_refined_creature_splits_every_voxel() -> None:
    coarse = load_creature("crawler2d")
    fine = locomotion.refined_creature("crawler2d", 2)
    assert fine.mesh.num_elements == 4 * coarse.mesh.num_elements
    assert fine.body_length == pytest.approx(coarse.body_length, rel=1e-12)
    assert float(fine.mesh.vertices[:, 1].min()) == 0.0
    # every actuator drives 4 times as many triangles (the crawler has no passive ones)
    counts = torch.bincount(fine.actuators) / torch.bincount(coarse.actuators)
    torch.testing.assert_close(counts, torch.full_like(counts, 4.0))
    assert fine.gait_phases == coarse.gait_phases


def test_main_writes_vtk_frames_pictures_and_checks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["--creature", "crawler2d", "--seconds", "0.2", "--frames-every", "3", "--quiet"]
    assert walk_script.main([*argv, "--window-size", "160", "96", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "check passed" in printed and "travelled +" in printed and "x real time" in printed
    # 12 steps saved at 0, 3, ..., 12
    sets = ET.parse(tmp_path / "frame.pvd").getroot().findall("./Collection/DataSet")
    times = [float(d.get("timestep")) for d in sets]
    np.testing.assert_allclose(times, [k / 60 for k in range(0, 13, 3)], rtol=0, atol=1e-12)
    creature = load_creature("crawler2d")
    spec = spec_of("crawler2d")
    gait = locomotion.default_gait(spec, creature)
    actuated = creature.actuators >= 0
    for time, data_set in zip(times, sets, strict=True):
        frame = meshio.read(tmp_path / data_set.get("file"))
        assert frame.points.shape == (creature.mesh.num_vertices, 3)
        assert frame.cells_dict["triangle"].shape == (creature.mesh.num_elements, 3)
        assert (frame.points[:, 1] > 0).all()
        action = gait.action(time).numpy()
        activation = frame.cell_data["activation"][0]
        np.testing.assert_allclose(activation[actuated], action[creature.actuators[actuated]], atol=1e-12)
        assert frame.cell_data["strain_energy_density"][0].shape == (creature.mesh.num_elements,)
    for picture in ("crawler2d.png", "crawler2d.gif"):
        assert (tmp_path / picture).stat().st_size > 1000


def test_bench_creatures_reports_a_small_error_beside_each_time(tmp_path: Path) -> None:
    bench_creatures = importlib.import_module("bench_creatures")
    argv = ["--creatures", "crawler2d", "--seconds", "0.1", "--no-plot", "--out", str(tmp_path)]
    (row,) = bench_creatures.main(argv)
    assert row.elements == 200 and row.kind == "triangles" and row.steps == 6 and row.converged == "6/6"
    assert row.ms_per_step > 0 and row.realtime_factor == pytest.approx(row.dt / (1e-3 * row.ms_per_step))
    assert row.median_ms_per_step > 0
    # a residual r (m/s) moves a step's end by about h·r: 6 steps at 1e-4 m/s, well under 6 h r = 1e-5 m
    assert row.error_m < 6 * row.dt * row.tol
    table = (tmp_path / "bench_creatures.md").read_text()
    assert "| crawler2d | 200 triangles |" in table
    assert (tmp_path / "bench_creatures.csv").read_text().count("\n") == 2
