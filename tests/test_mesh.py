"""Tests for energysim.mesh: generators, geometry queries, validation and file round trips."""

import logging

import meshio
import numpy as np
import pytest
import torch

from energysim.mesh import SimplexMesh, TetMesh, TriMesh, load_mesh, signed_volumes


def triangle_areas_normals(mesh: TetMesh, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    x = mesh.vertices[faces]
    cross = torch.linalg.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    return cross.norm(dim=1) / 2, cross


def edge_use_counts(faces: torch.Tensor) -> torch.Tensor:
    edges = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2).sort(dim=1).values
    return torch.unique(edges, dim=0, return_counts=True)[1]


def l_shape_3d() -> np.ndarray:
    occupancy = np.zeros((2, 2, 1), dtype=bool)
    occupancy[0, 0, 0] = occupancy[1, 0, 0] = occupancy[0, 1, 0] = True
    return occupancy


# --- generators and geometry ---------------------------------------------------------------------


def test_box_volume_3d():
    size = (2.0, 0.5, 1.5)
    mesh = TetMesh.box(size=size, cells=(3, 2, 4), origin=(-1.0, 0.25, 3.0))
    assert mesh.dim == 3
    assert mesh.vertices.dtype == torch.float64 and mesh.tets.dtype == torch.int64
    assert mesh.tets is mesh.elements
    volume = mesh.element_rest_volume()
    assert bool((volume > 0).all())
    assert float(volume.sum()) == pytest.approx(2.0 * 0.5 * 1.5, rel=1e-12)
    assert float(mesh.vertex_rest_volume().sum()) == pytest.approx(1.5, rel=1e-12)
    lo, hi = mesh.bounding_box()
    assert lo.tolist() == pytest.approx([-1.0, 0.25, 3.0])
    assert hi.tolist() == pytest.approx([1.0, 0.75, 4.5])


def test_box_volume_2d():
    mesh = TriMesh.box(size=(3.0, 0.5), cells=(4, 3), origin=(1.0, -2.0))
    assert mesh.dim == 2 and mesh.vertices.shape == (20, 2) and mesh.triangles.shape == (24, 3)
    area = mesh.element_rest_volume()
    assert bool((area > 0).all())
    assert float(area.sum()) == pytest.approx(1.5, rel=1e-12)
    assert float(mesh.vertex_rest_volume().sum()) == pytest.approx(1.5, rel=1e-12)


def test_box_counts():
    mesh = TetMesh.box(cells=(2, 3, 4))
    assert mesh.num_vertices == 3 * 4 * 5
    assert mesh.num_elements == 6 * 24
    assert mesh.tets.shape == (144, 4)


def test_box_is_conforming():
    mesh = TetMesh.box(size=(1.0, 2.0, 3.0), cells=(3, 3, 3))
    faces = mesh.tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3).sort(dim=1).values
    counts = torch.unique(faces, dim=0, return_counts=True)[1]
    assert int(counts.max()) == 2
    # Boundary faces are exactly the 2 triangles per boundary square.
    assert int((counts == 1).sum()) == 2 * 2 * (9 + 9 + 9)


def test_edges_of_single_cube():
    mesh = TetMesh.box()
    edges = mesh.edges()
    # 12 cube edges + 6 face diagonals + 1 body diagonal.
    assert edges.shape == (19, 2)
    assert bool((edges[:, 0] < edges[:, 1]).all())
    keys = edges[:, 0] * mesh.num_vertices + edges[:, 1]
    assert bool((keys[1:] > keys[:-1]).all())
    assert TriMesh.box().edges().tolist() == [[0, 1], [0, 2], [0, 3], [1, 3], [2, 3]]


def test_box_surface_closed_area_and_outward():
    size = torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64)
    mesh = TetMesh.box(size=tuple(size.tolist()), cells=(3, 2, 2), origin=(1.0, 1.0, 1.0))
    surface = mesh.surface()
    assert surface.shape == (2 * 2 * (3 * 2 + 2 * 2 + 3 * 2), 3)
    assert bool((edge_use_counts(surface) == 2).all())
    area, normal = triangle_areas_normals(mesh, surface)
    a, b, c = size.tolist()
    assert float(area.sum()) == pytest.approx(2 * (a * b + b * c + a * c), rel=1e-12)
    centre = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64) + size / 2
    outward = ((mesh.vertices[surface].mean(dim=1) - centre) * normal).sum(dim=1)
    assert bool((outward > 0).all())
    expected = torch.unique(surface.flatten())
    assert torch.equal(mesh.surface_vertices(), expected)
    # The 4 x 3 x 3 lattice of cells (3, 2, 2) has 2 x 1 x 1 interior points, all others are on the surface.
    assert mesh.surface_vertices().numel() == mesh.num_vertices - 2 * 1 * 1


