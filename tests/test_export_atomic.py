"""Re-exporting over a series: the ``.pvd`` always lists a complete series, and foreign files survive.

Each test writes an old series, disturbs a new export (an exception at a given frame, a killed process,
bad input) and then checks the folder as a reader sees it: every file the ``.pvd`` lists exists and
holds the positions of the old or of the new export, all of one, none of the other.
"""

from __future__ import annotations

import errno
import importlib.util
import json
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch

import energysim as es
from energysim.export import VTKSeries, export_rollout, render_gif, render_mp4
from energysim.export.series import MARKER_NAME

OLD_FRAMES, NEW_FRAMES = 5, 8
OLD_SHIFT, NEW_SHIFT = 0.0, 10.0  # m: a frame's points tell which export wrote it


def _scene_and_states(frames: int, shift: float) -> tuple[es.Scene, torch.Tensor]:
    """A small elastic box and `frames` states, frame k translated by `shift` + 0.01 k in x."""
    scene = es.Scene(es.TetMesh.box(size=(0.3, 0.1, 0.1), cells=(3, 1, 1)), dt=0.01, gravity=None)
    scene.add(es.NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    offset = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    states = [
        scene.initial_state(positions=scene.rest_positions + (shift + 0.01 * k) * offset)
        for k in range(frames)
    ]
    return scene, torch.stack(states)


def _tree(folder: Path) -> dict[str, bytes | None]:
    """Every path under `folder` with its bytes (None for folders)."""
    return {
        p.relative_to(folder).as_posix(): None if p.is_dir() else p.read_bytes() for p in folder.rglob("*")
    }


def _check_complete_series(pvd: Path, frames: int, shift: float, base: Path | None = None) -> None:
    """`pvd` lists exactly `frames` frames at k·h, each a whole file with the points of that export.

    Files are relative to `base` (default: the pvd's folder); only with the default is pyvista asked too.
    """
    scene, states = _scene_and_states(frames, shift)
    x, _ = scene.split_state(states)
    datasets = ET.parse(pvd).getroot().findall("./Collection/DataSet")
    assert [float(d.get("timestep")) for d in datasets] == pytest.approx([k * 0.01 for k in range(frames)])
    for k, dataset in enumerate(datasets):
        points = meshio.read((base or pvd.parent) / dataset.get("file")).points
        np.testing.assert_allclose(points, x[k].numpy(), rtol=0, atol=1e-12)
    if base is not None:
        return
    pv = pytest.importorskip("pyvista")
    reader = pv.get_reader(str(pvd))
    assert len(reader.time_values) == frames
    reader.set_active_time_value(reader.time_values[-1])
    np.testing.assert_allclose(reader.read()[0].points, x[-1].numpy(), rtol=0, atol=1e-12)


def _marked_folders(folder: Path) -> list[Path]:
    return sorted(p.parent for p in folder.glob(f"*/{MARKER_NAME}"))


def _export_old(folder: Path) -> Path:
    scene, states = _scene_and_states(OLD_FRAMES, OLD_SHIFT)
    return export_rollout(scene, states, folder)


def _export_new(folder: Path) -> Path:
    scene, states = _scene_and_states(NEW_FRAMES, NEW_SHIFT)
    return export_rollout(scene, states, folder)


# ------------------------------------------------------------------------------------ failures mid-export


@pytest.mark.parametrize(
    "error",
    [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()],
    ids=["ENOSPC", "interrupt"],
)
def test_a_failure_at_frame_3_leaves_the_old_series_byte_for_byte(tmp_path: Path, monkeypatch, error) -> None:
    pvd = _export_old(tmp_path)
    before = _tree(tmp_path)
    real_write, calls = meshio.write, []

    def write_until_frame_3(path, mesh, *args, **kwargs):
        calls.append(path)
        if len(calls) == 4:  # frames 0, 1, 2 are on disk; frame 3 fails half written
            Path(path).write_bytes(b"<VTKFile half")
            raise error
        return real_write(path, mesh, *args, **kwargs)

    monkeypatch.setattr(meshio, "write", write_until_frame_3)
    with pytest.raises(type(error)):
        _export_new(tmp_path)
    assert len(calls) == 4
    assert _tree(tmp_path) == before  # the new frames and their folder are gone, nothing else changed
    _check_complete_series(pvd, OLD_FRAMES, OLD_SHIFT)


def test_a_failed_pvd_switch_leaves_the_old_series(tmp_path: Path, monkeypatch) -> None:
    pvd = _export_old(tmp_path)
    before = _tree(tmp_path)
    real_replace = os.replace

    def disk_full_on_pvd(src, dst, *args, **kwargs):
        if str(dst).endswith(".pvd"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", disk_full_on_pvd)
    with pytest.raises(OSError, match="No space left"):
        _export_new(tmp_path)
    assert _tree(tmp_path) == before
    _check_complete_series(pvd, OLD_FRAMES, OLD_SHIFT)


def test_every_frame_is_on_disk_when_the_pvd_switches(tmp_path: Path, monkeypatch) -> None:
    _export_old(tmp_path)
    real_replace, seen = os.replace, []

    def check_then_replace(src, dst, *args, **kwargs):
        if str(dst).endswith(".pvd"):
            # the file about to become the .pvd must list only complete frames of the new export
            _check_complete_series(Path(src), NEW_FRAMES, NEW_SHIFT, base=Path(dst).parent)
            seen.append(dst)
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", check_then_replace)
    pvd = _export_new(tmp_path)
    assert [Path(p) for p in seen] == [pvd]
    _check_complete_series(pvd, NEW_FRAMES, NEW_SHIFT)
    assert len(_marked_folders(tmp_path)) == 1  # the old series' folder is removed


# ------------------------------------------------------------------------------------------ killed process

_CHILD = textwrap.dedent(
    """
    import os, pathlib, sys, time
    sys.path.insert(0, {tests!r})
    import meshio
    from test_export_atomic import _export_new

    folder, signal_file, mode = pathlib.Path({folder!r}), pathlib.Path({signal_file!r}), {mode!r}

    def stop_here():
        signal_file.write_text(str(os.getpid()))
        time.sleep(120)  # the test kills this process here

    if mode == "frames":
        real_write, calls = meshio.write, []
        def write(path, mesh, *args, **kwargs):
            calls.append(path)
            if len(calls) == 4:
                stop_here()
            return real_write(path, mesh, *args, **kwargs)
        meshio.write = write
    elif mode == "pvd":
        real_replace = os.replace
        def replace(src, dst, *args, **kwargs):
            if str(dst).endswith(".pvd"):
                stop_here()
            return real_replace(src, dst, *args, **kwargs)
        os.replace = replace
    elif mode == "cleanup":
        real_unlink, removed = pathlib.Path.unlink, []
        def unlink(self, *args, **kwargs):
            if self.suffix == ".vtu":
                removed.append(self)
                if len(removed) == 3:  # two old frames gone, three left
                    stop_here()
            return real_unlink(self, *args, **kwargs)
        pathlib.Path.unlink = unlink
    _export_new(folder)
    """
)


@pytest.mark.parametrize(("mode", "survivor"), [("frames", "old"), ("pvd", "old"), ("cleanup", "new")])
def test_a_killed_export_leaves_a_complete_series(tmp_path: Path, mode: str, survivor: str) -> None:
    folder, signal_file = tmp_path / "out", tmp_path / "stopped"
    pvd = _export_old(folder)
    (folder / "notes.txt").write_text("mine")
    code = _CHILD.format(
        tests=str(Path(__file__).parent), folder=str(folder), signal_file=str(signal_file), mode=mode
    )
    env = dict(os.environ, OMP_NUM_THREADS="1")
    child = subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not signal_file.exists():
            if child.poll() is not None:
                pytest.fail(f"the export ended before the kill: {child.stderr.read().decode()[-2000:]}")
            assert time.monotonic() < deadline, "the export never reached the point of the kill"
            time.sleep(0.05)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait()
        child.stderr.close()
    assert child.returncode == -signal.SIGKILL

    if survivor == "old":
        _check_complete_series(pvd, OLD_FRAMES, OLD_SHIFT)
    else:
        _check_complete_series(pvd, NEW_FRAMES, NEW_SHIFT)
    assert len(_marked_folders(folder)) == 2  # the listed series and the killed export's leftovers
    # the next export removes the leftovers: their writer has ended
    scene, states = _scene_and_states(3, 20.0)
    export_rollout(scene, states, folder)
    _check_complete_series(pvd, 3, 20.0)
    (kept,) = _marked_folders(folder)
    assert sorted(p.name for p in folder.iterdir()) == sorted(["frame.pvd", "notes.txt", kept.name])
    assert (folder / "notes.txt").read_text() == "mine"


# ---------------------------------------------------------------------------------------- foreign files


def test_files_the_library_did_not_write_survive_every_export(tmp_path: Path) -> None:
    # a hand-written .pvd over the user's own frame, a look-alike folder without the marker, notes
    user_frame = meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))])
    meshio.write(tmp_path / "frame_00042.vtu", user_frame)
    (tmp_path / "frame.pvd").write_text(
        '<?xml version="1.0"?>\n<VTKFile type="Collection"><Collection>'
        '<DataSet timestep="0" file="frame_00042.vtu"/>'
        '<DataSet timestep="1" file="frame.mine/frame_00000.vtu"/>'
        "</Collection></VTKFile>\n"
    )
    (tmp_path / "frame.mine").mkdir()
    (tmp_path / "frame.mine" / "frame_00000.vtu").write_text("the user's")
    (tmp_path / "notes.txt").write_text("notes")
    foreign = _tree(tmp_path)
    del foreign["frame.pvd"]

    pvd = _export_old(tmp_path)
    (first,) = _marked_folders(tmp_path)
    (first / "notes.txt").write_text("a note inside the series folder")
    _export_new(tmp_path)
    _export_old(tmp_path)

    _check_complete_series(pvd, OLD_FRAMES, OLD_SHIFT)
    after = _tree(tmp_path)
    assert {key: after.get(key) for key in foreign} == foreign
    # the first series' frames and marker are gone; the folder stays for the note in it
    assert sorted(p.name for p in first.iterdir()) == ["notes.txt"]
    assert len(_marked_folders(tmp_path)) == 1


