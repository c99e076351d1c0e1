"""Mesh files' named sets and cell data survive loading, renumbered, and pin the vertices they name."""

from __future__ import annotations

import meshio
import numpy as np
import pytest
import torch

import energysim as es
from energysim.mesh import MeshFileError, TetMesh, TriMesh, load_mesh

# Two tets sharing the face (1, 2, 3) plus a geometry point (5) that no tet uses; point 0 is first in the
# file, so pruning point 5 leaves the numbering of 0..4 alone, while a leading unused point shifts it.
POINTS = np.array([[9, 9, 9], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
TETS = np.array([[1, 2, 3, 4], [2, 3, 4, 5]])


def _write_gmsh(path):
    # triangle (1, 2, 3) is the physical surface "clamp" (tag 1); both tets the volume "body" (tag 2)
    dim_tags = np.array([[0, 1], [2, 1], [2, 1], [2, 1], [3, 1], [3, 1]])
    mesh = meshio.Mesh(
        POINTS,
        [("triangle", np.array([[1, 2, 3]])), ("tetra", TETS)],
        point_data={"gmsh:dim_tags": dim_tags},
        cell_data={
            "gmsh:physical": [np.array([1]), np.array([2, 2])],
            "gmsh:geometrical": [np.array([1]), np.array([1, 1])],
        },
        field_data={"clamp": np.array([1, 2]), "body": np.array([2, 3])},
    )
    meshio.write(path, mesh, file_format="gmsh", binary=False)  # MSH 4.1 ASCII


def test_gmsh_physical_groups_become_vertex_sets_renumbered_after_pruning(tmp_path):
    path = tmp_path / "part.msh"
    _write_gmsh(path)
    assert path.read_text().startswith("$MeshFormat\n4.1 0")
    mesh = TetMesh.load(path)
    assert mesh.num_vertices == 5  # file point 0 pruned: file point k is vertex k - 1
    assert mesh.vertex_sets["clamp"].tolist() == [0, 1, 2]
    assert mesh.vertex_sets["body"].tolist() == [0, 1, 2, 3, 4]
    assert mesh.element_sets["body"].tolist() == [0, 1]
    assert mesh.element_sets["clamp"].tolist() == []  # a surface group holds no tet
    assert mesh.cell_data["gmsh:physical"].tolist() == [2, 2]
    # the positions of the set's vertices are those of the file's points
    assert torch.equal(mesh.vertices[mesh.vertex_sets["clamp"]], torch.from_numpy(POINTS[[1, 2, 3]]))
    assert "gmsh:bounding_entities" not in mesh.vertex_sets
    same = load_mesh(path)
    assert same.vertex_sets["clamp"].tolist() == [0, 1, 2]


def test_abaqus_node_and_element_sets(tmp_path):
    path = tmp_path / "part.inp"
    mesh_in = meshio.Mesh(
        POINTS,
        [("tetra", TETS)],
        point_sets={"clamp": np.array([0, 1, 2])},  # point 0 is pruned: the set keeps 1, 2
        cell_sets={"tip": [np.array([1])]},
    )
    meshio.write(path, mesh_in)
    assert "*NSET, NSET=clamp" in path.read_text()
    mesh = TetMesh.load(path)
    assert mesh.vertex_sets["clamp"].tolist() == [0, 1]
    assert mesh.vertex_sets["tip"].tolist() == [1, 2, 3, 4]  # the vertices of tet 1
    assert mesh.element_sets["tip"].tolist() == [1]


def test_cell_data_follow_elements_across_blocks(tmp_path):
    path = tmp_path / "two_blocks.vtu"
    mesh_in = meshio.Mesh(
        POINTS[1:],
        [("tetra", TETS[:1] - 1), ("tetra", TETS[1:] - 1)],
        cell_data={
            "material": [np.array([7]), np.array([3])],
            "E": [np.array([[1.0, 2.0]]), np.array([[3.0, 4.0]])],
        },
    )
    meshio.write(path, mesh_in)
    mesh = TetMesh.load(path)
    assert mesh.cell_data["material"].tolist() == [7, 3]
    assert mesh.cell_data["E"].tolist() == [[1.0, 2.0], [3.0, 4.0]]


def test_fix_by_set_pins_exactly_those_vertices(tmp_path):
    path = tmp_path / "part.msh"
    _write_gmsh(path)
    mesh = TetMesh.load(path)
    scene = es.Scene(mesh)
    scene.fix(mesh.vertex_sets["clamp"])
    assert torch.nonzero(scene.fixed).reshape(-1).tolist() == [0, 1, 2]
    other = es.Scene(mesh)
    other.fix_set("clamp")
    assert torch.equal(other.fixed, scene.fixed)
    with pytest.raises(KeyError, match="no vertex set 'clam'.*'body', 'clamp'"):
        other.fix_set("clam")


def test_fix_set_refuses_an_empty_set():
    mesh = TetMesh(POINTS[1:5], TETS[:1] - 1, vertex_sets={"nothing": []})
    with pytest.raises(ValueError, match="vertex set 'nothing' is empty"):
        es.Scene(mesh).fix_set("nothing")


def test_tags_given_to_the_constructor_are_checked():
    with pytest.raises(ValueError, match=r"vertex_sets\['clamp'\]"):
        TetMesh(POINTS[1:5], TETS[:1] - 1, vertex_sets={"clamp": [0, 4]})
    with pytest.raises(ValueError, match=r"cell_data\['E'\] has shape \(2,\); expected \[1, \.\.\.\]"):
        TetMesh(POINTS[1:5], TETS[:1] - 1, cell_data={"E": [1.0, 2.0]})
    mesh = TriMesh([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]], element_sets={"all": [0]})
    assert mesh.element_sets["all"].tolist() == [0] and mesh.vertex_sets == {}


def test_a_set_naming_missing_points_is_a_file_error(tmp_path):
    path = tmp_path / "bad.inp"
    meshio.write(path, meshio.Mesh(POINTS, [("tetra", TETS)], point_sets={"clamp": np.array([0, 1])}))
    text = path.read_text().replace("*NSET, NSET=clamp\n1,2", "*NSET, NSET=clamp\n1,2,99")
    path.write_text(text)
    with pytest.raises(MeshFileError, match=r"bad\.inp"):
        TetMesh.load(path)
