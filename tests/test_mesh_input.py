"""Bad mesh and creature input fails with one clear error: corrupt, empty or missing files name their path,
repeated and overlapping elements are refused with their indices, and the flatness test does not depend
on the mesh's unit scale."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch

from energysim.contact import contact_areas
from energysim.creatures import CREATURES, load_creature
from energysim.mesh import MeshFileError, MeshFileNotFoundError, TetMesh, TriMesh, load_mesh

SHIPPED = Path(__file__).resolve().parents[1] / "energysim" / "assets" / "creatures"
UNIT_TET = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def loaders(path: Path) -> list:
    return [lambda: TetMesh.load(path), lambda: load_mesh(path)]


def assert_file_error(path: Path, pattern: str = "") -> MeshFileError:
    """Every loader raises MeshFileError naming `path` (and matching `pattern`); return the last one."""
    error = None
    for load in loaders(path):
        with pytest.raises(MeshFileError, match=pattern) as caught:
            load()
        error = caught.value
        assert str(path) in str(error) and error.path == path
    return error


# --- unreadable files ---------------------------------------------------------------------------


@pytest.fixture
def good_vtu(tmp_path) -> Path:
    path = tmp_path / "good.vtu"
    TetMesh.box(cells=(2, 1, 1)).save(path)
    assert TetMesh.load(path).num_elements == 12
    return path


def corrupt_payload(text: str, replacement: str) -> str:
    # The points array is the first binary payload: "<header>==<zlib data>" in base64.
    start = text.index('format="binary">') + len('format="binary">\n')
    end = text.index("\n", start)
    header, data = text[start:end].split("==", 1)
    return text[:start] + header + "==" + replacement(data) + text[end:]


@pytest.mark.parametrize(
    "damage, pattern",
    [
        (lambda b: b[: len(b) // 2], "truncated or corrupt.*ParseError"),
        (lambda b: b"", "is empty"),
        (lambda b: bytes(len(b)), "truncated or corrupt"),
        (lambda b: np.random.default_rng(0).bytes(len(b)), "truncated or corrupt"),
        # a base64 payload cut to an impossible length, and valid base64 of a broken zlib stream
        (lambda b: corrupt_payload(b.decode(), lambda d: d[:-3]).encode(), "binascii.Error"),
        (
            lambda b: corrupt_payload(b.decode(), lambda d: d[:8] + "A" * (len(d) - 9) + "=").encode(),
            "zlib.error",
        ),
    ],
    ids=["truncated", "empty", "zeros", "random", "bad-base64", "bad-zlib"],
)
def test_corrupt_vtu_raises_mesh_file_error_naming_the_path(good_vtu, damage, pattern):
    bad = good_vtu.with_name("bad.vtu")
    bad.write_bytes(damage(good_vtu.read_bytes()))
    error = assert_file_error(bad, pattern)
    assert isinstance(error, ValueError)
    if "empty" not in pattern:
        assert error.__cause__ is not None  # the parser's own error stays reachable


@pytest.mark.parametrize("suffix", [".msh", ".vtk", ".mesh"])
def test_truncated_text_formats_raise_mesh_file_error(tmp_path, suffix):
    good = tmp_path / f"good{suffix}"
    TetMesh.box(cells=(2, 2, 2)).save(good)
    text = good.read_bytes()
    bad = tmp_path / f"bad{suffix}"
    # cut inside the element block, where numpy's reshape used to fail without the path
    bad.write_bytes(text[: int(len(text) * 0.8)])
    assert_file_error(bad, "truncated or corrupt")


def test_missing_directory_and_unknown_extension(tmp_path):
    missing = tmp_path / "nowhere.vtu"
    for load in loaders(missing):
        with pytest.raises(MeshFileNotFoundError, match="nowhere.vtu") as caught:
            load()
        assert isinstance(caught.value, FileNotFoundError) and isinstance(caught.value, MeshFileError)
    folder = tmp_path / "folder.vtu"
    folder.mkdir()
    assert_file_error(folder, "not a regular file")
    unknown = tmp_path / "mesh.foo"
    unknown.write_text("anything")
    assert_file_error(unknown, r"unknown mesh file extension '\.foo'")


def test_files_without_valid_simplices(tmp_path):
    path = tmp_path / "lines.vtu"
    meshio.write(path, meshio.Mesh(np.eye(3), [("line", np.array([[0, 1], [1, 2]]))]))
    assert_file_error(path, r"(no 'tetra' cells|neither tetra nor triangle).*line")

    points = np.array(UNIT_TET + [[1.0, 1.0, 1.0]])
    nan_points = points.copy()
    nan_points[3, 2] = np.nan
    path = tmp_path / "nan.vtu"
    meshio.write(path, meshio.Mesh(nan_points, [("tetra", np.array([[0, 1, 2, 3]]))]))
    assert_file_error(path, r"points \[3\] have NaN")

    path = tmp_path / "range.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", np.array([[0, 1, 2, 3], [1, 2, 3, 9]]))]))
    assert_file_error(path, r"cells \[1\] reference point indices outside \[0, 5\)")

    path = tmp_path / "twice.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", np.array([[0, 1, 2, 3], [1, 2, 3, 4], [3, 2, 1, 0]]))]))
    assert_file_error(path, r"elements \[0, 2\] repeat another element's vertices")


def test_keyboard_interrupt_is_not_swallowed(good_vtu, monkeypatch):
    def interrupted(filename):
        raise KeyboardInterrupt

    monkeypatch.setitem(meshio._helpers.reader_map, "vtu", interrupted)
    with pytest.raises(KeyboardInterrupt):
        TetMesh.load(good_vtu)


def test_mesh_file_error_pickles():
    error = pickle.loads(pickle.dumps(MeshFileNotFoundError(Path("a/b.vtu"), "no such mesh file")))
    assert isinstance(error, FileNotFoundError) and str(error) == "a/b.vtu: no such mesh file"


# --- repeated and overlapping elements --------------------------------------------------------------


@pytest.mark.parametrize("copy", [[0, 1, 2, 3], [1, 0, 2, 3], [2, 3, 0, 1]], ids=["same", "odd", "even"])
def test_element_listed_twice_is_refused(copy):
    box = TetMesh.box(cells=(2, 1, 1))
    extra = box.tets[5][copy]
    with pytest.raises(ValueError, match=r"elements \[5, 12\] repeat another element's vertices"):
        TetMesh(box.vertices, torch.cat([box.tets, extra[None]]))
    rect = TriMesh.box(cells=(2, 1))
    with pytest.raises(ValueError, match=r"elements \[1, 4\] repeat"):
        TriMesh(rect.vertices, torch.cat([rect.triangles, rect.triangles[1:2, [2, 1, 0]]]))


def test_elements_on_the_same_side_of_a_face_are_refused():
    below = [0.2, 0.2, -1.0]
    above = [0.2, 0.2, 0.5]  # inside the half-space of the unit tet's apex: the two tets overlap
    valid = TetMesh([*UNIT_TET, below], [[0, 1, 2, 3], [0, 2, 1, 4]])
    assert valid.surface().shape == (6, 3)
    assert float(valid.element_rest_volume().sum()) == pytest.approx(1 / 6 + 1 / 6, rel=1e-12)
    with pytest.raises(ValueError, match=r"elements \[0, 1\] overlap: they lie on the same side"):
        TetMesh([*UNIT_TET, above], [[0, 1, 2, 3], [0, 1, 2, 4]])
    with pytest.raises(ValueError, match=r"elements \[0, 1, 2\] overlap: facets shared by more than two"):
        TetMesh([*UNIT_TET, below, above], [[0, 1, 2, 3], [0, 1, 2, 4], [0, 1, 2, 5]])
    # 2D: two triangles above the same edge
    with pytest.raises(ValueError, match=r"elements \[0, 1\] overlap"):
        TriMesh([[0, 0], [1, 0], [0, 1], [1, 1]], [[0, 1, 2], [0, 1, 3]])
    TriMesh([[0, 0], [1, 0], [0, 1], [1, -1]], [[0, 1, 2], [0, 1, 3]])


# --- scale-invariant flatness ---------------------------------------------------------------------


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_flatness_is_judged_relative_to_element_size(scale):
    box = TetMesh.box(size=(1.0, 2.0, 3.0), cells=(2, 2, 2))
    mesh = TetMesh(box.vertices * scale + 10 * scale, box.tets)
    assert float(mesh.element_rest_volume().sum()) == pytest.approx(6.0 * scale**3, rel=1e-12)
    assert torch.equal(mesh.surface(), box.surface())
    # a thin but honest sliver (height 1e-6 of its width) is a valid element at every scale
    sliver = np.array([*UNIT_TET[:3], [0.3, 0.3, 1e-6]]) * scale
    assert float(TetMesh(sliver, [[0, 1, 2, 3]]).element_rest_volume()) == pytest.approx(
        1e-6 / 6 * scale**3, rel=1e-9
    )
    # a flat element (fourth vertex in the plane of the first three) is refused with its index
    flat = np.array([*UNIT_TET, [0.3, 0.3, 0.0]]) * scale
    with pytest.raises(ValueError, match=r"1 degenerate .* elements \[1\]"):
        TetMesh(flat, [[0, 1, 2, 3], [0, 1, 2, 4]])
    with pytest.raises(ValueError, match=r"degenerate .* elements \[0\]"):
        TriMesh(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]) * scale, [[0, 1, 2]])


def test_volumes_outside_float64_are_named_as_such():
    with pytest.raises(
        ValueError, match=r"elements \[0\] are well shaped but their volumes overflow or underflow"
    ):
        TetMesh(np.array(UNIT_TET) * 1e-150, [[0, 1, 2, 3]])


def test_trimesh_planarity_is_relative():
    rect = TriMesh.box(cells=(1, 1))
    lifted = torch.cat([rect.vertices * 1e-9, torch.tensor([[0.0], [0.0], [0.0], [1e-12]])], dim=1)
    with pytest.raises(ValueError, match="non-constant z"):
        TriMesh(lifted, rect.triangles)


def test_every_boundary_and_interior_vertex_has_a_positive_contact_area():
    mesh = TetMesh.box(size=(1.0, 2.0, 3.0), cells=(3, 3, 3))  # 4 interior vertices
    area = contact_areas(mesh)
    assert bool(torch.isfinite(area).all()) and bool((area > 0).all())
    surface = mesh.surface_vertices()
    assert float(area[surface].sum()) == pytest.approx(2 * (1 * 2 + 2 * 3 + 3 * 1), rel=1e-12)


# --- creature files -----------------------------------------------------------------------------


@pytest.fixture
def worm_dir(tmp_path) -> Path:
    for suffix in (".vtu", ".json"):
        shutil.copy(SHIPPED / f"worm{suffix}", tmp_path / f"worm{suffix}")
    return tmp_path


def edit_json(folder: Path, change) -> Path:
    path = folder / "worm.json"
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    "change, pattern",
    [
        (lambda d: d.pop("density"), r"missing key 'density'"),
        (lambda d: d.update(dim="three"), r"key 'dim' must be 2 or 3, got 'three'"),
        (lambda d: d.update(youngs_modulus="soft"), r"key 'youngs_modulus' must be a number > 0"),
        (lambda d: d.update(poissons_ratio=0.5), r"key 'poissons_ratio' must be a number in \(-1, 0.5\)"),
        (lambda d: d.update(gait_amplitude=True), r"key 'gait_amplitude' must be a number"),
        (lambda d: d.update(gait_phases=[0.0]), r"key 'gait_phases' must be a list of 10"),
        (lambda d: d["actuator_names"].__setitem__(3, 7), r"key 'actuator_names'.*entries \[3\]"),
        (
            lambda d: d.update(
                num_actuators=11, gait_phases=[0.0] * 11, actuator_names=[str(i) for i in range(11)]
            ),
            r"actuators \[10\] .* drive no element of worm\.vtu",
        ),
    ],
    ids=["missing", "dim", "modulus", "poisson", "bool", "phases", "names", "empty-actuator"],
)
def test_bad_creature_json_names_the_file_and_key(worm_dir, change, pattern):
    path = edit_json(worm_dir, change)
    with pytest.raises(MeshFileError, match=pattern) as caught:
        load_creature("worm", worm_dir)
    assert caught.value.path == path and str(path) in str(caught.value)


def test_broken_creature_files(worm_dir):
    sidecar = worm_dir / "worm.json"
    text = sidecar.read_text()
    for broken, pattern in ((text[: len(text) // 2], "not valid JSON .* line"), ("[1, 2]", "JSON object")):
        sidecar.write_text(broken)
        with pytest.raises(MeshFileError, match=rf"worm\.json: .*{pattern}"):
            load_creature("worm", worm_dir)
    sidecar.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(MeshFileError, match=r"worm\.json: cannot be read as UTF-8"):
        load_creature("worm", worm_dir)
    sidecar.write_text(text)

    mesh_path = worm_dir / "worm.vtu"
    raw = meshio.read(mesh_path)
    actuators = raw.cell_data["actuator"][0].copy()
    actuators[[4, 9]] = 12
    meshio.write(
        mesh_path, meshio.Mesh(raw.points, raw.cells, cell_data={**raw.cell_data, "actuator": [actuators]})
    )
    with pytest.raises(MeshFileError, match=r"worm\.vtu: elements \[4, 9\] have actuators \[12, 12\]"):
        load_creature("worm", worm_dir)
    mesh_path.write_bytes(mesh_path.read_bytes()[:1000])
    with pytest.raises(MeshFileError, match=r"worm\.vtu: is not a readable vtu file"):
        load_creature("worm", worm_dir)


def test_unknown_creature_lists_the_shipped_names():
    with pytest.raises(ValueError, match="unknown creature 'dragon'") as caught:
        load_creature("dragon")
    assert all(name in str(caught.value) for name in CREATURES)
