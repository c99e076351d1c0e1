"""The example scripts at a tiny size: their checks pass, fail when they should, and their files appear."""

from __future__ import annotations

import dataclasses
import importlib
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import pyvista
import torch

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
H = 1 / 60


def _script(name: str) -> ModuleType:
    # scripts/ is not a package: its modules import each other (_common) as top-level modules
    if str(SCRIPTS) not in sys.path:
        sys.path.insert(0, str(SCRIPTS))
    return importlib.import_module(name)


drop_box = _script("drop_box")
cantilever = _script("cantilever")


pytestmark = pytest.mark.usefixtures("one_thread")


def _expected_frames(steps: int, every: int) -> list[int]:
    """Saved steps: every `every`-th one and always the last."""
    return sorted({*range(0, steps + 1, every), steps})


def _check_series(folder: Path, frame_steps: list[int], num_vertices: int, num_cells: int) -> None:
    pvd = folder / "frame.pvd"
    assert pvd.is_file()
    reader = pyvista.get_reader(str(pvd))
    np.testing.assert_allclose(reader.time_values, [k * H for k in frame_steps], rtol=0, atol=1e-12)
    assert len(list(folder.glob("frame.*/frame_*.vtu"))) == len(frame_steps)
    reader.set_active_time_value(reader.time_values[-1])
    grid = reader.read()[0]
    assert grid.n_points == num_vertices and grid.n_cells == num_cells
    assert grid.point_data["velocity"].shape == (num_vertices, 3)
    assert grid.cell_data["energy_density"].shape == (num_cells,)
    assert np.isfinite(grid.cell_data["energy_density"]).all()


def test_drop_box_main_writes_every_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--resolution", "2", "--seconds", "0.2", "--no-render", "--out", str(tmp_path)]
    assert drop_box.main(argv) == 0
    printed = capsys.readouterr().out
    assert "check passed" in printed and "ms per step" in printed
    # a 2×2×2 cube: 27 vertices, 48 tets
    _check_series(tmp_path, _expected_frames(12, 1), 27, 48)
    assert not list(tmp_path.glob("*.png")) and not list(tmp_path.glob("*.gif"))


def test_cantilever_main_saves_every_nth_frame_and_the_last(tmp_path: Path) -> None:
    # 0.8 s: the coarse beam's tip turns back up at about 0.6 s, which the check requires
    argv = ["--resolution", "2", "--seconds", "0.8", "--frames-every", "5", "--no-render"]
    argv += ["--out", str(tmp_path)]
    assert cantilever.main(argv) == 0
    # a 10×2×2 beam: 99 vertices, 240 tets; 48 steps saved at 0, 5, ..., 45 and 48
    _check_series(tmp_path, _expected_frames(48, 5), 99, 240)


def test_drop_box_run_and_check_directly() -> None:
    scene = drop_box.build_scene(resolution=2)
    rollout = drop_box.run(scene, seconds=0.1, progress=False)
    drop_box.check(rollout)
    assert rollout.vtk is None
    assert rollout.positions.shape == (7, scene.num_vertices, 3)
    assert len(rollout.stats) == 6 and all(s.converged for s in rollout.stats)
    torch.testing.assert_close(rollout.times, torch.arange(7, dtype=torch.float64) * H)
    # the check has teeth: a centre of mass 1 µm off free fall is far beyond what the residuals allow
    history = dict(rollout.history)
    history["com"] = history["com"] + torch.tensor([0.0, 1e-6, 0.0], dtype=torch.float64)
    history["com"][0] = rollout.history["com"][0]
    with pytest.raises(AssertionError, match="free fall"):
        drop_box.check(dataclasses.replace(rollout, history=history))


@pytest.mark.parametrize("solver", ["lbfgs", "adam"])
def test_drop_box_check_passes_with_other_solvers(solver: str) -> None:
    rollout = drop_box.run(drop_box.build_scene(resolution=2, solver=solver), seconds=0.05, progress=False)
    drop_box.check(rollout)
    assert rollout.stats[0].solver == {"lbfgs": "LBFGS", "adam": "Adam"}[solver]


def test_cantilever_run_and_check_directly() -> None:
    scene = cantilever.build_scene(resolution=2)
    assert int(scene.fixed.sum()) == 9  # the 3×3 vertices of the x = 0 face
    rollout = cantilever.run(scene, seconds=0.8, progress=False)
    cantilever.check(rollout)
    figures = cantilever.measure(rollout)
    assert figures["clamped vertex motion (m, m/s)"] == 0.0
    assert figures["largest energy rise (J)"] < 0
    # too short a run to see the tip come back up: the check must say so rather than pass
    short = cantilever.run(scene, seconds=0.2, progress=False)
    with pytest.raises(AssertionError, match="never came back up"):
        cantilever.check(short)


def test_rendering_writes_png_and_gif(tmp_path: Path) -> None:
    from PIL import Image

    argv = ["--resolution", "2", "--seconds", "0.1", "--out", str(tmp_path)]
    assert drop_box.main(argv) == 0
    with Image.open(tmp_path / "drop_box.png") as png:
        pixels = np.asarray(png.convert("RGB"))
    # not a blank picture: the cube covers a fair number of non-white pixels
    assert (pixels.min(axis=-1) < 200).sum() > 1000
    with Image.open(tmp_path / "drop_box.gif") as gif:
        # 7 frames at 60 fps are shown at 20 fps: frames 0, 3, 6
        assert gif.n_frames == 3
