"""Tests of energysim.export: VTK frames / PVD series (round trips, atomicity) and off-screen rendering."""

from __future__ import annotations

import importlib.util
import logging
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch
from conftest import random_rotation

import energysim as es
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.export import (
    VTKSeries,
    export_rollout,
    render_gif,
    render_mp4,
    render_png,
    write_pvd,
    write_vtu,
)

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _cube_tets() -> tuple[np.ndarray, np.ndarray]:
    """Unit cube split into 6 tetrahedra around the diagonal 0-6: `[8, 3]` vertices, `[6, 4]` cells."""
    v = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
    # corner index = x + 2y + 4z; the six tets share the diagonal (0, 7)
    cells = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    return v, cells


def _boundary_triangles(cells: np.ndarray) -> np.ndarray:
    """Faces of a tet mesh that belong to exactly one tet, `[s, 3]`."""
    faces = np.concatenate([cells[:, [a, b, c]] for a, b, c in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))])
    keys, counts = np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)
    return keys[counts == 1]


def _square_tris() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.5, 0.5]])
    return v, np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])


# ---------------------------------------------------------------------------------------------- VTK files


def test_write_vtu_round_trip_tets(tmp_path: Path) -> None:
    v, cells = _cube_tets()
    rng = np.random.default_rng(0)
    v = v + 1e-3 * rng.standard_normal(v.shape)  # non-round values probe binary precision
    temp = rng.standard_normal(8)
    vel = rng.standard_normal((8, 3))
    vol = rng.uniform(0.1, 1.0, 6)
    out = write_vtu(
        tmp_path / "a.vtu",
        torch.tensor(v, requires_grad=True),  # tensors with grad are detached, not rejected
        torch.tensor(cells),
        point_data={"temperature": temp, "velocity": torch.tensor(vel)},
        cell_data={"volume": vol},
    )
    assert out == tmp_path / "a.vtu"
    m = meshio.read(out)
    np.testing.assert_allclose(m.points, v, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(m.cells_dict["tetra"], cells)
    np.testing.assert_allclose(m.point_data["temperature"], temp, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m.point_data["velocity"], vel, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m.cell_data["volume"][0], vol, rtol=0, atol=1e-12)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.vtu"]


def test_write_vtu_round_trip_2d_pads_z_and_vectors(tmp_path: Path) -> None:
    v, tris = _square_tris()
    disp = np.arange(10.0).reshape(5, 2)
    stress = np.arange(8.0).reshape(4, 2)
    write_vtu(
        tmp_path / "b.vtu", v, tris, point_data={"u": disp, "flag": v[:, 0] > 0.5}, cell_data={"s": stress}
    )
    m = meshio.read(tmp_path / "b.vtu")
    np.testing.assert_allclose(m.points, np.c_[v, np.zeros(5)], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(m.cells_dict["triangle"], tris)
    np.testing.assert_array_equal(m.point_data["u"], np.c_[disp, np.zeros(5)])
    np.testing.assert_array_equal(m.point_data["flag"], [0, 1, 1, 0, 0])
    np.testing.assert_array_equal(m.cell_data["s"][0], np.c_[stress, np.zeros(4)])


def test_write_pvd_lists_relative_files_and_exact_times(tmp_path: Path) -> None:
    times = [0.0, 0.1, 1 / 3]
    pvd = write_pvd(
        tmp_path / "s.pvd", [(times[0], "f0.vtu"), (times[1], tmp_path / "f1.vtu"), (times[2], "f 2.vtu")]
    )
    sets = ET.parse(pvd).getroot().findall("./Collection/DataSet")
    assert [float(d.get("timestep")) for d in sets] == times  # exact, not rounded
    assert [d.get("file") for d in sets] == ["f0.vtu", "f1.vtu", "f 2.vtu"]


def test_vtk_series_read_back_with_pyvista(tmp_path: Path) -> None:
    pv = pytest.importorskip("pyvista")
    v, cells = _cube_tets()
    series = VTKSeries(tmp_path / "run" / "vtk", cells, name="body")
    times = [0.0, 0.25, 0.5]
    frames = [v + np.array([0.0, -0.3 * k, 0.1 * k]) for k in range(3)]
    for t, f in zip(times, frames, strict=True):
        series.write(torch.tensor(t), torch.tensor(f), point_data={"height": f[:, 1]})
    assert not series.pvd_path.exists()  # published only on commit
    assert series.commit() == tmp_path / "run" / "vtk" / "body.pvd"
    assert [t for t, _ in series.frames] == times
    assert [p.name for _, p in series.frames] == ["body_00000.vtu", "body_00001.vtu", "body_00002.vtu"]

    reader = pv.get_reader(str(series.pvd_path))
    assert list(reader.time_values) == times
    reader.set_active_time_value(times[-1])
    grid = reader.read()[0]
    np.testing.assert_allclose(grid.points, frames[-1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(grid.point_data["height"], frames[-1][:, 1], rtol=0, atol=1e-12)


def _failing_write(path, mesh, *args, **kwargs) -> None:
    Path(path).write_bytes(b"<VTKFile half written")
    raise RuntimeError("disk full")


def test_write_vtu_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    v, cells = _cube_tets()
    dest = write_vtu(tmp_path / "a.vtu", v, cells)
    before = dest.read_bytes()
    monkeypatch.setattr(meshio, "write", _failing_write)
    with pytest.raises(RuntimeError, match="disk full"):
        write_vtu(dest, v + 1.0, cells)
    assert dest.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["a.vtu"]  # no temporary file left
    with pytest.raises(RuntimeError):
        write_vtu(tmp_path / "new.vtu", v, cells)
    assert not (tmp_path / "new.vtu").exists()


def test_vtk_series_failed_frame_leaves_no_file_and_can_be_retried(tmp_path: Path, monkeypatch) -> None:
    v, cells = _cube_tets()
    series = VTKSeries(tmp_path, cells)
    series.write(0.0, v)
    series.write(0.5, v + 1.0)
    series.commit()
    pvd_before = series.pvd_path.read_bytes()
    files_before = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*"))
    with monkeypatch.context() as mp:
        mp.setattr(meshio, "write", _failing_write)
        with pytest.raises(RuntimeError):
            series.write(1.0, v + 2.0)
    assert series.pvd_path.read_bytes() == pvd_before
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == files_before
    assert len(series.frames) == 2
    # the next write retries the same index and the series goes on
    assert series.write(1.0, v + 2.0).name == "frame_00002.vtu"
    series.commit()
    sets = ET.parse(series.pvd_path).getroot().findall("./Collection/DataSet")
    folder = series.series_folder.name
    assert [(float(d.get("timestep")), d.get("file")) for d in sets] == [
        (0.0, f"{folder}/frame_00000.vtu"),
        (0.5, f"{folder}/frame_00001.vtu"),
        (1.0, f"{folder}/frame_00002.vtu"),
    ]


@pytest.mark.parametrize(
    ("vertices", "cells", "kwargs", "match"),
    [
        (np.zeros((8, 4)), None, {}, r"shape \[n, 2\] or \[n, 3\]"),
        (np.zeros((0, 3)), None, {}, "empty"),
        (np.full((8, 3), np.nan), None, {}, "NaN"),
        (None, np.array([[0, 1, 2, 8]]), {}, "outside the valid range"),
        (None, np.array([[0, 1, -1, 2]]), {}, "outside the valid range"),
        (None, np.array([[0.0, 1.0, 2.0, 3.0]]), {}, "integer"),
        (None, np.array([[0, 1, 2, 3, 4]]), {}, r"shape \[m, 3\] or \[m, 4\]"),
        (None, None, {"point_data": {"t": np.zeros(7)}}, r"point_data\['t'\] must have shape \[8\]"),
        (None, None, {"cell_data": {"c": np.zeros((5, 3))}}, r"cell_data\['c'\] must have shape \[6\]"),
        (None, None, {"point_data": {"t": np.array(["a"] * 8)}}, "numeric"),
        (np.zeros((8, 2)), None, {}, "need 3D vertices"),
    ],
)
def test_write_vtu_rejects_bad_input(tmp_path: Path, vertices, cells, kwargs, match) -> None:
    v, c = _cube_tets()
    with pytest.raises(ValueError, match=match):
        write_vtu(
            tmp_path / "x.vtu", v if vertices is None else vertices, c if cells is None else cells, **kwargs
        )
    assert list(tmp_path.iterdir()) == []


def test_series_and_pvd_reject_bad_times(tmp_path: Path) -> None:
    v, cells = _cube_tets()
    series = VTKSeries(tmp_path, cells)
    series.write(1.0, v)
    with pytest.raises(ValueError, match="increase"):
        series.write(1.0, v)
    with pytest.raises(ValueError, match="finite"):
        series.write(float("nan"), v)
    with pytest.raises(ValueError, match="out"):
        VTKSeries(tmp_path, np.array([[0, 1, 2, 9]])).write(0.0, v)
    with pytest.raises(ValueError, match="strictly increasing"):
        write_pvd(tmp_path / "x.pvd", [(0.0, "a.vtu"), (0.0, "b.vtu")])
    with pytest.raises(ValueError, match="path separators"):
        VTKSeries(tmp_path, cells, name="a/b")


def test_import_does_not_load_pyvista() -> None:
    code = "import sys, energysim.export; print('pyvista' in sys.modules, 'vtkmodules' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


# ---------------------------------------------------------------------------------------------- rendering


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


def _rgb(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def _fraction_not_background(img: np.ndarray) -> float:
    background = img[0, 0]  # corners are background with the default camera
    return float(np.mean(np.any(img != background, axis=-1)))


def test_render_png_3d(tmp_path: Path, offscreen) -> None:
    v, cells = _cube_tets()
    faces = _boundary_triangles(cells)
    assert faces.shape == (12, 3)
    out = render_png(
        tmp_path / "cube.png",
        torch.tensor(v),
        faces,
        scalars=v[:, 1],
        window_size=(320, 200),
        ground_height=0.0,
        title="cube",
    )
    img = _rgb(out)
    assert img.shape == (200, 320, 3)
    assert _fraction_not_background(img) > 0.02
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50  # shading and colour map, not flat fills
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.png"]


def test_render_png_2d_triangles_and_segments(tmp_path: Path, offscreen) -> None:
    v, tris = _square_tris()
    img = _rgb(render_png(tmp_path / "tri.png", v, tris, window_size=(200, 120)))
    assert img.shape == (120, 200, 3)
    assert _fraction_not_background(img) > 0.02
    segments = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    img = _rgb(render_png(tmp_path / "seg.png", v, segments, window_size=(200, 120), ground_height=-0.2))
    assert img.shape == (120, 200, 3)
    assert _fraction_not_background(img) > 0.02


def test_render_png_failure_keeps_previous_file(tmp_path: Path, offscreen, monkeypatch) -> None:
    from PIL import Image

    v, tris = _square_tris()
    dest = render_png(tmp_path / "p.png", v, tris, window_size=(64, 64))
    before = dest.read_bytes()

    def broken_save(self, fp, *args, **kwargs) -> None:
        Path(fp).write_bytes(b"\x89PNG half")
        raise OSError("disk full")

    monkeypatch.setattr(Image.Image, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        render_png(dest, v + 1.0, tris, window_size=(64, 64))
    assert dest.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["p.png"]


def _hide_module(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    """Make ``importlib.util.find_spec`` report ``name`` as not installed, as on a machine without it."""
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == name else real(n, *a))


def _gif_frames(path: Path) -> list[np.ndarray]:
    from PIL import Image, ImageSequence

    with Image.open(path) as im:
        return [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(im)]


def _falling_cube(n_frames: int) -> tuple[list[np.ndarray], np.ndarray]:
    v, cells = _cube_tets()
    return [v + np.array([0.0, 2.0 - 0.5 * k, 0.0]) for k in range(n_frames)], _boundary_triangles(cells)


@pytest.mark.parametrize("writer", ["imageio", "pillow"])
def test_render_gif(tmp_path: Path, offscreen, monkeypatch, writer: str) -> None:
    if writer == "imageio" and importlib.util.find_spec("imageio") is None:
        pytest.skip("imageio is not installed")
    if writer == "pillow":  # the fallback used when imageio is missing
        _hide_module(monkeypatch, "imageio")
    frames, faces = _falling_cube(5)
    heights = np.stack([f[:, 1] for f in frames])
    out = render_gif(
        tmp_path / "fall.gif",
        frames,
        faces,
        scalars=heights,
        fps=10,
        window_size=(160, 96),
        ground_height=0.0,
    )
    images = _gif_frames(out)
    assert len(images) == 5
    assert images[0].shape == (96, 160, 3)
    assert np.mean(np.any(images[0] != images[-1], axis=-1)) > 0.01
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fall.gif"]


def test_render_mp4(tmp_path: Path, offscreen, monkeypatch, caplog) -> None:
    frames, faces = _falling_cube(4)
    if importlib.util.find_spec("imageio_ffmpeg") is not None:
        out = render_mp4(tmp_path / "fall.mp4", frames, faces, window_size=(160, 96))
        assert out == tmp_path / "fall.mp4" and out.stat().st_size > 1000
        import imageio.v3 as iio

        assert iio.imread(out).shape == (4, 96, 160, 3)
    _hide_module(monkeypatch, "imageio_ffmpeg")
    with caplog.at_level(logging.INFO, logger="energysim.export.render"):
        assert render_mp4(tmp_path / "none.mp4", frames, faces) is None
    assert "imageio-ffmpeg" in caplog.text
    assert not (tmp_path / "none.mp4").exists()


def test_render_rejects_bad_input(tmp_path: Path) -> None:
    v, cells = _cube_tets()
    faces = _boundary_triangles(cells)
    with pytest.raises(ValueError, match="empty"):
        render_png(tmp_path / "x.png", v, np.zeros((0, 3), dtype=int))
    with pytest.raises(ValueError, match="empty"):
        render_png(tmp_path / "x.png", np.zeros((0, 3)), faces)
    with pytest.raises(ValueError, match="outside the valid range"):
        render_png(tmp_path / "x.png", v, faces + 1)
    with pytest.raises(ValueError, match=r"\[m, 2\] or \[m, 3\]"):
        render_png(tmp_path / "x.png", v, cells)
    with pytest.raises(ValueError, match="NaN"):
        render_png(tmp_path / "x.png", np.where(v > 0.5, np.nan, v), faces)
    with pytest.raises(ValueError, match="one value per vertex"):
        render_png(tmp_path / "x.png", v, faces, scalars=np.zeros(7))
    with pytest.raises(ValueError, match="window_size"):
        render_png(tmp_path / "x.png", v, faces, window_size=(0, 10))
    with pytest.raises(ValueError, match="nothing to render"):
        render_gif(tmp_path / "x.gif", [], faces)
    with pytest.raises(ValueError, match="all must match"):
        render_gif(tmp_path / "x.gif", [v, v[:7]], faces)
    with pytest.raises(ValueError, match="fps"):
        render_gif(tmp_path / "x.gif", [v, v], faces, fps=0)
    with pytest.raises(ValueError, match="one value per vertex"):
        render_gif(tmp_path / "x.gif", [v, v], faces, scalars=np.zeros((3, 8)))
    with pytest.raises(ValueError, match="outside the valid range"):
        render_mp4(tmp_path / "x.mp4", [v, v], faces + 1)
    assert list(tmp_path.iterdir()) == []


def test_a_new_series_replaces_the_old_one_of_the_same_name_only(tmp_path):
    from energysim.export import VTKSeries

    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    cells = np.array([[0, 1, 2, 3]])
    with VTKSeries(tmp_path, cells) as long_run:
        for k in range(3):
            long_run.write(0.1 * k, vertices)
    with VTKSeries(tmp_path, cells, name="other") as other:
        other.write(0.0, vertices)
    with VTKSeries(tmp_path, cells) as short_run:
        short_run.write(0.0, vertices)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.glob("frame*/frame_*.vtu")) == [
        f"{short_run.series_folder.name}/frame_00000.vtu"
    ]
    assert not long_run.series_folder.exists()
    assert (other.series_folder / "other_00000.vtu").exists()
    assert len(_frames(other.pvd_path)) == 1


# ---------------------------------------------------------------------------------------------- rollouts


def _muscle_scene(dim: int) -> tuple[es.Scene, torch.Tensor]:
    """A small box with elasticity and fibre muscles: actuator e mod 3 − 1 (so a third are passive)."""
    if dim == 3:
        mesh = es.TetMesh.box(size=(0.3, 0.1, 0.1), cells=(3, 1, 1))
    else:
        mesh = es.TriMesh.box(size=(0.3, 0.1), cells=(3, 1))
    scene = es.Scene(mesh, dt=0.01, gravity=None)
    scene.add(es.NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    actuators = torch.arange(mesh.num_elements) % 3 - 1
    fibres = torch.zeros(mesh.num_elements, dim, dtype=torch.float64)
    fibres[:, 0] = 1.0
    scene.add(FibreMuscles(fibres, actuators, stiffness=1e5))
    return scene, actuators


def _rigid_states(scene: es.Scene, frames: int) -> torch.Tensor:
    """`frames` states `[F, 2·num_dofs]`, each a rotation and translation of the rest shape."""
    rest = scene.rest_positions
    states = []
    for k in range(frames):
        rotation = random_rotation(scene.dim)
        x = rest @ rotation.T + 0.1 * k
        v = torch.full_like(rest, 0.5 * k) + rest
        states.append(scene.initial_state(positions=x, velocities=v))
    return torch.stack(states)


def _frames(pvd: Path) -> list[tuple[float, Path]]:
    sets = ET.parse(pvd).getroot().findall("./Collection/DataSet")
    return [(float(d.get("timestep")), pvd.parent / d.get("file")) for d in sets]


@pytest.mark.parametrize("dim", [3, 2])
def test_export_rollout_round_trips_positions_velocities_and_rigid_motions(tmp_path: Path, dim: int) -> None:
    pv = pytest.importorskip("pyvista")
    scene, actuators = _muscle_scene(dim)
    states = _rigid_states(scene, 4)
    times = [0.0, 0.1, 0.25, 0.3]
    actions = torch.tensor([[0.3, -0.7], [1.0, 0.0], [-0.2, 0.5], [0.9, -1.0]], dtype=torch.float64)
    pvd = export_rollout(scene, states, tmp_path / "run", actions=actions, times=times)

    assert pvd == tmp_path / "run" / "frame.pvd"
    listed = _frames(pvd)
    assert [t for t, _ in listed] == times  # every frame, with its exact time
    (series_folder,) = {p.parent for _, p in listed}
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == sorted(["frame.pvd", series_folder.name])
    assert sorted(p.name for p in series_folder.iterdir()) == sorted(
        [".energysim-series.json"] + [p.name for _, p in listed]
    )
    x, v = scene.split_state(states)
    n, m = scene.num_vertices, scene.mesh.num_elements
    pad = np.zeros((n, 3 - dim))
    reader = pv.get_reader(str(pvd))
    assert list(reader.time_values) == times
    for k, (time, path) in enumerate(listed):
        frame = meshio.read(path)
        np.testing.assert_allclose(frame.points, np.c_[x[k].numpy(), pad], rtol=0, atol=1e-14)
        np.testing.assert_array_equal(
            frame.cells_dict["tetra" if dim == 3 else "triangle"], scene.mesh.elements
        )
        np.testing.assert_allclose(frame.point_data["velocity"], np.c_[v[k].numpy(), pad], rtol=0, atol=1e-14)
        rest = scene.rest_positions.numpy()
        np.testing.assert_allclose(
            frame.point_data["displacement"], np.c_[x[k].numpy() - rest, pad], atol=1e-14
        )
        # a rigid motion stores no elastic energy: zero up to rounding of E (1e5 Pa) times strains ~1e-16
        assert np.abs(frame.cell_data["strain_energy_density"][0]).max() < 1e-8
        # activation is the element's actuator's action; passive elements (actuator -1) show 0
        activation = frame.cell_data["activation"][0]
        actuated = actuators.numpy() >= 0
        np.testing.assert_array_equal(frame.cell_data["actuator"][0], actuators.numpy())
        np.testing.assert_allclose(
            activation[actuated], actions[k, actuators[actuated]].numpy(), rtol=0, atol=0
        )
        assert (activation[~actuated] == 0).all()
        reader.set_active_time_value(time)
        grid = reader.read()[0]
        assert grid.n_points == n and grid.n_cells == m
        np.testing.assert_allclose(grid.points, frame.points, rtol=0, atol=0)
        assert grid.cell_data["strain_energy_density"].shape == (m,)
        assert grid.cell_data["activation"].shape == (m,)


def test_export_rollout_strain_energy_integrates_to_the_elastic_energy(tmp_path: Path) -> None:
    scene, _ = _muscle_scene(3)
    rest = scene.rest_positions
    stretched = rest * torch.tensor([1.2, 0.95, 1.0], dtype=torch.float64)  # a uniform stretch
    bent = rest + 0.02 * torch.randn_like(rest)
    states = torch.stack([scene.initial_state(positions=x) for x in (stretched, bent)])
    pvd = export_rollout(scene, states, tmp_path)
    (neo_hookean,) = [term for term in scene.terms if isinstance(term, es.NeoHookean)]
    for (_, path), x in zip(_frames(pvd), (stretched, bent), strict=True):
        density = meshio.read(path).cell_data["strain_energy_density"][0]
        volume = neo_hookean.rest_volume.numpy()
        # Σ_e ψ_e V_e is the term's energy in J
        assert float((density * volume).sum()) == pytest.approx(float(neo_hookean(x[None])[0]), rel=1e-12)
        assert (density > 0).all()
    # a uniform stretch strains every element alike
    first = meshio.read(_frames(pvd)[0][1]).cell_data["strain_energy_density"][0]
    np.testing.assert_allclose(first, first[0], rtol=1e-10)
    # without actions there is no activation, but the muscle layout is there
    assert "activation" not in meshio.read(_frames(pvd)[0][1]).cell_data
    assert "actuator" in meshio.read(_frames(pvd)[0][1]).cell_data


def test_export_rollout_of_es_rollout_shows_each_steps_action(tmp_path: Path) -> None:
    scene, actuators = _muscle_scene(3)
    steps = 5
    actions = torch.linspace(-1.0, 1.0, 2 * steps, dtype=torch.float64).reshape(steps, 2)
    states = es.rollout(scene, scene.initial_state(), actions)
    assert states.shape[0] == steps + 1
    pvd = export_rollout(scene, list(states), tmp_path, actions=actions, every=2, name="walk")
    listed = _frames(pvd)
    # every 2nd state and the last: 0, 2, 4, 5 at k·h
    assert [p.name for _, p in listed] == [f"walk_{k:05d}.vtu" for k in range(4)]
    np.testing.assert_allclose([t for t, _ in listed], [0.0, 0.02, 0.04, 0.05], rtol=0, atol=1e-15)
    actuated = actuators >= 0
    x, _ = scene.split_state(states)
    for (_, path), k in zip(listed, (0, 2, 4, 5), strict=True):
        frame = meshio.read(path)
        np.testing.assert_allclose(frame.points, x[k].numpy(), rtol=0, atol=1e-14)
        # state k was solved with the action of step k - 1; the initial state had none
        expected = torch.zeros(2, dtype=torch.float64) if k == 0 else actions[k - 1]
        np.testing.assert_allclose(frame.cell_data["activation"][0][actuated], expected[actuators[actuated]])


def test_export_rollout_spring_activation_is_the_mean_over_a_vertexs_springs(tmp_path: Path) -> None:
    mesh = es.TriMesh.box(size=(1.0, 1.0), cells=(1, 1))
    scene = es.Scene(mesh, dt=0.01, gravity=None)
    edges = torch.tensor([[0, 1], [1, 3], [0, 3]])
    scene.add(es.ActuatedSprings(edges, actuators=torch.tensor([0, 1, 1]), stiffness=10.0))
    states = scene.initial_state().expand(2, -1)
    actions = torch.tensor([[0.5, -0.25], [2.0, 0.0]], dtype=torch.float64)  # 2.0 is clamped to 1
    pvd = export_rollout(scene, states, tmp_path, actions=actions)
    frames = [meshio.read(p) for _, p in _frames(pvd)]
    # vertex 0: springs 0 (a0) and 2 (a1); vertex 1: 0 and 1; vertex 2: none; vertex 3: 1 and 2
    np.testing.assert_allclose(frames[0].point_data["spring_activation"], [0.125, 0.125, 0.0, -0.25])
    np.testing.assert_allclose(frames[1].point_data["spring_activation"], [0.5, 0.5, 0.0, 0.0])
    # no elasticity and no fibre muscles: those arrays are left out
    assert frames[0].cell_data == {}


def test_export_rollout_rejects_bad_input_and_writes_nothing(tmp_path: Path) -> None:
    scene, _ = _muscle_scene(3)
    states = _rigid_states(scene, 3)
    with pytest.raises(ValueError, match="batch entry"):
        export_rollout(scene, states[:, None].expand(3, 2, -1), tmp_path)
    with pytest.raises(ValueError, match=r"one per step\) or \[3, a\]"):
        export_rollout(scene, states, tmp_path, actions=torch.zeros(1, 2))
    with pytest.raises(ValueError, match="strictly increasing"):
        export_rollout(scene, states, tmp_path, times=[0.0, 0.2, 0.1])
    with pytest.raises(ValueError, match="one per state"):
        export_rollout(scene, states, tmp_path, times=[0.0, 0.2])
    with pytest.raises(ValueError, match="every"):
        export_rollout(scene, states, tmp_path, every=0)
    with pytest.raises(ValueError, match="NaN"):
        export_rollout(scene, torch.where(states > 0.2, float("nan"), states), tmp_path)
    with pytest.raises(ValueError, match="need 2"):
        export_rollout(scene, states, tmp_path, actions=torch.zeros(3, 1))
    with pytest.raises(ValueError, match="empty"):
        export_rollout(scene, states[:0], tmp_path)
    assert list(tmp_path.iterdir()) == []
