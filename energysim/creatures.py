"""The shipped soft creatures: voxel bodies with fibre muscles, read from the package data in
energysim/assets/creatures/.

`scripts/make_creatures.py` makes every creature NAME as ``NAME.vtu`` (the rest mesh, x forward, y up, the
lowest vertex at y = 0, with cell data ``actuator`` (−1 passive) and ``fibre``) beside ``NAME.json`` (a
description, the suggested material, muscle and open-loop gait). `load_creature` reads them back through
`importlib.resources`, so they load from a source tree, an installed wheel and a zipped package alike.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from importlib.resources import as_file, files
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Any

import meshio
import numpy as np
import torch
from torch import Tensor

from energysim.contact import Ground
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.energies.neo_hookean import NeoHookean
from energysim.mesh import SimplexMesh, TetMesh, TriMesh
from energysim.mesh.io import (
    MeshFileError,
    MeshFileNotFoundError,
    read_meshio,
    reading,
    simplices_from_meshio,
)
from energysim.model.scene import Scene
from energysim.solvers import Solver

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

CREATURES = ("worm", "quadruped", "starfish", "jumper", "crawler2d", "walker2d")
MESHES_ENV = "ENERGYSIM_MESHES"
# the shipped files: package data of `energysim`, declared in pyproject.toml
ASSETS_PACKAGE = "energysim"
ASSETS_FOLDER = ("assets", "creatures")
MAKE_SCRIPT = "scripts/make_creatures.py"
STANDARD_GRAVITY = 9.81  # m/s², the creatures' scenes pull along −y


@dataclass(frozen=True, eq=False)
class Creature:
    """A soft creature at rest, with its muscles and suggested numbers.

    Attributes:
        name: one of `CREATURES`.
        mesh: rest mesh (`TetMesh` in 3D, `TriMesh` in 2D), in m; x forward, y up, lowest vertex at y = 0.
        actuators: actuator of each element, int64, shape `[m]`; −1: passive.
        fibres: unit rest fibre direction of each element, float64, shape `[m, d]`.
        num_actuators: a, the length of the action the creature's muscles read.
        body_length: extent of the rest mesh along x, in m.
        description: what the creature is and how its actuators are laid out.
        actuator_names: a name per actuator, a of them.
        youngs_modulus: suggested E of the body in Pa.
        poissons_ratio: suggested ν.
        density: suggested ρ in kg/m³ (kg/m² per metre of depth in 2D).
        muscle_stiffness: suggested active fibre stiffness k in Pa.
        max_contraction: suggested c in (0, 1): full activation asks for fibre stretch 1 − c.
        gait_frequency: suggested open-loop gait frequency f in Hz.
        gait_amplitude: suggested activation amplitude, in [0, 1].
        gait_phases: suggested phase φ_j of each actuator, in rad.
    """

    name: str
    mesh: SimplexMesh
    actuators: Tensor
    fibres: Tensor
    num_actuators: int
    body_length: float
    description: str
    actuator_names: tuple[str, ...]
    youngs_modulus: float
    poissons_ratio: float
    density: float
    muscle_stiffness: float
    max_contraction: float
    gait_frequency: float
    gait_amplitude: float
    gait_phases: tuple[float, ...]

    @property
    def dim(self) -> int:
        """Spatial dimension d (2 or 3)."""
        return self.mesh.dim

    def muscles(
        self, stiffness: float | Tensor | None = None, max_contraction: float | None = None
    ) -> FibreMuscles:
        """The creature's `FibreMuscles` term; stiffness (Pa) and c default to the suggested ones."""
        return FibreMuscles(
            self.fibres,
            self.actuators,
            stiffness=self.muscle_stiffness if stiffness is None else stiffness,
            max_contraction=self.max_contraction if max_contraction is None else max_contraction,
        )

    def gait_action(self, time: float | Tensor) -> Tensor:
        """The suggested open-loop action A sin(2π f t + φ_j), shape `[a]` (or `[T, a]` for times `[T]`).

        Args:
            time: t in s, a number or shape `[T]`.
        """
        t = torch.as_tensor(time, dtype=torch.float64)
        phases = torch.tensor(self.gait_phases, dtype=torch.float64)
        return self.gait_amplitude * torch.sin(2 * math.pi * self.gait_frequency * t[..., None] + phases)

    def scene(self, dt: float = 1 / 60, friction: float = 0.8, solver: Solver | None = None) -> Scene:
        """The creature on level ground: its suggested material and muscles, gravity along −y and an
        IPC ground at y = 0 with lagged Coulomb friction μ.

        Terms, in order: gravity (9.81 m/s² along −y), `NeoHookean` (E, ν), `muscles()`, `Ground`.

        Args:
            dt: time step h in s, > 0.
            friction: Coulomb coefficient μ of the ground, ≥ 0.
            solver: the scene's optimizer; default the `Scene` default.
        """
        up = (0.0, 1.0, 0.0) if self.dim == 3 else (0.0, 1.0)
        scene = Scene(
            self.mesh,
            density=self.density,
            dt=dt,
            gravity=tuple(-STANDARD_GRAVITY * u for u in up),
            solver=solver,
        )
        scene.add(NeoHookean(self.youngs_modulus, self.poissons_ratio))
        scene.add(self.muscles())
        scene.add(Ground(0.0, normal=up, friction=friction))
        return scene