def test_box_boundary_2d():
    mesh = TriMesh.box(size=(3.0, 2.0), cells=(3, 4))
    segments = mesh.surface()
    x = mesh.vertices[segments]
    direction = x[:, 1] - x[:, 0]
    assert float(direction.norm(dim=1).sum()) == pytest.approx(10.0, rel=1e-12)
    signed_area = 0.5 * (x[:, 0, 0] * x[:, 1, 1] - x[:, 1, 0] * x[:, 0, 1]).sum()
    assert float(signed_area) == pytest.approx(6.0, rel=1e-12)
    outward_normal = torch.stack([direction[:, 1], -direction[:, 0]], dim=1)
    centre = torch.tensor([1.5, 1.0], dtype=torch.float64)
    assert bool((((x.mean(dim=1) - centre) * outward_normal).sum(dim=1) > 0).all())
    # Every boundary vertex starts exactly one segment and ends exactly one: a closed loop.
    starts = torch.bincount(segments[:, 0], minlength=mesh.num_vertices)
    ends = torch.bincount(segments[:, 1], minlength=mesh.num_vertices)
    assert torch.equal(starts, ends) and int(starts.max()) == 1


def test_from_voxels_l_shape():
    h = 0.5
    mesh = TetMesh.from_voxels(l_shape_3d(), voxel_size=h, origin=(1.0, 2.0, 3.0))
    assert mesh.num_elements == 18
    assert float(mesh.element_rest_volume().sum()) == pytest.approx(3 * h**3, rel=1e-12)
    # Footprint of an L of 3 squares has 8 corners, on 2 layers.
    assert mesh.num_vertices == 16
    assert torch.unique(mesh.vertices, dim=0).shape[0] == mesh.num_vertices
    surface = mesh.surface()
    assert bool((edge_use_counts(surface) == 2).all())
    area, _ = triangle_areas_normals(mesh, surface)
    assert float(area.sum()) == pytest.approx(14 * h**2, rel=1e-12)
    lo, hi = mesh.bounding_box()
    assert lo.tolist() == pytest.approx([1.0, 2.0, 3.0]) and hi.tolist() == pytest.approx([2.0, 3.0, 3.5])


def test_from_voxels_neighbours_share_faces():
    occupancy = np.zeros((3, 2, 2), dtype=bool)
    occupancy[1, 1, 0] = occupancy[2, 1, 0] = True
    mesh = TetMesh.from_voxels(occupancy, voxel_size=2.0)
    assert mesh.num_vertices == 12  # unused lattice points dropped
    area, _ = triangle_areas_normals(mesh, mesh.surface())
    assert mesh.surface().shape[0] == 20
    assert float(area.sum()) == pytest.approx(10 * 4.0, rel=1e-12)


def test_from_voxels_2d_and_errors():
    occupancy = np.array([[1, 1], [1, 0]], dtype=bool)
    mesh = TriMesh.from_voxels(occupancy, voxel_size=(2.0, 1.0))
    assert mesh.num_vertices == 8 and mesh.num_elements == 6
    assert float(mesh.element_rest_volume().sum()) == pytest.approx(6.0)
    x = mesh.vertices[mesh.surface()]
    assert float((x[:, 1] - x[:, 0]).norm(dim=1).sum()) == pytest.approx(12.0)
    with pytest.raises(ValueError, match="no occupied"):
        TetMesh.from_voxels(np.zeros((2, 2, 2), dtype=bool))
    with pytest.raises(ValueError, match="3 dimensions"):
        TetMesh.from_voxels(occupancy)


def test_signed_volume_is_differentiable():
    vertices = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    vertices.requires_grad_(True)
    volume = signed_volumes(vertices, torch.tensor([[0, 1, 2, 3]]))
    assert float(volume.detach()) == pytest.approx(1 / 6)
    volume.sum().backward()
    assert vertices.grad[3].tolist() == pytest.approx([0.0, 0.0, 1 / 6])


# --- validation ----------------------------------------------------------------------------------


