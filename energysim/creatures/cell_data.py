"""A creature mesh's muscle cell data, read and checked: the ``actuator`` of each element (−1
passive) and its unit rest ``fibre`` direction. Every refusal is a `MeshFileError` that names the
file and the offending elements (or, for an actuator that drives no element, the sidecar).
"""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
import torch
from torch import Tensor

from energysim.creatures.shipped_files import MAKE_SCRIPT
from energysim.mesh.io import MeshFileError


def read_muscle_cell_data(
    raw: meshio.Mesh,
    cell_type: str,
    num_elements: int,
    num_actuators: int,
    dim: int,
    mesh_path: Path,
    sidecar_path: Path,
) -> tuple[Tensor, Tensor]:
    """The actuators and fibres of the `cell_type` elements of `raw`, read from `mesh_path`.

    Args:
        raw: the mesh file as meshio read it.
        cell_type: "tetra" (3D) or "triangle" (2D).
        num_elements: m, the elements of the creature's mesh.
        num_actuators: a, as the sidecar at `sidecar_path` declares.
        dim: spatial dimension d.

    Returns:
        actuators: int64, shape `[m]`, each in [−1, a), every actuator used by some element;
        fibres: float64, shape `[m, d]`, finite, of unit length on every actuated element.

    Raises:
        MeshFileError: cell data missing, of the wrong shape or type, or that do not fit the mesh or
            the declared actuators.
    """
    actuator_data = _cell_data(raw, "actuator", cell_type, mesh_path)
    if actuator_data.shape[0] != num_elements:
        raise MeshFileError(
            mesh_path,
            f"'actuator' cell data has {actuator_data.shape[0]} entries for {num_elements} elements",
        )
    actuators = _actuators(actuator_data, num_actuators, mesh_path, sidecar_path)
    fibres = _fibres(_cell_data(raw, "fibre", cell_type, mesh_path), actuators, dim, mesh_path)
    return actuators, fibres


def _cell_data(mesh: meshio.Mesh, name: str, cell_type: str, path: Path) -> np.ndarray:
    arrays = mesh.cell_data.get(name, [])
    if len(arrays) != len(mesh.cells):
        raise MeshFileError(path, f"has no {name!r} cell data; rebuild it with {MAKE_SCRIPT}")
    blocks = [
        np.asarray(data) for block, data in zip(mesh.cells, arrays, strict=True) if block.type == cell_type
    ]
    if not blocks:
        raise MeshFileError(path, f"has no {name!r} cell data; rebuild it with {MAKE_SCRIPT}")
    if any(not np.issubdtype(block.dtype, np.number) for block in blocks):
        raise MeshFileError(path, f"{name!r} cell data must be numbers, got dtype {blocks[0].dtype}")
    if len({block.shape[1:] for block in blocks}) != 1:
        raise MeshFileError(path, f"{name!r} cell data blocks have different shapes")
    return np.concatenate(blocks)


def _actuators(values: np.ndarray, num_actuators: int, path: Path, sidecar_path: Path) -> Tensor:
    """The actuator cell data as int64 `[m]`, each in [−1, a), every actuator used by some element."""
    if values.ndim == 2 and values.shape[1] == 1:
        values = values[:, 0]
    if values.ndim != 1:
        raise MeshFileError(
            path, f"'actuator' cell data must have one entry per element, got shape {values.shape}"
        )
    bad = np.flatnonzero(~np.isfinite(values) | (values != np.round(values)))
    if bad.size:
        raise MeshFileError(path, f"'actuator' cell data of elements {bad[:10].tolist()} is not an integer")
    actuators = values.astype(np.int64)
    bad = np.flatnonzero((actuators < -1) | (actuators >= num_actuators))
    if bad.size:
        raise MeshFileError(
            path,
            f"elements {bad[:10].tolist()} have actuators {actuators[bad[:10]].tolist()}, outside [-1, "
            f"{num_actuators}) (-1: passive; {sidecar_path.name} declares {num_actuators} actuators)",
        )
    unused = np.setdiff1d(np.arange(num_actuators), actuators)
    if unused.size:
        raise MeshFileError(
            sidecar_path,
            f"actuators {unused[:10].tolist()} (of 'num_actuators' = {num_actuators}) drive no element of "
            f"{path.name}; every declared actuator needs cells",
        )
    return torch.from_numpy(actuators)


def _fibres(values: np.ndarray, actuators: Tensor, dim: int, path: Path) -> Tensor:
    """The fibre cell data as float64 `[m, d]`: finite, and of unit length on every actuated element."""
    if values.ndim != 2 or values.shape != (actuators.shape[0], dim):
        raise MeshFileError(
            path, f"'fibre' cell data has shape {values.shape}; expected [{actuators.shape[0]}, {dim}]"
        )
    fibres = values.astype(np.float64)
    length = np.linalg.norm(fibres, axis=1)
    bad = np.flatnonzero(
        ~np.isfinite(fibres).all(axis=1) | ((actuators.numpy() >= 0) & ~(np.abs(length - 1) < 1e-6))
    )
    if bad.size:
        raise MeshFileError(
            path,
            f"'fibre' cell data of elements {bad[:10].tolist()} is not finite, or not of unit length on a "
            "muscle element",
        )
    return torch.from_numpy(fibres)


__all__ = ["read_muscle_cell_data"]