def test_a_live_series_of_this_process_is_not_taken_for_leftovers(tmp_path: Path) -> None:
    scene, states = _scene_and_states(2, OLD_SHIFT)
    x, _ = scene.split_state(states)
    live = VTKSeries(tmp_path, scene.mesh.elements)
    live.write(0.0, x[0])
    _export_new(tmp_path)  # commits, then looks for leftovers
    assert (live.series_folder / "frame_00000.vtu").is_file()
    live.write(0.01, x[1])
    pvd = live.commit()
    _check_complete_series(pvd, 2, OLD_SHIFT)
    assert _marked_folders(tmp_path) == [live.series_folder]


def test_a_folder_of_a_writer_on_another_host_or_name_is_kept(tmp_path: Path) -> None:
    for folder_name, marker in [
        ("frame.elsewhere", {"name": "frame", "pid": 1, "host": "another-host"}),
        ("frame.x.unfinished", {"name": "frame.x", "pid": 2**22 + 1, "host": None}),
    ]:
        (tmp_path / folder_name).mkdir()
        marker = {"format": "energysim.vtk_series", **marker}
        (tmp_path / folder_name / MARKER_NAME).write_text(json.dumps(marker))
        (tmp_path / folder_name / "frame_00000.vtu").write_text("frame")
    before = _tree(tmp_path)
    pvd = _export_new(tmp_path)
    _check_complete_series(pvd, NEW_FRAMES, NEW_SHIFT)
    after = _tree(tmp_path)
    assert {key: after.get(key) for key in before} == before