def test_reorientation(caplog):
    box = TetMesh.box(cells=(2, 2, 1))
    flipped = box.tets.clone()
    flip = torch.tensor([1, 4, 5, 11])
    flipped[flip] = flipped[flip][:, [1, 0, 2, 3]]
    assert int((signed_volumes(box.vertices, flipped) < 0).sum()) == 4
    with caplog.at_level(logging.INFO, logger="energysim.mesh.simplex"):
        mesh = TetMesh(box.vertices.numpy(), flipped.tolist())
    assert "4" in caplog.text
    volume = mesh.element_rest_volume()
    assert bool((volume > 0).all())
    assert torch.allclose(volume, box.element_rest_volume(), rtol=0, atol=1e-15)
    assert torch.equal(mesh.tets.sort(dim=1).values, box.tets.sort(dim=1).values)


def test_trimesh_reorients_and_drops_constant_z():
    mesh = TriMesh([[0, 0, 5.0], [1, 0, 5.0], [0, 1, 5.0]], [[0, 2, 1]])
    assert mesh.vertices.shape == (3, 2)
    assert mesh.triangles.tolist() == [[0, 1, 2]]
    assert float(mesh.element_rest_volume()) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="non-constant z"):
        TriMesh([[0, 0, 0.0], [1, 0, 0.0], [0, 1, 1.0]], [[0, 1, 2]])


UNIT_TET = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def two_tets() -> tuple[list[list[float]], list[list[int]]]:
    return [*UNIT_TET, [1.0, 1.0, 1.0]], [[0, 1, 2, 3], [1, 2, 3, 4]]


def test_nan_vertex_named():
    vertices, tets = two_tets()
    vertices[4][1] = float("nan")
    with pytest.raises(ValueError, match=r"vertices \[4\]"):
        TetMesh(vertices, tets)
    vertices[4][1] = float("inf")
    with pytest.raises(ValueError, match=r"\[4\]"):
        TetMesh(vertices, tets)


def test_out_of_range_named():
    vertices, tets = two_tets()
    tets[1][3] = 5
    with pytest.raises(ValueError, match=r"elements \[1\]"):
        TetMesh(vertices, tets)
    tets[1][3] = -1
    with pytest.raises(ValueError, match=r"elements \[1\]"):
        TetMesh(vertices, tets)


def test_degenerate_named():
    vertices, tets = two_tets()
    with pytest.raises(ValueError, match=r"degenerate.*elements \[1\]"):
        TetMesh(vertices, [tets[0], [1, 2, 2, 4]])
    flat = [*UNIT_TET, [0.5, 0.5, 0.0]]
    with pytest.raises(ValueError, match=r"degenerate.*elements \[1\]"):
        TetMesh(flat, [[0, 1, 2, 3], [0, 1, 2, 4]])
    # A tiny but well-shaped tet is fine: the threshold is relative to its own size.
    TetMesh(np.array(UNIT_TET) * 1e-5, [[0, 1, 2, 3]])
    with pytest.raises(ValueError, match=r"degenerate.*elements \[0\]"):
        TriMesh([[0, 0], [1, 1], [2, 2]], [[0, 1, 2]])


def test_many_bad_indices_truncated():
    box = TetMesh.box(cells=(3, 1, 1))
    tets = box.tets.clone()
    tets[:, 3] = tets[:, 2]
    with pytest.raises(ValueError, match=r"\[0, 1, 2, 3, 4, 5, 6, 7, 8, 9\] and 8 more"):
        TetMesh(box.vertices, tets)


def test_no_elements():
    with pytest.raises(ValueError, match="no elements"):
        TetMesh(UNIT_TET, np.zeros((0, 4), dtype=np.int64))
    with pytest.raises(ValueError, match="no elements"):
        TriMesh([[0, 0], [1, 0], [0, 1]], [])


def test_wrong_shapes():
    with pytest.raises(ValueError, match=r"\[n, 3\], got \(4, 2\)"):
        TetMesh(np.zeros((4, 2)), [[0, 1, 2, 3]])
    with pytest.raises(ValueError, match=r"\[m, 4\], got \(1, 3\)"):
        TetMesh(UNIT_TET, [[0, 1, 2]])
    with pytest.raises(ValueError, match=r"\[m, 3\], got \(3,\)"):
        TriMesh([[0, 0], [1, 0], [0, 1]], [0, 1, 2])
    with pytest.raises(ValueError, match=r"\[n, 2\], got \(3, 4\)"):
        TriMesh(np.zeros((3, 4)), [[0, 1, 2]])
    with pytest.raises(ValueError, match="integer"):
        TetMesh(UNIT_TET, [[0.0, 1.0, 2.0, 3.0]])