def scene_ground(scene: Scene) -> Ground:
    """The scene's one `Ground` term; ValueError when it has none or several."""
    grounds = [term for term in scene.terms if isinstance(term, Ground)]
    if len(grounds) != 1:
        raise ValueError(f"expected one Ground term in the scene, found {len(grounds)}")
    return grounds[0]


def resting_state(
    scene: Scene, positions: Tensor | None = None, velocities: Tensor | None = None
) -> Tensor:
    """A state that starts in contact with the ground, outside it: `positions` moved along the ground's
    normal until the lowest vertex is half the barrier distance d̂ above it.

    With the rest positions (lowest vertex on the ground) that is the rest shape lifted by d̂/2: inside
    the barrier's reach, so the creature rests on the ground from the first step instead of falling
    onto it.

    Args:
        scene: a scene with one `Ground` term (e.g. from `Creature.scene`).
        positions: shape `[n, d]` or `[B, n, d]`, in m; default the rest positions.
        velocities: same shape, in m/s; default zero.

    Returns:
        the state, shape `[2·n·d]` (or `[B, 2·n·d]` for batched positions).
    """
    ground = scene_ground(scene)
    x = scene.rest_positions if positions is None else torch.as_tensor(positions).to(scene.rest_positions)
    n, d = scene.num_vertices, scene.dim
    if tuple(x.shape[-2:]) != (n, d) or x.ndim not in (2, 3):
        raise ValueError(f"positions must have shape [{n}, {d}] or [B, {n}, {d}], got {list(x.shape)}")
    v = torch.zeros_like(x) if velocities is None else torch.as_tensor(velocities).to(x)
    if v.shape != x.shape:
        raise ValueError(f"velocities must have the shape of positions {list(x.shape)}, got {list(v.shape)}")
    lowest = ground.signed_distance(x).amin(dim=-1)
    lift = 0.5 * ground.barrier_distance - lowest
    x = x + lift[..., None, None] * ground.normal.to(x)
    return torch.cat([x.flatten(-2), v.flatten(-2)], dim=-1)


def shipped_meshes_dir() -> Traversable:
    """The shipped creature files, energysim/assets/creatures/ in the package (a `pathlib.Path` unless the
    package is imported from a zip archive)."""
    folder = files(ASSETS_PACKAGE)
    for part in ASSETS_FOLDER:
        folder = folder.joinpath(part)
    return folder


def default_meshes_dir() -> Path | Traversable:
    """Where `load_creature` looks by default: `$ENERGYSIM_MESHES` if set, else `shipped_meshes_dir()`."""
    override = os.environ.get(MESHES_ENV)
    if override:
        return Path(override)
    return shipped_meshes_dir()


@contextmanager
def _local_files(folder: Path | Traversable, names: tuple[str, ...]) -> Iterator[tuple[Path, ...]]:
    """Paths on disk for the files `names` in `folder`: the files themselves in a folder on disk, temporary
    copies inside a zip archive (removed on exit). MeshFileNotFoundError for the first one missing."""
    with ExitStack() as stack:
        paths = []
        for name in names:
            resource = folder.joinpath(name)
            if not (resource.is_file() or resource.is_dir()):
                shown = resource if isinstance(resource, Path) else str(resource)
                raise MeshFileNotFoundError(
                    shown, f"creature file not found; make it with `python {MAKE_SCRIPT}`"
                )
            paths.append(Path(stack.enter_context(as_file(resource))))
        yield tuple(paths)


def _describe(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:60] + "..."


