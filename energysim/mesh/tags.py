"""Named vertex sets, element sets and per-element data that a mesh file carries beside its cells.

Mesh generators name the parts of a model so that boundary conditions can refer to them: gmsh's
physical groups, Abaqus' ``*NSET`` / ``*ELSET``, meshio's ``point_sets`` / ``cell_sets`` of any format
(meshio turns gmsh physical groups into ``cell_sets`` already). They are kept here in the mesh's own
numbering, so that ``scene.fix(mesh.vertex_sets["clamp"])`` pins the vertices the file names:

- `vertex_sets`: every point set, and the vertices of the cells of every cell set, of any cell type
  (the triangles of a gmsh surface group, the lines of an edge group); a point set wins over a cell set
  of the same name.
- `element_sets`: every cell set restricted to the mesh's simplices, as element indices.
- `cell_data`: every numeric per-cell array of the file (``gmsh:physical``, material ids, ...), restricted
  to the mesh's simplices, one row per element.

Vertex indices are renumbered like the mesh's vertices when unused points are pruned; a set's points
that no simplex uses are dropped (a set may end up empty: it named only geometry points).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import NamedTuple

import meshio
import numpy as np
import torch
from torch import Tensor

logger = logging.getLogger(__name__)

# meshio's bookkeeping of gmsh entities, not a set a user named
_INTERNAL_PREFIX = "gmsh:bounding_entities"


class MeshTags(NamedTuple):
    """The tags of a mesh file in the mesh's numbering (see the module docstring)."""

    vertex_sets: dict[str, Tensor]
    element_sets: dict[str, Tensor]
    cell_data: dict[str, Tensor]


def _sorted_indices(values: np.ndarray) -> Tensor:
    return torch.from_numpy(np.unique(values.astype(np.int64)))


def _vertex_map(mesh: meshio.Mesh, cell_type: str, prune: bool) -> np.ndarray:
    """File point index -> mesh vertex index, −1 for a point that was pruned, shape `[points]`."""
    count = len(mesh.points)
    if not prune:
        return np.arange(count)
    used = np.unique(
        np.concatenate([np.asarray(b.data).reshape(-1) for b in mesh.cells if b.type == cell_type])
    )
    mapping = np.full(count, -1, dtype=np.int64)
    mapping[used] = np.arange(used.size)
    return mapping


def _renumber(points: np.ndarray, mapping: np.ndarray, what: str) -> Tensor:
    points = np.asarray(points).reshape(-1)
    if points.size and not np.issubdtype(points.dtype, np.integer):
        raise ValueError(f"{what} holds {points.dtype} entries; expected integer point indices")
    points = points.astype(np.int64)
    outside = points[(points < 0) | (points >= mapping.size)]
    if outside.size:
        raise ValueError(
            f"{what} names points {np.unique(outside)[:10].tolist()} outside [0, {mapping.size}) "
            f"({mapping.size} points)"
        )
    kept = mapping[points]
    return _sorted_indices(kept[kept >= 0])


