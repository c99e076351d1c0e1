"""`load_creature`: a shipped creature from its two files, ``NAME.vtu`` (the rest mesh with its
muscle cell data) and ``NAME.json`` (the sidecar), both checked before a `Creature` is made.
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path

from energysim.creatures.cell_data import read_muscle_cell_data
from energysim.creatures.creature import Creature
from energysim.creatures.shipped_files import CREATURES, default_meshes_dir, local_files
from energysim.creatures.sidecar import read_creature_sidecar
from energysim.mesh import TetMesh, TriMesh
from energysim.mesh.io import read_meshio, reading, simplices_from_meshio


def load_creature(name: str, meshes_dir: str | PathLike[str] | None = None) -> Creature:
    """Read creature `name` (see `CREATURES`) from ``NAME.vtu`` and ``NAME.json`` in `meshes_dir`.

    Args:
        name: the creature's name.
        meshes_dir: folder of the files; default `default_meshes_dir()` (`$ENERGYSIM_MESHES`, else the
            files shipped in the package).

    Raises:
        ValueError: unknown name, listing the shipped ones.
        MeshFileError: a missing file (then also a FileNotFoundError, naming the script that makes it),
            an unreadable or corrupt one, a JSON file with a missing or ill-typed key, or cell data that
            do not fit the mesh or the declared actuators; the message names the file and, for the
            JSON file, the key.
    """
    if name not in CREATURES:
        raise ValueError(f"unknown creature {name!r}; choose one of {', '.join(CREATURES)}")
    folder = default_meshes_dir() if meshes_dir is None else Path(meshes_dir)
    with local_files(folder, (f"{name}.vtu", f"{name}.json")) as (mesh_path, sidecar_path):
        return _read_creature(name, mesh_path, sidecar_path)


def _read_creature(name: str, mesh_path: Path, sidecar_path: Path) -> Creature:
    """`load_creature` once both files are on disk."""
    sidecar = read_creature_sidecar(sidecar_path)
    dim = sidecar.dim
    raw = read_meshio(mesh_path)
    cell_type = "tetra" if dim == 3 else "triangle"
    with reading(mesh_path):
        # No pruning: the cell data stay aligned with the elements, which pruning would keep anyway.
        vertices, elements = simplices_from_meshio(raw, cell_type, prune=False, source=f"the {dim}D creature")
        mesh = TetMesh(vertices, elements) if dim == 3 else TriMesh(vertices, elements)
    actuators, fibres = read_muscle_cell_data(
        raw, cell_type, mesh.num_elements, sidecar.num_actuators, dim, mesh_path, sidecar_path
    )
    low, high = mesh.bounding_box()
    return Creature(
        name=name,
        mesh=mesh,
        actuators=actuators,
        fibres=fibres,
        num_actuators=sidecar.num_actuators,
        body_length=float(high[0] - low[0]),
        description=sidecar.description,
        actuator_names=sidecar.actuator_names,
        gait_phases=sidecar.gait_phases,
        **sidecar.suggested,
    )


__all__ = ["load_creature"]