# -------------------------------------------------------------------------------------------- bad input


def test_bad_input_is_refused_before_anything_is_written(tmp_path: Path, monkeypatch) -> None:
    pvd = _export_old(tmp_path)
    (tmp_path / "notes.txt").write_text("notes")
    before = _tree(tmp_path)
    scene, states = _scene_and_states(3, NEW_SHIFT)
    num_state = 2 * scene.num_dofs
    actions = torch.zeros(2, 1, dtype=torch.float64)

    with pytest.raises(NotADirectoryError, match=r"notes\.txt' is a file"):
        export_rollout(scene, states, tmp_path / "notes.txt")
    with pytest.raises(NotADirectoryError, match=r"notes\.txt' is a file"):
        export_rollout(scene, states, tmp_path / "notes.txt" / "run")
    with pytest.raises(
        ValueError, match=rf"states must have shape \[F, {num_state}\].*got \(3, {num_state - 1}\)"
    ):
        export_rollout(scene, states[:, :-1], tmp_path)
    with pytest.raises(ValueError, match=rf"states\[1\] has shape \({num_state - 3},\)"):
        export_rollout(scene, [states[0], states[1, :-3]], tmp_path)
    with pytest.raises(ValueError, match=r"states \[1\] hold NaN or inf"):
        export_rollout(scene, states.index_fill(0, torch.tensor([1]), torch.inf), tmp_path)
    with pytest.raises(ValueError, match=r"actions must have shape \[2, a\].*\[3, a\].*got \(5, 1\)"):
        export_rollout(scene, states, tmp_path, actions=torch.zeros(5, 1))
    with pytest.raises(ValueError, match=r"actions \[1\] hold NaN or inf"):
        export_rollout(scene, states, tmp_path, actions=actions.index_fill(0, torch.tensor([1]), torch.nan))
    with pytest.raises(ValueError, match="path separators"):
        export_rollout(scene, states, tmp_path, name="a/b")

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    with monkeypatch.context() as mp:
        mp.setattr(tempfile, "mkdtemp", refuse)
        with pytest.raises(PermissionError, match=rf"folder '{tmp_path}' is not writable"):
            export_rollout(scene, states, tmp_path)
    assert _tree(tmp_path) == before
    _check_complete_series(pvd, OLD_FRAMES, OLD_SHIFT)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root may write anywhere")
