"""export_rollout's fields (TimeValue, stress, contact force), obstacles, surface-only frames and XDMF."""

from __future__ import annotations

import shutil
import subprocess
import textwrap
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch

import energysim as es
from energysim.contact.obstacles import Ground, SphereObstacle
from energysim.export import export_rollout
from energysim.fem.materials import lame_parameters, stable_neo_hookean_density

YOUNGS, POISSON = 2e5, 0.3


def _stretched_scene() -> tuple[es.Scene, torch.Tensor, torch.Tensor]:
    """A cube under a homogeneous deformation F0 (frame 1) after its rest state (frame 0)."""
    scene = es.Scene(es.TetMesh.box(size=(1.0, 1.0, 1.0), cells=(2, 2, 2)), gravity=None)
    scene.add(es.NeoHookean(youngs_modulus=YOUNGS, poissons_ratio=POISSON))
    F0 = torch.tensor([[1.2, 0.1, 0.0], [0.0, 0.9, 0.05], [0.0, 0.0, 1.1]], dtype=torch.float64)
    rest = scene.rest_positions
    states = torch.stack([scene.initial_state(), scene.initial_state(positions=rest @ F0.T)])
    return scene, states, F0


def _frames(pvd: Path) -> list[Path]:
    return [pvd.parent / d.get("file") for d in ET.parse(pvd).getroot().iter("DataSet")]


def test_time_value_and_cauchy_stress_of_a_homogeneous_deformation(tmp_path):
    scene, states, F0 = _stretched_scene()
    pvd = export_rollout(scene, states, tmp_path, times=[0.5, 0.75])
    frames = [meshio.read(path) for path in _frames(pvd)]
    text = _frames(pvd)[1].read_text(errors="replace")
    assert '<DataArray type="Float64" Name="TimeValue" NumberOfTuples="1" format="ascii">0.75<' in text
    rest_stress = frames[0].cell_data["cauchy_stress"][0]
    assert np.abs(rest_stress).max() < 1e-6 * YOUNGS  # the rest state is stress-free
    # independent: P = dψ/dF by autograd of the density, σ = J⁻¹ P Fᵀ
    mu, lam = lame_parameters(
        torch.tensor(YOUNGS, dtype=torch.float64), torch.tensor(POISSON, dtype=torch.float64)
    )
    F = F0.clone().requires_grad_()
    (P,) = torch.autograd.grad(stable_neo_hookean_density(F, mu, lam), F)
    sigma = (P @ F0.T / torch.linalg.det(F0)).reshape(9).numpy()
    stress = frames[1].cell_data["cauchy_stress"][0]
    assert stress.shape == (scene.mesh.num_elements, 9)
    np.testing.assert_allclose(stress, np.broadcast_to(sigma, stress.shape), rtol=1e-9, atol=1e-9 * YOUNGS)
    piola = export_rollout(scene, states, tmp_path / "p", stress="first_piola")
    first = meshio.read(_frames(piola)[1]).cell_data["first_piola_stress"][0]
    np.testing.assert_allclose(first[0], P.reshape(9).numpy(), rtol=1e-9, atol=1e-9 * YOUNGS)
    none = export_rollout(scene, states, tmp_path / "n", stress=None)
    assert "cauchy_stress" not in meshio.read(_frames(none)[0]).cell_data


def test_contact_force_is_minus_the_barrier_gradient_and_obstacles_are_drawn(tmp_path):
    scene = es.Scene(es.TetMesh.box(size=(0.2, 0.2, 0.2), cells=(1, 1, 1)), gravity=None)
    scene.add(es.NeoHookean())
    ground = scene.add(Ground(height=0.0))
    scene.add(SphereObstacle(center=(0.1, 1.0, 0.1), radius=0.2))
    lifted = scene.rest_positions + torch.tensor(
        [0.3, 0.5 * ground.barrier_distance, 0.0], dtype=torch.float64
    )
    states = torch.stack(
        [
            scene.initial_state(positions=lifted + torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64)),
            scene.initial_state(positions=lifted),
        ]
    )
    pvd = export_rollout(scene, states, tmp_path)
    force = meshio.read(_frames(pvd)[1]).point_data["contact_force"]
    x = lifted[None].clone().requires_grad_()
    (gradient,) = torch.autograd.grad(ground(x).sum(), x)
    np.testing.assert_allclose(force, -gradient[0].numpy(), rtol=1e-9, atol=1e-12)
    bottom = (lifted[:, 1] < 0.1).numpy()
    assert (force[bottom, 1] > 0).all() and np.abs(force[~bottom]).max() == 0.0
    assert np.abs(meshio.read(_frames(pvd)[0]).point_data["contact_force"]).max() == 0.0  # 0.1 m away

    statics = _frames(tmp_path / "frame_obstacles.pvd")
    assert len(statics) == 1
    drawn = meshio.read(statics[0])
    owner = drawn.cell_data["obstacle"][0]
    quad = np.unique(drawn.cells[0].data[owner == 0])
    assert np.abs(drawn.points[quad, 1]).max() == 0.0  # on the plane y = 0
    span = lifted[:, 0].min().item(), lifted[:, 0].max().item()
    assert drawn.points[quad, 0].min() < span[0] and drawn.points[quad, 0].max() > span[1]
    ball = np.unique(drawn.cells[0].data[owner == 1])
    radii = np.linalg.norm(drawn.points[ball] - [0.1, 1.0, 0.1], axis=1)
    np.testing.assert_allclose(radii, 0.2, rtol=1e-12)