def test_unused_vertex_named():
    with pytest.raises(ValueError, match=r"vertices \[2\] are used by no element"):
        TriMesh([[0, 0], [1, 0], [5, 5], [0, 1]], [[0, 1, 3]])


def test_generic_base_infers_dim():
    mesh = SimplexMesh([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]])
    assert mesh.dim == 2 and float(mesh.element_rest_volume()) == pytest.approx(0.5)


# --- files ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".msh", ".mesh"])
def test_round_trip_tet(tmp_path, suffix):
    mesh = TetMesh.box(size=(0.3, 0.7, 1.1), cells=(2, 3, 2), origin=(0.1, -0.2, 1 / 3))
    path = tmp_path / f"box{suffix}"
    mesh.save(path)
    loaded = TetMesh.load(path)
    assert torch.equal(loaded.vertices, mesh.vertices)
    assert torch.equal(loaded.tets, mesh.tets)
    again = load_mesh(path)
    assert isinstance(again, TetMesh) and torch.equal(again.tets, mesh.tets)
    assert not [p for p in tmp_path.iterdir() if p.name != path.name]


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".msh", ".mesh"])
def test_round_trip_tri(tmp_path, suffix):
    mesh = TriMesh.box(size=(0.3, 0.7), cells=(3, 2), origin=(0.1, 1 / 3))
    path = tmp_path / f"rect{suffix}"
    mesh.save(path)
    loaded = load_mesh(path)
    assert isinstance(loaded, TriMesh)
    assert torch.equal(loaded.vertices, mesh.vertices)
    assert torch.equal(loaded.triangles, mesh.triangles)


def test_save_with_data(tmp_path):
    mesh = TetMesh.box(cells=(1, 1, 2))
    path = tmp_path / "data.vtu"
    mesh.save(path, point_data={"u": mesh.vertices * 2}, cell_data={"vol": mesh.element_rest_volume()})
    raw = meshio.read(path)
    np.testing.assert_array_equal(raw.point_data["u"], mesh.vertices.numpy() * 2)
    np.testing.assert_array_equal(raw.cell_data["vol"][0], mesh.element_rest_volume().numpy())
    with pytest.raises(ValueError, match="point_data 'u'"):
        mesh.save(path, point_data={"u": np.zeros(3)})


def test_load_missing_file(tmp_path):
    path = tmp_path / "nope.vtu"
    with pytest.raises(FileNotFoundError, match="nope.vtu"):
        TetMesh.load(path)
    with pytest.raises(FileNotFoundError, match="nope.vtu"):
        load_mesh(path)


def test_load_triangles_as_tet_fails(tmp_path):
    path = tmp_path / "tris.vtu"
    TriMesh.box(cells=(2, 2)).save(path)
    with pytest.raises(ValueError, match="tris.vtu.*tetra"):
        TetMesh.load(path)


def test_load_concatenates_blocks_and_prunes(tmp_path):
    box = TetMesh.box(cells=(2, 1, 1))
    # Two extra points no tet uses, a triangle block to ignore, and the tets split over two blocks.
    points = np.concatenate([[[9.0, 9.0, 9.0]], box.vertices.numpy(), [[-9.0, 0.0, 0.0]]])
    tets = box.tets.numpy() + 1
    cells = [("tetra", tets[:5]), ("triangle", np.array([[0, 1, 2]])), ("tetra", tets[5:])]
    path = tmp_path / "blocks.vtu"
    meshio.write(path, meshio.Mesh(points, cells))
    mesh = TetMesh.load(path)
    assert torch.equal(mesh.vertices, box.vertices)
    assert torch.equal(mesh.tets, box.tets)
    assert isinstance(load_mesh(path), TetMesh)
    with pytest.raises(ValueError, match=r"vertices \[0, 13\] are used by no element"):
        TetMesh.load(path, prune=False)


def test_save_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "mesh.vtu"
    TetMesh.box().save(path)
    before = path.read_bytes()

    def failing_write(filename, mesh, *args, **kwargs):
        with open(filename, "wb") as f:
            f.write(b"<VTKFile half-written")
        raise RuntimeError("disk full")

    monkeypatch.setattr(meshio, "write", failing_write)
    with pytest.raises(RuntimeError, match="disk full"):
        TetMesh.box(cells=(2, 2, 2)).save(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["mesh.vtu"]
    monkeypatch.undo()
    assert TetMesh.load(path).num_elements == 6
