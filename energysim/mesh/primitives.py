"""Structured simplex meshes on a regular lattice: boxes and voxel (pixel) occupancy grids.

Every cell of the lattice is split with the Kuhn (Freudenthal) pattern: one simplex per permutation of the
axes, walking from the cell's min corner to its max corner one axis step at a time. Because the pattern
is the same in every cell, the diagonal of each shared square face runs min-to-max corner on both sides,
so neighbouring cells' faces match and the mesh is conforming (6 tets per cube, 2 triangles per square).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch


def kuhn_pattern(dim: int) -> np.ndarray:
    """Corner offsets of the d! Kuhn simplices of the unit cell, shape `[d!, d + 1, d]`, 0/1 entries.

    Each simplex is positively oriented (its signed volume is +1 / d!).
    """
    pattern = []
    for perm in itertools.permutations(range(dim)):
        corners = np.zeros((dim + 1, dim), dtype=np.int64)
        for step, axis in enumerate(perm):
            corners[step + 1] = corners[step]
            corners[step + 1, axis] = 1
        if np.linalg.det((corners[1:] - corners[0]).astype(np.float64)) < 0:
            corners[[-2, -1]] = corners[[-1, -2]]
        pattern.append(corners)
    return np.stack(pattern)


def _per_axis(value: Any, dim: int, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    if array.shape[0] not in (1, dim):
        raise ValueError(f"{name} needs 1 or {dim} entries, got {value!r}")
    array = np.broadcast_to(array, (dim,)).copy()
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return array


def voxels(
    occupancy: Any, voxel_size: float | Sequence[float] = 1.0, origin: Any = None, dim: int | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Conforming simplex mesh of the occupied cells of a regular grid.

    `occupancy`: bool, shape `[nx, ny]` or `[nx, ny, nz]`; cell (i, j, k) spans
    `origin + [i, j, k] * voxel_size` to `origin + [i + 1, j + 1, k + 1] * voxel_size`. `voxel_size`: cell
    edge length in m, a scalar or one per axis. `origin`: min corner of cell 0, shape `[d]`, in m (default 0).
    `dim`: expected d, checked against `occupancy` when given.

    Returns `(vertices, elements)`: positions, shape `[n, d]`, float64, in m (only the lattice points that
    some simplex uses, each once, in lattice order), and positively oriented simplices, shape
    `[d! * occupied, d + 1]`, int64. Raises ValueError if no cell is occupied.
    """
    occupancy = np.asarray(occupancy)
    d = occupancy.ndim
    if dim is not None and d != dim:
        raise ValueError(f"occupancy must have {dim} dimensions, got shape {occupancy.shape}")
    if d not in (2, 3):
        raise ValueError(f"occupancy must have shape [nx, ny] or [nx, ny, nz], got {occupancy.shape}")
    occupancy = occupancy.astype(bool)
    spacing = _per_axis(voxel_size, d, "voxel_size")
    if np.any(spacing <= 0):
        raise ValueError(f"voxel_size must be positive, got {voxel_size!r}")
    offset = _per_axis(0.0 if origin is None else origin, d, "origin")

    cells = np.argwhere(occupancy)
    if cells.shape[0] == 0:
        raise ValueError(f"occupancy of shape {occupancy.shape} has no occupied voxel")

    # Lattice points are indexed C-order on the (nx + 1, ny + 1[, nz + 1]) grid of cell corners.
    lattice_shape = tuple(s + 1 for s in occupancy.shape)
    corners = cells[:, None, None, :] + kuhn_pattern(d)[None]  # [cells, d!, d + 1, d]
    lattice_ids = np.ravel_multi_index(tuple(np.moveaxis(corners, -1, 0)), lattice_shape)
    # Neighbouring voxels name a shared corner by the same lattice id, so unique() merges them.
    used, elements = np.unique(lattice_ids.reshape(-1, d + 1), return_inverse=True)
    elements = elements.reshape(-1, d + 1)
    points = np.stack(np.unravel_index(used, lattice_shape), axis=1)
    vertices = offset + points * spacing
    return torch.from_numpy(vertices).to(torch.float64), torch.from_numpy(elements).to(torch.int64)


def box(
    size: Sequence[float], cells: Sequence[int], origin: Sequence[float] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Conforming simplex mesh of an axis-aligned box (d = len(size), 2 or 3).

    `size`: edge lengths, shape `[d]`, in m. `cells`: number of cells per axis, shape `[d]`. `origin`: min
    corner, shape `[d]`, in m (default 0). Returns `(vertices, elements)` with `prod(cells + 1)` vertices,
    shape `[n, d]` in m, and `d! * prod(cells)` positively oriented simplices, shape `[m, d + 1]`.
    """
    size_arr = np.asarray(size, dtype=np.float64).reshape(-1)
    d = size_arr.shape[0]
    cells_arr = np.asarray(cells).reshape(-1)
    if d not in (2, 3) or cells_arr.shape[0] != d:
        raise ValueError(f"size and cells need 2 or 3 entries each, got size={size!r}, cells={cells!r}")
    if not np.all(np.isfinite(size_arr)) or np.any(size_arr <= 0):
        raise ValueError(f"size must be positive and finite, got {size!r}")
    if not np.issubdtype(cells_arr.dtype, np.integer) or np.any(cells_arr < 1):
        raise ValueError(f"cells must be positive integers, got {cells!r}")
    occupancy = np.ones(tuple(int(c) for c in cells_arr), dtype=bool)
    return voxels(occupancy, size_arr / cells_arr, origin, dim=d)


__all__ = ["box", "voxels", "kuhn_pattern"]