def test_surface_only_keeps_the_boundary_with_restricted_fields(tmp_path):
    scene, states, _ = _stretched_scene()
    states[1, scene.num_dofs :] = 1.0 + torch.arange(scene.num_dofs, dtype=torch.float64)
    whole = meshio.read(_frames(export_rollout(scene, states, tmp_path / "w"))[1])
    surface = meshio.read(_frames(export_rollout(scene, states, tmp_path / "s", surface_only=True))[1])
    facets, owners = scene.mesh.surface_with_elements()
    kept = torch.unique(facets).numpy()
    assert surface.cells[0].type == "triangle" and len(surface.cells[0].data) == 2 * 6 * 4  # 2x2 per side
    np.testing.assert_array_equal(surface.points, whole.points[kept])
    np.testing.assert_array_equal(surface.point_data["velocity"], whole.point_data["velocity"][kept])
    np.testing.assert_array_equal(
        surface.cell_data["cauchy_stress"][0], whole.cell_data["cauchy_stress"][0][owners.numpy()]
    )
    # the triangles are the same facets, in the file's own numbering
    np.testing.assert_array_equal(kept[surface.cells[0].data], facets.numpy())


def test_xdmf_single_file_holds_every_frame(tmp_path):
    pytest.importorskip("h5py")
    vtk = pytest.importorskip("vtk")
    scene, states, F0 = _stretched_scene()
    pvd = export_rollout(scene, states, tmp_path, times=[0.0, 0.25], single_file="xdmf")
    xdmf = pvd.with_suffix(".xdmf")
    reader = vtk.vtkXdmfReader()
    reader.SetFileName(str(xdmf))
    reader.UpdateInformation()
    times = reader.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS())
    assert list(times) == [0.0, 0.25]
    reader.UpdateTimeStep(0.25)
    grid = reader.GetOutputDataObject(0)
    grid = grid.GetBlock(0) if grid.IsA("vtkMultiBlockDataSet") else grid
    from vtk.util.numpy_support import vtk_to_numpy

    points = vtk_to_numpy(grid.GetPoints().GetData())
    np.testing.assert_allclose(points, (scene.rest_positions @ F0.T).numpy(), rtol=0, atol=1e-12)
    stress = vtk_to_numpy(grid.GetCellData().GetArray("cauchy_stress"))
    np.testing.assert_array_equal(stress, meshio.read(_frames(pvd)[1]).cell_data["cauchy_stress"][0])
    # a second export replaces the pair; the older arrays go with the older frames
    export_rollout(scene, states, tmp_path, times=[0.0, 0.5], single_file="xdmf")
    assert len(list(tmp_path.glob("frame.*/frame.h5"))) == 1
    assert 'Value="0.5"' in xdmf.read_text()
    export_rollout(scene, states, tmp_path)  # no xdmf now: the stale one is removed with its arrays
    assert not xdmf.exists() and not list(tmp_path.glob("frame.*/frame.h5"))


@pytest.mark.parametrize(
    ("option", "match"),
    [
        ({"stress": "von_mises"}, "stress must be one of"),
        ({"single_file": "vtkhdf"}, "single_file must be one of"),
        ({"surface_only": 1}, "surface_only must be True or False"),
    ],
)
def test_bad_options_are_refused_before_writing(tmp_path, option, match):
    scene, states, _ = _stretched_scene()
    with pytest.raises(ValueError, match=match):
        export_rollout(scene, states, tmp_path, **option)
    assert list(tmp_path.iterdir()) == []


def test_surface_only_refuses_a_2d_mesh(tmp_path):
    scene = es.Scene(es.TriMesh.box(), gravity=None)
    with pytest.raises(ValueError, match="surface_only needs a 3D mesh"):
        export_rollout(scene, scene.initial_state()[None], tmp_path, surface_only=True)


@pytest.mark.skipif(shutil.which("pvbatch") is None, reason="ParaView's pvbatch is not on PATH")
def test_paraview_reads_the_pvd_and_the_xdmf_with_their_fields(tmp_path):
    pytest.importorskip("h5py")
    scene, states, _ = _stretched_scene()
    scene.add(Ground(height=-0.5))
    pvd = export_rollout(
        scene, torch.cat([states, states[1:]]), tmp_path, times=[0, 1, 2], single_file="xdmf"
    )
    script = tmp_path / "check.py"
    script.write_text(
        textwrap.dedent(
            f"""
            from paraview.simple import OpenDataFile, servermanager
            for path in ({str(pvd)!r}, {str(pvd.with_suffix(".xdmf"))!r}):
                reader = OpenDataFile(path)
                assert list(reader.TimestepValues) == [0.0, 1.0, 2.0], reader.TimestepValues
                for t in (0.0, 2.0):
                    # the proxy's own update: paraview.simple.UpdatePipeline ignores time=0.0 (falsy)
                    reader.UpdatePipeline(t)
                    cells = reader.CellData.keys()
                    points = reader.PointData.keys()
                    assert "cauchy_stress" in cells and "contact_force" in points, (cells, points)
                    data = servermanager.Fetch(reader)
                    assert data.GetNumberOfCells() > 0 and data.GetCellData().GetArray("cauchy_stress")
            print("ok")
            """
        )
    )
    result = subprocess.run(["pvbatch", str(script)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "ok" in result.stdout, result.stderr[-2000:]
