"""Mesh files through meshio: reading simplex cells out of any format, and atomic writes."""

from __future__ import annotations

import os
import secrets
from collections.abc import Mapping
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Any

import meshio
import numpy as np
import torch

if TYPE_CHECKING:
    from .simplex import SimplexMesh


def _numpy(value: Any) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def read_meshio(path: str | PathLike[str]) -> meshio.Mesh:
    """Read any meshio-supported file; FileNotFoundError naming `path` if it does not exist."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    return meshio.read(path)


def simplices_from_meshio(
    mesh: meshio.Mesh, cell_type: str, prune: bool = True, source: str = "mesh"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Concatenate all `cell_type` blocks ("tetra" or "triangle") of a meshio mesh, ignoring other cells.

    Returns `(vertices, elements)`: positions, shape `[n, 3]` (or `[n, 2]` if the file is planar), float64,
    in the file's units (m expected), and indices, shape `[m, 4]` or `[m, 3]`, int64. With `prune`, vertices
    no element uses are dropped and the elements renumbered. Raises ValueError naming `source` if there
    is no `cell_type` cell.
    """
    blocks = [np.asarray(block.data) for block in mesh.cells if block.type == cell_type]
    if not blocks or sum(b.shape[0] for b in blocks) == 0:
        found = sorted({block.type for block in mesh.cells})
        raise ValueError(f"{source} has no {cell_type!r} cells (found cell types {found})")
    elements = np.concatenate(blocks).astype(np.int64)
    vertices = np.asarray(mesh.points, dtype=np.float64)
    if prune:
        # Files often carry geometry points or lower-dimensional cells' vertices that no simplex uses.
        used, inverse = np.unique(elements, return_inverse=True)
        if used[0] >= 0 and used[-1] < vertices.shape[0]:
            vertices = vertices[used]
            elements = inverse.reshape(elements.shape)
    return torch.from_numpy(np.ascontiguousarray(vertices)), torch.from_numpy(np.ascontiguousarray(elements))


def read_simplices(
    path: str | PathLike[str], cell_type: str, prune: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Read the `cell_type` cells of the file at `path`; see `simplices_from_meshio` for the result."""
    return simplices_from_meshio(read_meshio(path), cell_type, prune, source=str(path))


def write_simplices(
    path: str | PathLike[str],
    vertices: torch.Tensor,
    elements: torch.Tensor,
    cell_type: str,
    point_data: Mapping[str, Any] | None = None,
    cell_data: Mapping[str, Any] | None = None,
) -> None:
    """Write a single-block mesh atomically, in the meshio format that the extension of `path` names.

    `vertices`: shape `[n, d]`, in m (2D points get z = 0, which every format accepts). `elements`: shape
    `[m, d + 1]`. `point_data` / `cell_data`: arrays with leading dimension n / m. Readers never see a
    half-written file: the data goes to a temporary file in the same folder, which is then renamed over
    `path` (a same-filesystem rename is atomic); on failure the temporary file is removed and any
    previous file at `path` is left untouched.
    """
    path = Path(path)
    points = _numpy(vertices).astype(np.float64)
    if points.shape[1] == 2:
        points = np.concatenate([points, np.zeros((points.shape[0], 1))], axis=1)
    cells = _numpy(elements).astype(np.int64)
    pdata = {name: _numpy(value) for name, value in (point_data or {}).items()}
    cdata = {name: [_numpy(value)] for name, value in (cell_data or {}).items()}
    for name, value in pdata.items():
        if value.ndim == 0 or value.shape[0] != points.shape[0]:
            raise ValueError(
                f"point_data {name!r} has shape {value.shape}, expected [{points.shape[0]}, ...]"
            )
    for name, (value,) in cdata.items():
        if value.ndim == 0 or value.shape[0] != cells.shape[0]:
            raise ValueError(f"cell_data {name!r} has shape {value.shape}, expected [{cells.shape[0]}, ...]")
    mesh = meshio.Mesh(points, [(cell_type, cells)], point_data=pdata, cell_data=cdata)

    # Keep the full destination name as the tail so meshio infers the same format from the extension.
    tmp = path.parent / f".tmp-{secrets.token_hex(6)}-{path.name}"
    try:
        meshio.write(tmp, mesh)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def load_mesh(path: str | PathLike[str], prune: bool = True) -> SimplexMesh:
    """Load a TetMesh if the file at `path` has "tetra" cells, else a TriMesh if it has "triangle" cells."""
    # Imported here because simplex.py imports this module for TetMesh.load / SimplexMesh.save.
    from .simplex import TetMesh, TriMesh

    mesh = read_meshio(path)
    cell_types = {block.type for block in mesh.cells}
    if "tetra" in cell_types:
        return TetMesh(*simplices_from_meshio(mesh, "tetra", prune, source=str(path)))
    if "triangle" in cell_types:
        return TriMesh(*simplices_from_meshio(mesh, "triangle", prune, source=str(path)))
    raise ValueError(f"{path} has neither tetra nor triangle cells (found cell types {sorted(cell_types)})")


__all__ = ["load_mesh", "read_meshio", "read_simplices", "simplices_from_meshio", "write_simplices"]