def test_a_read_only_folder_is_refused_and_left_as_it_was(tmp_path: Path) -> None:
    pvd = _export_old(tmp_path)
    before = _tree(tmp_path)
    tmp_path.chmod(0o555)
    try:
        with pytest.raises(PermissionError, match="not writable"):
            _export_new(tmp_path)
    finally:
        tmp_path.chmod(0o755)
    assert _tree(tmp_path) == before
    _check_complete_series(pvd, OLD_FRAMES, OLD_SHIFT)


# ----------------------------------------------------------------------------------------- single files


@pytest.fixture(scope="module")
def offscreen() -> None:
    pv = pytest.importorskip("pyvista")
    try:
        plotter = pv.Plotter(off_screen=True, window_size=[32, 32])
        plotter.add_mesh(pv.Sphere())
        plotter.screenshot(None, return_img=True)
        plotter.close()
    except Exception as err:  # noqa: BLE001 - any failure here means no off-screen OpenGL
        pytest.skip(f"pyvista cannot create an off-screen render window: {err}")


@pytest.mark.parametrize("kind", ["gif", "mp4"])
def test_a_failed_animation_keeps_the_previous_file(
    tmp_path: Path, offscreen, monkeypatch, kind: str
) -> None:
    if kind == "mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        pytest.skip("no mp4 encoder installed")
    import pyvista as pv
    from PIL import Image

    render = {"gif": render_gif, "mp4": render_mp4}[kind]
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    frames, faces = [vertices + 0.1 * k for k in range(3)], np.array([[0, 1, 2]])
    dest = render(tmp_path / f"a.{kind}", frames, faces, window_size=(64, 48))
    before = dest.read_bytes()
    real_write_frame = pv.Plotter.write_frame

    def disk_full_at_frame_2(self):
        if self._frames_written == 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        self._frames_written = 1
        return real_write_frame(self)

    def disk_full_in_pillow(self, fp, *args, **kwargs):  # the GIF writer without imageio
        Path(fp).write_bytes(b"GIF89a half")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pv.Plotter, "_frames_written", 0, raising=False)
    monkeypatch.setattr(pv.Plotter, "write_frame", disk_full_at_frame_2)
    monkeypatch.setattr(Image.Image, "save", disk_full_in_pillow)
    with pytest.raises(OSError, match="No space left"):
        render(dest, [f + 1.0 for f in frames], faces, window_size=(64, 48))
    assert dest.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [dest.name]


def test_a_series_dropped_without_commit_warns_that_its_frames_are_not_published(tmp_path):
    import gc

    series = VTKSeries(tmp_path, cells=np.array([[0, 1, 2, 3]]), name="frame")
    series.write(0.0, np.eye(4, 3))
    with pytest.warns(UserWarning, match="1 frame\\(s\\).*call commit"):
        del series
        gc.collect()