def _read_sidecar(path: Path) -> dict[str, Any]:
    """The JSON object in `path`; MeshFileError naming `path` when it is not UTF-8 JSON holding an object."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise MeshFileError(
            path, f"cannot be read as UTF-8 text ({type(error).__name__}: {error})"
        ) from error
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise MeshFileError(
            path, f"is not valid JSON ({error.msg} at line {error.lineno}, column {error.colno})"
        ) from error
    except RecursionError as error:
        raise MeshFileError(path, "is not valid JSON (nested too deeply)") from error
    if not isinstance(data, dict):
        raise MeshFileError(path, f"must hold a JSON object, got {type(data).__name__}")
    return data


def _entry(data: dict[str, Any], key: str, path: Path, expected: str) -> Any:
    if key not in data:
        raise MeshFileError(path, f"missing key {key!r} ({expected}); rebuild it with {MAKE_SCRIPT}")
    return data[key]


def _is_number(value: object) -> bool:
    # bool is an int in Python, but `true` is no number in a JSON file.
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _number(
    data: dict[str, Any], key: str, path: Path, expected: str, valid: Callable[[float], bool]
) -> float:
    value = _entry(data, key, path, expected)
    if not (_is_number(value) and valid(float(value))):
        raise MeshFileError(path, f"key {key!r} must be {expected}, got {_describe(value)}")
    return float(value)


def _integer(data: dict[str, Any], key: str, path: Path, expected: str, valid: Callable[[int], bool]) -> int:
    value = _entry(data, key, path, expected)
    if not (isinstance(value, int) and not isinstance(value, bool) and valid(value)):
        raise MeshFileError(path, f"key {key!r} must be {expected}, got {_describe(value)}")
    return value


def _sequence(
    data: dict[str, Any], key: str, path: Path, length: int, item: str, valid: Callable[[object], bool]
) -> list[Any]:
    expected = f"a list of {length} {item}"
    value = _entry(data, key, path, expected)
    if not isinstance(value, list) or len(value) != length:
        raise MeshFileError(path, f"key {key!r} must be {expected}, got {_describe(value)}")
    bad = [index for index, entry in enumerate(value) if not valid(entry)]
    if bad:
        raise MeshFileError(
            path,
            f"key {key!r} must be {expected}; entries {bad[:10]} are not, e.g. {_describe(value[bad[0]])}",
        )
    return value


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
    with _local_files(folder, (f"{name}.vtu", f"{name}.json")) as (mesh_path, sidecar_path):
        return _read_creature(name, mesh_path, sidecar_path)


def _read_creature(name: str, mesh_path: Path, sidecar_path: Path) -> Creature:
    """`load_creature` once both files are on disk."""
    metadata = _read_sidecar(sidecar_path)
    dim = _integer(metadata, "dim", sidecar_path, "2 or 3", lambda d: d in (2, 3))
    num_actuators = _integer(metadata, "num_actuators", sidecar_path, "an integer >= 1", lambda a: a >= 1)
    phases = _sequence(
        metadata, "gait_phases", sidecar_path, num_actuators, "finite numbers (rad)", _is_number
    )
    names = _sequence(
        metadata, "actuator_names", sidecar_path, num_actuators, "strings", lambda v: isinstance(v, str)
    )
    description = _entry(metadata, "description", sidecar_path, "a string")
    if not isinstance(description, str):
        raise MeshFileError(sidecar_path, f"key 'description' must be a string, got {_describe(description)}")
    numbers = {
        key: _number(metadata, key, sidecar_path, expected, valid)
        for key, expected, valid in (
            ("youngs_modulus", "a number > 0 (Pa)", lambda v: v > 0),
            ("poissons_ratio", "a number in (-1, 0.5)", lambda v: -1 < v < 0.5),
            ("density", "a number > 0 (kg/m^3)", lambda v: v > 0),
            ("muscle_stiffness", "a number >= 0 (Pa)", lambda v: v >= 0),
            ("max_contraction", "a number in (0, 1)", lambda v: 0 < v < 1),
            ("gait_frequency", "a number >= 0 (Hz)", lambda v: v >= 0),
            ("gait_amplitude", "a number in [0, 1]", lambda v: 0 <= v <= 1),
        )
    }

    raw = read_meshio(mesh_path)
    cell_type = "tetra" if dim == 3 else "triangle"
    with reading(mesh_path):
        # No pruning: the cell data stay aligned with the elements, which pruning would keep anyway.
        vertices, elements = simplices_from_meshio(raw, cell_type, prune=False, source=f"the {dim}D creature")
        mesh = TetMesh(vertices, elements) if dim == 3 else TriMesh(vertices, elements)
    actuator_data = _cell_data(raw, "actuator", cell_type, mesh_path)
    if actuator_data.shape[0] != mesh.num_elements:
        raise MeshFileError(
            mesh_path,
            f"'actuator' cell data has {actuator_data.shape[0]} entries for {mesh.num_elements} elements",
        )
    actuators = _actuators(actuator_data, num_actuators, mesh_path, sidecar_path)
    fibres = _fibres(_cell_data(raw, "fibre", cell_type, mesh_path), actuators, dim, mesh_path)
    low, high = mesh.bounding_box()
    return Creature(
        name=name,
        mesh=mesh,
        actuators=actuators,
        fibres=fibres,
        num_actuators=num_actuators,
        body_length=float(high[0] - low[0]),
        description=description,
        actuator_names=tuple(names),
        gait_phases=tuple(float(phase) for phase in phases),
        **numbers,
    )


__all__ = [
    "CREATURES",
    "Creature",
    "default_meshes_dir",
    "load_creature",
    "resting_state",
    "scene_ground",
    "shipped_meshes_dir",
]
