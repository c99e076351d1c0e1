"""The shipped soft creatures: voxel bodies with fibre muscles, read from meshes/.

`scripts/make_creatures.py` makes every creature NAME as ``NAME.vtu`` (the rest mesh, x forward, y up, the
lowest vertex at y = 0, with cell data ``actuator`` (−1 passive) and ``fibre``) beside ``NAME.json`` (a
description, the suggested material, muscle and open-loop gait). `load_creature` reads them back.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import meshio
import numpy as np
import torch
from torch import Tensor

from energysim.contact import Ground
from energysim.energies.fibre_muscles import FibreMuscles
from energysim.energies.neo_hookean import NeoHookean
from energysim.mesh import SimplexMesh, TetMesh, TriMesh
from energysim.mesh.io import read_meshio, simplices_from_meshio
from energysim.optim import Solver
from energysim.scene import Scene

CREATURES = ("worm", "quadruped", "starfish", "jumper", "crawler2d", "walker2d")
MESHES_ENV = "ENERGYSIM_MESHES"
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


def default_meshes_dir() -> Path:
    """Where creature files live: `$ENERGYSIM_MESHES` if set, else meshes/ at the repository root."""
    override = os.environ.get(MESHES_ENV)
    if override:
        return Path(override)
    return Path(__file__).resolve().parent.parent / "meshes"


def _cell_data(mesh: meshio.Mesh, name: str, cell_type: str, path: Path) -> np.ndarray:
    arrays = mesh.cell_data.get(name, [])
    if len(arrays) != len(mesh.cells):
        raise ValueError(f"{path} has no {name!r} cell data; rebuild it with {MAKE_SCRIPT}")
    blocks = [
        np.asarray(data) for block, data in zip(mesh.cells, arrays, strict=True) if block.type == cell_type
    ]
    if not blocks:
        raise ValueError(f"{path} has no {name!r} cell data; rebuild it with {MAKE_SCRIPT}")
    return np.concatenate(blocks)


def load_creature(name: str, meshes_dir: str | PathLike[str] | None = None) -> Creature:
    """Read creature `name` (see `CREATURES`) from ``NAME.vtu`` and ``NAME.json`` in `meshes_dir`.

    Args:
        name: the creature's name.
        meshes_dir: folder of the files; default `default_meshes_dir()`.

    Raises:
        ValueError: unknown name, or a file whose arrays do not fit its mesh.
        FileNotFoundError: a missing file, naming its path and the script that makes it.
    """
    if name not in CREATURES:
        raise ValueError(f"unknown creature {name!r}; choose one of {CREATURES}")
    folder = default_meshes_dir() if meshes_dir is None else Path(meshes_dir)
    mesh_path, sidecar_path = folder / f"{name}.vtu", folder / f"{name}.json"
    for path in (mesh_path, sidecar_path):
        if not path.is_file():
            raise FileNotFoundError(f"creature file {path} not found; make it with `python {MAKE_SCRIPT}`")
    metadata = json.loads(sidecar_path.read_text())
    raw = read_meshio(mesh_path)
    dim = int(metadata["dim"])
    cell_type = "tetra" if dim == 3 else "triangle"
    # No pruning: the cell data stay aligned with the elements, which pruning would keep anyway.
    vertices, elements = simplices_from_meshio(raw, cell_type, prune=False, source=str(mesh_path))
    mesh = TetMesh(vertices, elements) if dim == 3 else TriMesh(vertices, elements)
    actuators = torch.from_numpy(_cell_data(raw, "actuator", cell_type, mesh_path).astype(np.int64))
    fibres = torch.from_numpy(_cell_data(raw, "fibre", cell_type, mesh_path).astype(np.float64))
    count = mesh.num_elements
    if tuple(actuators.shape) != (count,) or tuple(fibres.shape) != (count, dim):
        raise ValueError(
            f"{mesh_path}: actuator {tuple(actuators.shape)} and fibre {tuple(fibres.shape)} cell data "
            f"do not fit {count} elements in {dim}D"
        )
    num_actuators = int(metadata["num_actuators"])
    phases = tuple(float(phase) for phase in metadata["gait_phases"])
    if int(actuators.max()) + 1 != num_actuators or len(phases) != num_actuators:
        raise ValueError(
            f"{sidecar_path} declares {num_actuators} actuators with {len(phases)} gait phases; "
            f"the mesh uses {int(actuators.max()) + 1}"
        )
    low, high = mesh.bounding_box()
    return Creature(
        name=name,
        mesh=mesh,
        actuators=actuators,
        fibres=fibres,
        num_actuators=num_actuators,
        body_length=float(high[0] - low[0]),
        description=str(metadata["description"]),
        actuator_names=tuple(metadata["actuator_names"]),
        youngs_modulus=float(metadata["youngs_modulus"]),
        poissons_ratio=float(metadata["poissons_ratio"]),
        density=float(metadata["density"]),
        muscle_stiffness=float(metadata["muscle_stiffness"]),
        max_contraction=float(metadata["max_contraction"]),
        gait_frequency=float(metadata["gait_frequency"]),
        gait_amplitude=float(metadata["gait_amplitude"]),
        gait_phases=phases,
    )


__all__ = ["CREATURES", "Creature", "default_meshes_dir", "load_creature", "resting_state", "scene_ground"]