def mesh_tags(mesh: meshio.Mesh, cell_type: str, prune: bool = True, source: str = "mesh") -> MeshTags:
    """The vertex sets, element sets and cell data of `mesh` for its `cell_type` simplices.

    Args:
        mesh: what meshio read.
        cell_type: "tetra" or "triangle": the blocks that make the mesh's elements, in file order.
        prune: whether the mesh drops points that no `cell_type` cell uses (as `simplices_from_meshio`).
        source: how errors name the file.

    Raises:
        ValueError: a set names points or cells that do not exist (naming the set and the indices).
    """
    mapping = _vertex_map(mesh, cell_type, prune)
    blocks = list(mesh.cells)
    simplex_blocks = [k for k, block in enumerate(blocks) if block.type == cell_type]
    offsets = np.cumsum([0] + [len(blocks[k].data) for k in simplex_blocks])

    vertex_sets: dict[str, Tensor] = {}
    element_sets: dict[str, Tensor] = {}
    for name, per_block in (mesh.cell_sets or {}).items():
        if name.startswith(_INTERNAL_PREFIX):
            continue
        if len(per_block) != len(blocks):
            raise ValueError(
                f"{source}: cell set {name!r} has {len(per_block)} blocks, the file {len(blocks)}"
            )
        points, elements = [], []
        for k, cells in enumerate(per_block):
            cells = np.asarray(cells if cells is not None else [], dtype=np.int64).reshape(-1)
            size = len(blocks[k].data)
            bad = cells[(cells < 0) | (cells >= size)]
            if bad.size:
                raise ValueError(
                    f"{source}: cell set {name!r} names {blocks[k].type} cells {bad[:10].tolist()} outside "
                    f"[0, {size})"
                )
            points.append(np.asarray(blocks[k].data)[cells].reshape(-1))
            if k in simplex_blocks:
                elements.append(cells + offsets[simplex_blocks.index(k)])
        vertex_sets[name] = _renumber(np.concatenate(points), mapping, f"{source}: cell set {name!r}")
        element_sets[name] = _sorted_indices(np.concatenate(elements))
    for name, points in (mesh.point_sets or {}).items():
        vertex_sets[name] = _renumber(points, mapping, f"{source}: point set {name!r}")

    cell_data: dict[str, Tensor] = {}
    for name, per_block in (mesh.cell_data or {}).items():
        arrays = [np.asarray(per_block[k]) for k in simplex_blocks if k < len(per_block)]
        if len(arrays) != len(simplex_blocks) or not all(
            a.ndim >= 1 and (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_) for a in arrays
        ):
            logger.info(
                "%s: cell data %r is not numeric on every %s block; left out", source, name, cell_type
            )
            continue
        if any(a.shape[0] != len(blocks[k].data) for a, k in zip(arrays, simplex_blocks, strict=True)):
            raise ValueError(f"{source}: cell data {name!r} does not have one row per {cell_type} cell")
        if len({a.shape[1:] for a in arrays}) != 1:
            logger.info("%s: cell data %r changes shape between blocks; left out", source, name)
            continue
        cell_data[name] = torch.from_numpy(np.ascontiguousarray(np.concatenate(arrays)))
    return MeshTags(vertex_sets, element_sets, cell_data)


def check_tags(
    vertex_sets: Mapping[str, object] | None,
    element_sets: Mapping[str, object] | None,
    cell_data: Mapping[str, object] | None,
    num_vertices: int,
    num_elements: int,
) -> MeshTags:
    """Validate tags given to a mesh: sorted unique int64 index tensors and per-element rows.

    Raises:
        ValueError: a name that is not a non-empty string, indices that are not integers or lie outside
            `[0, num_vertices)` / `[0, num_elements)` (naming the set and the indices), cell data without
            one row per element.
    """
    from .indices import as_indices

    checked: list[dict[str, Tensor]] = []
    for what, sets, count in (
        ("vertex_sets", vertex_sets, num_vertices),
        ("element_sets", element_sets, num_elements),
    ):
        out: dict[str, Tensor] = {}
        for name, indices in (sets or {}).items():
            if not isinstance(name, str) or not name:
                raise ValueError(f"{what} names must be non-empty strings, got {name!r}")
            index = as_indices(indices, f"{what}[{name!r}]", count)
            out[name] = torch.unique(index.reshape(-1).to(torch.int64))
        checked.append(out)
    data: dict[str, Tensor] = {}
    for name, values in (cell_data or {}).items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"cell_data names must be non-empty strings, got {name!r}")
        tensor = values.detach() if isinstance(values, Tensor) else torch.as_tensor(np.asarray(values))
        if tensor.ndim == 0 or tensor.shape[0] != num_elements:
            raise ValueError(
                f"cell_data[{name!r}] has shape {tuple(tensor.shape)}; expected [{num_elements}, ...] "
                "(one row per element)"
            )
        data[name] = tensor
    return MeshTags(checked[0], checked[1], data)


__all__ = ["MeshTags", "check_tags", "mesh_tags"]
