"""Simplex meshes: tetrahedra in 3D, triangles in 2D, validated once at construction.

Every later module trusts these invariants: finite float64 rest positions, int64 element indices in range,
no degenerate elements, no element listed twice, no two elements overlapping across a shared facet, no
orphan vertices and positive orientation of every element.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Mapping
from os import PathLike
from typing import Any

import numpy as np
import torch

from . import io as mesh_io
from . import primitives
from .tags import check_tags

logger = logging.getLogger(__name__)

# Relative threshold below which an element counts as flat: |volume| <= tol * (mean edge length)**d.
DEGENERACY_TOLERANCE = 1e-12

# Faces of a positively oriented tet (v0..v3), each ordered so its right-hand normal points outwards.
_TET_FACES = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))
# Edges of a positively oriented (counter-clockwise) triangle; traversed CCW, the outside is on the right.
_TRI_EDGES = ((0, 1), (1, 2), (2, 0))


def format_indices(indices: torch.Tensor, limit: int = 10) -> str:
    """Format the indices `indices` (shape `[k]`) as `"[a, b, ...]"`, listing at most `limit` of them."""
    values = indices.flatten().tolist()
    text = "[" + ", ".join(str(int(v)) for v in values[:limit]) + "]"
    if len(values) > limit:
        text += f" and {len(values) - limit} more"
    return text


def _edge_determinant(edges: torch.Tensor) -> torch.Tensor:
    """det of the d edge vectors `edges[..., k, :]` (shape `[..., d, d]`), shape `[...]`."""
    if edges.shape[-1] == 3:
        # Explicit triple product: exactly zero for repeated vertices, unlike an LU-based determinant.
        return (edges[..., 0, :] * torch.linalg.cross(edges[..., 1, :], edges[..., 2, :])).sum(-1)
    return edges[..., 0, 0] * edges[..., 1, 1] - edges[..., 0, 1] * edges[..., 1, 0]


def signed_volumes(vertices: torch.Tensor, elements: torch.Tensor) -> torch.Tensor:
    """Signed simplex volumes, differentiable in `vertices`.

    `vertices`: positions, shape `[n, d]` with d = 2 or 3, in m. `elements`: vertex indices, shape
    `[m, d + 1]`. Returns shape `[m]`, in m^d: `det[x1-x0, x2-x0, x3-x0] / 6` in 3D, `det[x1-x0, x2-x0] / 2`
    in 2D (area, i.e. volume per metre of depth). Positive for positively oriented elements.
    """
    x = vertices[elements]
    edges = x[:, 1:] - x[:, :1]
    return _edge_determinant(edges) / (6.0 if vertices.shape[1] == 3 else 2.0)


def _to_tensor(data: Any) -> torch.Tensor:
    if isinstance(data, torch.Tensor):
        return data.detach().cpu()
    return torch.as_tensor(np.asarray(data))


def _check_finite(vertices: torch.Tensor) -> None:
    bad = torch.nonzero(~torch.isfinite(vertices).all(dim=1)).flatten()
    if bad.numel():
        raise ValueError(f"vertices {format_indices(bad)} have NaN or infinite coordinates")


def _row_keys(rows: torch.Tensor) -> torch.Tensor:
    """For non-negative integer rows, shape `[r, k]`, an int64 key per row, shape `[r]`, equal exactly
    for equal rows."""
    # Fold the columns into one scalar key, replacing the partial key by its dense rank before each
    # step so it stays below r * n (no int64 overflow); 1-D unique is far faster than unique(dim=0).
    key = rows[:, 0]
    for column in range(1, rows.shape[1]):
        rank = torch.unique(key, return_inverse=True)[1]
        key = rank * (int(rows[:, column].max()) + 1) + rows[:, column]
    return key


def _key_counts(key: torch.Tensor) -> torch.Tensor:
    """How many entries of `key` (shape `[r]`) equal each one, shape `[r]`."""
    _, inverse, counts = torch.unique(key, return_inverse=True, return_counts=True)
    return counts[inverse]


def _row_counts(rows: torch.Tensor) -> torch.Tensor:
    """For non-negative integer rows, shape `[r, k]`, how many rows equal each one, shape `[r]`."""
    return _key_counts(_row_keys(rows))


def _check_degenerate(vertices: torch.Tensor, elements: torch.Tensor, dim: int) -> None:
    """Refuse elements with a repeated vertex or (near) zero volume, and volumes float64 cannot hold.

    Flatness is judged on each element scaled to unit size (its edges divided by its largest coordinate
    extent), so the test is the same for a mesh in micrometres or in kilometres and cannot overflow.
    """
    sorted_ids = elements.sort(dim=1).values
    repeated = (sorted_ids[:, 1:] == sorted_ids[:, :-1]).any(dim=1)
    x = vertices[elements]
    extent = (x.amax(dim=1) - x.amin(dim=1)).amax(dim=1)
    unit = (x[:, 1:] - x[:, :1]) / torch.where(extent > 0, extent, torch.ones_like(extent))[:, None, None]
    unit_volume = _edge_determinant(unit) / math.factorial(dim)
    pairs = torch.tensor(list(itertools.combinations(range(dim), 2)))
    # Edges between vertices 1..d, plus the d edges from vertex 0 (the rows of `unit`).
    other_edges = unit[:, pairs[:, 1]] - unit[:, pairs[:, 0]]
    lengths = torch.cat([unit.norm(dim=-1), other_edges.norm(dim=-1)], dim=1)
    mean_edge = lengths.mean(dim=1)
    # Written as "not above" so that a NaN from coincident vertices counts as flat.
    flat = ~(unit_volume.abs() > DEGENERACY_TOLERANCE * mean_edge**dim)
    bad = torch.nonzero(repeated | flat | (extent == 0)).flatten()
    if bad.numel():
        raise ValueError(
            f"{bad.numel()} degenerate (repeated-vertex or near-zero-volume) elements {format_indices(bad)}"
        )
    volume = signed_volumes(vertices, elements)
    bad = torch.nonzero(~torch.isfinite(volume) | (volume == 0)).flatten()
    if bad.numel():
        raise ValueError(
            f"elements {format_indices(bad)} are well shaped but their volumes overflow or underflow "
            f"float64 (element sizes {float(extent.min()):.3g} to {float(extent.max()):.3g} m); "
            "rescale the mesh to metres"
        )


def _check_distinct(elements: torch.Tensor) -> None:
    """Refuse two elements on the same vertex set (an element listed twice, in any vertex order)."""
    key_counts = _row_counts(elements.sort(dim=1).values)
    bad = torch.nonzero(key_counts > 1).flatten()
    if bad.numel():
        raise ValueError(
            f"elements {format_indices(bad)} repeat another element's vertices (an element listed twice, "
            "possibly with its vertices permuted); each element must appear once"
        )


def _permutation_parity(order: torch.Tensor) -> torch.Tensor:
    """Parity (0 even, 1 odd) of each row of `order`, a permutation of 0..k-1, shape `[r, k]`."""
    k = order.shape[1]
    inversions = sum((order[:, i] > order[:, j]).long() for i in range(k) for j in range(i + 1, k))
    return inversions % 2


def _check_no_overlap(elements: torch.Tensor, dim: int) -> None:
    """Refuse positively oriented elements that overlap in volume across a shared facet.

    In a valid mesh a facet bounds at most two elements, one on each side, so the two traverse it in
    opposite orientations. A facet of three or more elements, or of two that traverse it the same way
    (both on the same side), means the elements overlap.
    """
    local = _TET_FACES if dim == 3 else _TRI_EDGES
    facets = elements[:, local].reshape(-1, dim)
    ordered = facets.sort(dim=1)
    parity = _permutation_parity(ordered.indices)
    owner = torch.arange(elements.shape[0]).repeat_interleave(len(local))
    key = _row_keys(ordered.values)
    shared = _key_counts(key)
    same_way = _key_counts(2 * torch.unique(key, return_inverse=True)[1] + parity)
    crowded = shared > 2
    if bool(crowded.any()):
        first = facets[crowded][0].sort().values
        raise ValueError(
            f"elements {format_indices(torch.unique(owner[crowded]))} overlap: facets shared by more than "
            f"two elements (e.g. vertices {format_indices(first)})"
        )
    same_side = (shared == 2) & (same_way == 2)
    if bool(same_side.any()):
        first = facets[same_side][0].sort().values
        raise ValueError(
            f"elements {format_indices(torch.unique(owner[same_side]))} overlap: they lie on the same side "
            f"of a shared facet (e.g. vertices {format_indices(first)})"
        )


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

        vertices = vertices.to(torch.float64).clone().contiguous()
        elements = elements.to(torch.int64).clone().contiguous()
        n = vertices.shape[0]
        _check_finite(vertices)

        bad = torch.nonzero(((elements < 0) | (elements >= n)).any(dim=1)).flatten()
        if bad.numel():
            raise ValueError(
                f"elements {format_indices(bad)} reference vertex indices outside [0, {n}) ({n} vertices)"
            )

        _check_degenerate(vertices, elements, dim)
        volume = signed_volumes(vertices, elements)
        _check_distinct(elements)

        used = torch.bincount(elements.flatten(), minlength=n) > 0
        bad = torch.nonzero(~used).flatten()
        if bad.numel():
            raise ValueError(f"vertices {format_indices(bad)} are used by no element")

        negative = volume < 0
        count = int(negative.sum())
        if count:
            # Swapping two vertices flips the sign of the determinant and leaves the element unchanged.
            elements[negative] = elements[negative][:, [*range(dim - 1), dim, dim - 1]]
            logger.info("reoriented %d of %d negatively oriented elements", count, elements.shape[0])
        _check_no_overlap(elements, dim)

        self.vertices: torch.Tensor = vertices
        self.elements: torch.Tensor = elements.contiguous()
        self.dim: int = dim
        # reorientation swaps vertices within an element, never reorders elements: tags stay aligned
        tags = check_tags(vertex_sets, element_sets, cell_data, n, elements.shape[0])
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
        local = _TET_FACES if self.dim == 3 else _TRI_EDGES
        facets = self.elements[:, local].reshape(-1, self.dim)
        boundary = _row_counts(facets.sort(dim=1).values) == 1
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
            _check_finite(vertices)
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
