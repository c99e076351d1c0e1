"""Simplex meshes: tetrahedra in 3D, triangles in 2D, validated once at construction.

Every later module trusts these invariants: finite float64 rest positions, int64 element indices in range,
no degenerate elements, no element listed twice, no two elements overlapping across a shared facet, no
orphan vertices and positive orientation of every element.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from os import PathLike
from typing import Any

import numpy as np
import torch

from . import io as mesh_io
from . import primitives
from .tags import check_tags
from .validation import (
    TET_FACES,
    TRI_EDGES,
    check_finite,
    format_indices,
    row_counts,
    signed_volumes,
    validated,
)


def _to_tensor(data: Any) -> torch.Tensor:
    if isinstance(data, torch.Tensor):
        return data.detach().cpu()
    return torch.as_tensor(np.asarray(data))


class SimplexMesh:
    """Dimension-generic simplex mesh (d = 2 or 3) with validated, positively oriented elements.

    `vertices`: rest positions, shape `[n, d]`, float64, in m. `elements`: vertex indices, shape
    `[m, d + 1]`, int64. Negatively oriented elements are repaired by swapping their last two vertices;
    every other defect raises ValueError naming the offending indices: non-finite coordinates, indices
    out of range, flat elements (judged relative to each element's size, so any unit scale works),
    elements repeated (in any vertex order), elements overlapping across a shared facet, and vertices
    that no element uses (they would carry no mass; the file loaders drop them with `prune`).

    Tags name parts of the mesh (see `energysim.mesh.tags`; the file loaders fill them from the file):
    `vertex_sets` (name -> sorted vertex indices `[k]`, int64: ``scene.fix(mesh.vertex_sets["clamp"])``),
    `element_sets` (name -> sorted element indices `[k]`, int64) and `cell_data` (name -> per-element
    values `[m, ...]`, in the file's units). Each defaults to empty.
    """

    def __init__(
        self,
        vertices: Any,
        elements: Any,
        dim: int | None = None,
        *,
        vertex_sets: Mapping[str, Any] | None = None,
        element_sets: Mapping[str, Any] | None = None,
        cell_data: Mapping[str, Any] | None = None,
    ) -> None:
        vertices = _to_tensor(vertices)
        elements = _to_tensor(elements)
        if dim is None:
            dim = vertices.shape[1] if vertices.ndim == 2 else -1
        if dim not in (2, 3):
            raise ValueError(f"vertices must have shape [n, 2] or [n, 3], got {tuple(vertices.shape)}")
        if vertices.ndim != 2 or vertices.shape[1] != dim:
            raise ValueError(f"vertices must have shape [n, {dim}], got {tuple(vertices.shape)}")
        if elements.numel() == 0:
            raise ValueError("mesh has no elements")
        if elements.ndim != 2 or elements.shape[1] != dim + 1:
            raise ValueError(f"elements must have shape [m, {dim + 1}], got {tuple(elements.shape)}")
        if elements.dtype.is_floating_point or elements.dtype.is_complex or elements.dtype == torch.bool:
            raise ValueError(f"elements must hold integer vertex indices, got dtype {elements.dtype}")
        if vertices.dtype.is_complex or vertices.dtype == torch.bool:
            raise ValueError(f"vertices must hold real coordinates, got dtype {vertices.dtype}")

        vertices, elements = validated(vertices, elements, dim)

        self.vertices: torch.Tensor = vertices
        self.elements: torch.Tensor = elements.contiguous()
        self.dim: int = dim
        # reorientation swaps vertices within an element, never reorders elements: tags stay aligned
        tags = check_tags(vertex_sets, element_sets, cell_data, vertices.shape[0], elements.shape[0])
        self.vertex_sets: dict[str, torch.Tensor] = tags.vertex_sets
        self.element_sets: dict[str, torch.Tensor] = tags.element_sets
        self.cell_data: dict[str, torch.Tensor] = tags.cell_data

    def __repr__(self) -> str:
        return f"{type(self).__name__}(num_vertices={self.num_vertices}, num_elements={self.num_elements})"

    @property
    def num_vertices(self) -> int:
        """Number of vertices n."""
        return self.vertices.shape[0]

    @property
    def num_elements(self) -> int:
        """Number of elements m."""
        return self.elements.shape[0]

    def element_rest_volume(self) -> torch.Tensor:
        """Rest volume of each element, shape `[m]`, in m^d (> 0; an area per metre of depth in 2D)."""
        return signed_volumes(self.vertices, self.elements)

    def vertex_rest_volume(self) -> torch.Tensor:
        """Lumped rest volume per vertex, shape `[n]`, in m^d: each element gives volume/(d+1) to each of
        its vertices."""
        share = (self.element_rest_volume() / (self.dim + 1)).repeat_interleave(self.dim + 1)
        out = torch.zeros(self.num_vertices, dtype=self.vertices.dtype)
        return out.index_add_(0, self.elements.flatten(), share)

    def edges(self) -> torch.Tensor:
        """Unique undirected edges, shape `[e, 2]`, each row `i < j`, rows sorted lexicographically."""
        pairs = list(itertools.combinations(range(self.dim + 1), 2))
        ends = self.elements[:, pairs].reshape(-1, 2).sort(dim=1).values
        # A scalar key i * n + j sorts exactly like the (i, j) rows and makes unique 1-D (fast).
        n = self.num_vertices
        keys = torch.unique(ends[:, 0] * n + ends[:, 1])
        return torch.stack([keys // n, keys % n], dim=1)

    def surface(self) -> torch.Tensor:
        """Oriented boundary facets: facets used by exactly one element.

        3D: triangles, shape `[s, 3]`, ordered so the right-hand normal points outwards. 2D: segments,
        shape `[s, 2]`, traversing the boundary counter-clockwise, so the outward normal is the segment
        direction rotated by -90 degrees.
        """
        return self.surface_with_elements()[0]

    def surface_with_elements(self) -> tuple[torch.Tensor, torch.Tensor]:
        """`surface()` and the element each facet bounds, shape `[s]`, int64."""
        local = TET_FACES if self.dim == 3 else TRI_EDGES
        facets = self.elements[:, local].reshape(-1, self.dim)
        boundary = row_counts(facets.sort(dim=1).values) == 1
        owner = torch.arange(self.num_elements).repeat_interleave(len(local))
        return facets[boundary].contiguous(), owner[boundary]

    def surface_vertices(self) -> torch.Tensor:
        """Sorted unique indices of the vertices on the boundary, shape `[k]`."""
        return torch.unique(self.surface().flatten())

    def bounding_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Axis-aligned bounds of the rest positions: `(min, max)`, each shape `[d]`, in m."""
        return self.vertices.min(dim=0).values, self.vertices.max(dim=0).values

    def save(
        self,
        path: str | PathLike[str],
        point_data: Mapping[str, Any] | None = None,
        cell_data: Mapping[str, Any] | None = None,
    ) -> None:
        """Write the mesh with meshio (format from the extension), atomically.

        `point_data`: optional arrays with leading dimension n; `cell_data`: optional arrays with leading
        dimension m. The file is written next to `path` under a temporary name, then renamed over it.
        """
        cell_type = "tetra" if self.dim == 3 else "triangle"
        mesh_io.write_simplices(path, self.vertices, self.elements, cell_type, point_data, cell_data)


class TetMesh(SimplexMesh):
    """Tetrahedral mesh. `vertices`: rest positions, shape `[n, 3]`, in m; `tets`: shape `[m, 4]`."""

    def __init__(self, vertices: Any, tets: Any, **tags: Mapping[str, Any] | None) -> None:
        super().__init__(vertices, tets, dim=3, **tags)

    @property
    def tets(self) -> torch.Tensor:
        """Tetrahedra, shape `[m, 4]`, int64, positively oriented (same tensor as `elements`)."""
        return self.elements

    @classmethod
    def box(
        cls,
        size: tuple[float, float, float] = (1.0, 1.0, 1.0),
        cells: tuple[int, int, int] = (1, 1, 1),
        origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> TetMesh:
        """Axis-aligned box of `size` (m) from `origin` (m), `cells` cubes per axis, 6 tets per cube."""
        return cls(*primitives.box(size, cells, origin))

    @classmethod
    def from_voxels(
        cls, occupancy: Any, voxel_size: float | tuple[float, ...] = 1.0, origin: Any = (0.0, 0.0, 0.0)
    ) -> TetMesh:
        """Conforming mesh of the occupied voxels, 6 tets each. `occupancy`: bool, shape `[nx, ny, nz]`;
        `voxel_size`: edge length(s) in m; `origin`: position of voxel (0, 0, 0)'s min corner in m."""
        return cls(*primitives.voxels(occupancy, voxel_size, origin, dim=3))

    @classmethod
    def load(cls, path: str | PathLike[str], prune: bool = True) -> TetMesh:
        """Read the "tetra" cells of any meshio format (all blocks); `prune` drops unused vertices and
        renumbers. Keeps the file's vertex sets, element sets and cell data (`energysim.mesh.tags`).
        Every failure (missing, unreadable or corrupt file, no "tetra" cells, an invalid mesh)
        is a `MeshFileError` (a ValueError; a FileNotFoundError too when nothing is at `path`) naming
        `path`."""
        vertices, tets, tags = mesh_io.read_tagged_simplices(path, "tetra", prune)
        with mesh_io.reading(path):
            return cls(vertices, tets, **tags._asdict())


class TriMesh(SimplexMesh):
    """Triangle mesh in the (x, y) plane. `vertices`: shape `[n, 2]` (or `[n, 3]` with constant z), in m."""

    def __init__(self, vertices: Any, triangles: Any, **tags: Mapping[str, Any] | None) -> None:
        vertices = _to_tensor(vertices)
        if vertices.ndim == 2 and vertices.shape[1] == 3 and vertices.shape[0] > 0:
            check_finite(vertices)
            z = vertices[:, 2].to(torch.float64)
            # Relative to the coordinates' magnitude, so the test means the same at any scale.
            scale = float(vertices.to(torch.float64).abs().max())
            if float((z - z[0]).abs().max()) > 1e-12 * scale:
                raise ValueError("TriMesh needs planar vertices: got shape [n, 3] with non-constant z")
            vertices = vertices[:, :2]
        super().__init__(vertices, triangles, dim=2, **tags)

    @property
    def triangles(self) -> torch.Tensor:
        """Triangles, shape `[m, 3]`, int64, counter-clockwise (same tensor as `elements`)."""
        return self.elements

    @classmethod
    def box(
        cls,
        size: tuple[float, float] = (1.0, 1.0),
        cells: tuple[int, int] = (1, 1),
        origin: tuple[float, float] = (0.0, 0.0),
    ) -> TriMesh:
        """Axis-aligned rectangle of `size` (m) from `origin` (m), `cells` squares per axis, 2 triangles
        per square."""
        return cls(*primitives.box(size, cells, origin))

    @classmethod
    def from_voxels(
        cls, occupancy: Any, voxel_size: float | tuple[float, ...] = 1.0, origin: Any = (0.0, 0.0)
    ) -> TriMesh:
        """Conforming mesh of the occupied pixels, 2 triangles each. `occupancy`: bool, shape `[nx, ny]`;
        `voxel_size`: edge length(s) in m; `origin`: position of pixel (0, 0)'s min corner in m."""
        return cls(*primitives.voxels(occupancy, voxel_size, origin, dim=2))

    @classmethod
    def load(cls, path: str | PathLike[str], prune: bool = True) -> TriMesh:
        """Read the "triangle" cells of any meshio format (all blocks); `prune` drops unused vertices and
        renumbers. Keeps the file's vertex sets, element sets and cell data (`energysim.mesh.tags`).
        Every failure (missing, unreadable or corrupt file, no "triangle" cells, an invalid
        mesh) is a `MeshFileError` (a ValueError; a FileNotFoundError too when nothing is at `path`)
        naming `path`."""
        vertices, triangles, tags = mesh_io.read_tagged_simplices(path, "triangle", prune)
        with mesh_io.reading(path):
            return cls(vertices, triangles, **tags._asdict())


__all__ = ["SimplexMesh", "TetMesh", "TriMesh", "signed_volumes", "format_indices"]
