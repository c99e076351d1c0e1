"""Build the shipped soft creatures from voxel designs and write them into the package data folder
energysim/assets/creatures/; the run checks itself.

    python scripts/make_creatures.py [--out energysim/assets/creatures] [--only worm quadruped ...]

Each creature is a set of occupied voxels (pixels in 2D) split into simplices (6 tets per cube, 2 triangles
per square). Every voxel carries an actuator index (−1: passive) and a rest fibre direction, which its
simplices inherit. Coordinates are in metres: x is forward, y is up, the lowest vertex lies at y = 0 and the
bounding box is centred on x = 0 (and z = 0 in 3D). Nothing here is random, so the files are reproducible.

For each creature NAME the script writes ``NAME.vtu`` (the mesh, with cell data ``actuator`` (int, −1 for
passive elements) and ``fibre`` (unit rest fibre, d components)) and ``NAME.json`` (description, suggested
material, muscle and open-loop gait), both atomically. `energysim.creatures.load_creature` reads them.

Gaits are a(t)_j = amplitude · sin(2π f t + φ_j) per actuator j; the numbers below are the defaults of the
walking scripts (``scripts/walk.py``, which adds the ground, friction and a ramp-in), tried there.

What must hold (`check`): every creature loads back with the arrays it was built from, has no degenerate or
inverted element, unit fibres, every actuator 0..a−1 drives at least one element, and its lowest vertex is at
y = 0.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import secrets
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from energysim.creatures import CREATURES, Creature, load_creature
from energysim.mesh import TetMesh, TriMesh, signed_volumes
from energysim.mesh.io import write_simplices

# the source tree's package data, which `load_creature` reads by default and wheels ship
MESHES = Path(__file__).resolve().parents[1] / "energysim" / "assets" / "creatures"
X, Y, Z = np.eye(3)


@dataclass(frozen=True)
class VoxelDesign:
    """A creature as voxels; grids are indexed `[i, j(, k)]` along (x, y(, z)).

    Attributes:
        occupancy: which voxels are solid, bool, shape `[nx, ny(, nz)]`.
        actuator: actuator index of each voxel, int, same shape; −1: passive.
        fibre: rest fibre direction of each voxel, shape `[nx, ny(, nz), d]` (unit where actuated).
        voxel_size: edge length of a voxel in m.
        metadata: what goes into the JSON sidecar (see `energysim.creatures.Creature`).
    """

    name: str
    occupancy: np.ndarray
    actuator: np.ndarray
    fibre: np.ndarray
    voxel_size: float
    metadata: dict = field(default_factory=dict)


@dataclass(frozen=True)
class CreatureArrays:
    """A built creature: positions `[n, d]` (m), elements `[m, d+1]`, actuators `[m]`, fibres `[m, d]`."""

    name: str
    vertices: np.ndarray
    elements: np.ndarray
    actuators: np.ndarray
    fibres: np.ndarray
    metadata: dict


def _empty(shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An empty design: no voxel, all passive, fibres along x (never read for passive voxels)."""
    dim = len(shape)
    fibre = np.zeros((*shape, dim))
    fibre[..., 0] = 1.0
    return np.zeros(shape, dtype=bool), np.full(shape, -1, dtype=np.int64), fibre


def _metadata(
    description: str,
    actuator_names: list[str],
    phases: list[float],
    *,
    frequency: float,
    youngs_modulus: float = 1e5,
    muscle_stiffness: float = 3e5,
    max_contraction: float = 0.3,
) -> dict:
    if len(phases) != len(actuator_names):
        raise ValueError(f"{len(phases)} gait phases for {len(actuator_names)} actuators")
    return {
        "description": description,
        "youngs_modulus": youngs_modulus,
        "poissons_ratio": 0.4,
        "density": 1000.0,
        "muscle_stiffness": muscle_stiffness,
        "max_contraction": max_contraction,
        "gait_frequency": frequency,
        "gait_amplitude": 1.0,
        "gait_phases": [round(phase % (2 * math.pi), 12) for phase in phases],
        "actuator_names": actuator_names,
    }


def worm() -> VoxelDesign:
    """A 0.30 m × 0.04 m × 0.04 m bar of 5 segments; bottom and top layers of each are x-fibre actuators."""
    segments, per_segment = 5, 3
    occupancy, actuator, fibre = _empty((segments * per_segment, 2, 2))
    occupancy[:] = True
    for segment in range(segments):
        cells = slice(segment * per_segment, (segment + 1) * per_segment)
        actuator[cells, 0] = 2 * segment  # bottom layer
        actuator[cells, 1] = 2 * segment + 1  # top layer
    names = [f"segment{s}_{layer}" for s in range(segments) for layer in ("bottom", "top")]
    # a bending wave running tail (x < 0) to head, one wavelength per body; top opposite to bottom
    phases = [-2 * math.pi * s / segments + math.pi * layer for s in range(segments) for layer in (0, 1)]
    description = (
        "peristaltic crawler: 5 segments along x (tail at -x), bottom/top layer of each one actuator "
        "(2s, 2s+1), fibres along x"
    )
    return VoxelDesign(
        "worm", occupancy, actuator, fibre, 0.02, _metadata(description, names, phases, frequency=1.5)
    )


def quadruped() -> VoxelDesign:
    """A 0.25 m body on four legs; each leg's front and back halves are vertical-fibre actuators."""
    occupancy, actuator, fibre = _empty((10, 5, 5))
    occupancy[:, 3:5, :] = True  # body
    legs = {"front_left": (8, 0), "front_right": (8, 3), "back_left": (0, 0), "back_right": (0, 3)}
    for leg, (x0, z0) in enumerate(legs.values()):
        occupancy[x0 : x0 + 2, 0:3, z0 : z0 + 2] = True
        actuator[x0 + 1, 0:3, z0 : z0 + 2] = 2 * leg  # front half (larger x)
        actuator[x0, 0:3, z0 : z0 + 2] = 2 * leg + 1  # back half
        fibre[x0 : x0 + 2, 0:3, z0 : z0 + 2] = Y
    names = [f"{leg}_{half}" for leg in legs for half in ("front", "back")]
    # front legs together, back legs a quarter period behind them; a leg's back half opposite its front
    # half. On a μ = 0.8 ground (scripts/walk.py --creature quadruped) this went forward at 3 Hz, but
    # swayed back by a tenth of its length in every stride; at 4 Hz it went faster (1.5 body lengths in
    # 2 s, within 10 % of that at h = 1/120 s) and swayed back a fifth as much. A trot (diagonal legs
    # together) and the back legs leading went backwards
    leg_phase = [0.0, 0.0, -math.pi / 2, -math.pi / 2]
    phases = [leg_phase[leg] + math.pi * half for leg in range(4) for half in (0, 1)]
    description = (
        "quadruped: 0.25 m body (y 0.075-0.125 m) on four 2x3x2-voxel legs; left is -z; each leg's front "
        "(+x) and back halves are actuators (2l, 2l+1) with vertical fibres, legs ordered " + ", ".join(legs)
    )
    metadata = _metadata(description, names, phases, frequency=4.0, youngs_modulus=2e5, muscle_stiffness=6e5)
    return VoxelDesign("quadruped", occupancy, actuator, fibre, 0.025, metadata)


def starfish() -> VoxelDesign:
    """A flat 0.29 m five-armed star; each arm's bottom and top layers are radial-fibre actuators."""
    size, voxel, arms = 19, 0.016, 5
    occupancy, actuator, fibre = _empty((size, 2, size))
    centre = np.arange(size) + 0.5 - size / 2  # voxel centres in voxel units, about the middle
    px, pz = np.meshgrid(centre, centre, indexing="ij")
    radius = np.hypot(px, pz)
    disc = radius < 3.6
    angles = 2 * math.pi * np.arange(arms) / arms  # arm 0 points forward (+x)
    # distance of each voxel centre from each arm's axis, and how far along the arm it lies
    along = px[..., None] * np.cos(angles) + pz[..., None] * np.sin(angles)
    across = np.abs(-px[..., None] * np.sin(angles) + pz[..., None] * np.cos(angles))
    half_width = 2.1 - 1.0 * np.clip(along / (size / 2), 0, 1)  # arms taper towards the tips
    in_arm = (along > 0) & (across < half_width) & (radius < size / 2)[..., None]
    arm_of = np.where(in_arm.any(axis=-1), np.argmin(np.where(in_arm, across, np.inf), axis=-1), -1)
    solid = disc | (arm_of >= 0)
    occupancy[:] = solid[:, None, :]
    for arm in range(arms):
        muscle = (arm_of == arm) & ~disc
        direction = np.cos(angles[arm]) * X + np.sin(angles[arm]) * Z
        for layer in (0, 1):
            actuator[:, layer, :][muscle] = 2 * arm + layer
            fibre[:, layer, :][muscle] = direction
    names = [f"arm{arm}_{layer}" for arm in range(arms) for layer in ("bottom", "top")]
    # the back arms (2, 3) push a quarter period after the side arms (1, 4), the front arm (0) in
    # opposition to the side arms; top opposite to bottom. In a short trial on a μ = 0.8 ground this
    # crept forward; a wave running round the arms went nowhere
    arm_phase = [math.pi, 0.0, -math.pi / 2, -math.pi / 2, 0.0]
    phases = [arm_phase[arm] + math.pi * layer for arm in range(arms) for layer in (0, 1)]
    description = (
        "starfish: flat 0.29 m five-armed star, 0.032 m thick; arm k points along angle 2 pi k / 5 from +x "
        "towards +z; its bottom/top layers are actuators (2k, 2k+1) with radial fibres; the disc is passive"
    )
    metadata = _metadata(description, names, phases, frequency=1.5)
    return VoxelDesign("starfish", occupancy, actuator, fibre, voxel, metadata)


def jumper() -> VoxelDesign:
    """A 0.20 m body on two thick legs (back, front) with strong vertical-fibre muscles."""
    occupancy, actuator, fibre = _empty((8, 5, 4))
    occupancy[:, 3:5, :] = True  # body
    for leg, cells in enumerate((slice(0, 3), slice(5, 8))):
        occupancy[cells, 0:3, :] = True
        actuator[cells, 0:3, :] = leg
        fibre[cells, 0:3, :] = Y
    names = ["back_leg", "front_leg"]
    # crouch (a > 0 shortens the legs) then kick (a < 0 lengthens them by c); the back leg leads
    phases = [0.0, -math.pi / 4]
    description = (
        "jumper: 0.20 m body on two 3x3x4-voxel legs with strong vertical fibres, actuator 0 the back leg, "
        "1 the front leg; a = -1 lengthens a leg by max_contraction"
    )
    metadata = _metadata(
        description, names, phases, frequency=1.0, muscle_stiffness=1e6, max_contraction=0.35
    )
    return VoxelDesign("jumper", occupancy, actuator, fibre, 0.025, metadata)


def crawler2d() -> VoxelDesign:
    """A 0.30 m × 0.048 m strip of 5 segments; bottom and top halves of each are x-fibre actuators."""
    segments, per_segment = 5, 5
    occupancy, actuator, fibre = _empty((segments * per_segment, 4))
    occupancy[:] = True
    for segment in range(segments):
        cells = slice(segment * per_segment, (segment + 1) * per_segment)
        actuator[cells, 0:2] = 2 * segment
        actuator[cells, 2:4] = 2 * segment + 1
    names = [f"segment{s}_{layer}" for s in range(segments) for layer in ("bottom", "top")]
    phases = [-2 * math.pi * s / segments + math.pi * layer for s in range(segments) for layer in (0, 1)]
    description = (
        "2D crawler: 5 segments along x (tail at -x), bottom/top halves of each one actuator (2s, 2s+1), "
        "fibres along x; plane strain, quantities per metre of depth"
    )
    return VoxelDesign(
        "crawler2d", occupancy, actuator, fibre, 0.012, _metadata(description, names, phases, frequency=1.5)
    )


def walker2d() -> VoxelDesign:
    """A 0.24 m body on a front and a back leg; each leg's front/back halves are vertical-fibre muscles."""
    occupancy, actuator, fibre = _empty((24, 12))
    occupancy[:, 6:12] = True  # body
    legs = {"front": 18, "back": 2}
    for leg, x0 in enumerate(legs.values()):
        occupancy[x0 : x0 + 4, 0:6] = True
        actuator[x0 + 2 : x0 + 4, 0:6] = 2 * leg  # front half (larger x)
        actuator[x0 : x0 + 2, 0:6] = 2 * leg + 1
        fibre[x0 : x0 + 4, 0:6] = Y[:2]
    names = [f"{leg}_leg_{half}" for leg in legs for half in ("front", "back")]
    # the back leg a quarter period behind the front one, a leg's halves in opposition, at 3 Hz: on a
    # μ = 0.8 ground (scripts/walk.py --creature walker2d) it walked forward at h = 1/60 and 1/120 s
    # alike. The back leg ahead walked forward at 2 Hz but rocked back by half its length in a stride, and
    # backwards at 3 Hz; faster gaits changed direction with the time step
    phases = [-math.pi / 2 * leg + math.pi * half for leg in range(2) for half in (0, 1)]
    description = (
        "2D walker: 0.24 m x 0.06 m body on a front and a back 0.04 m x 0.06 m leg; each leg's front (+x) "
        "and back halves are actuators (2l, 2l+1) with vertical fibres; plane strain, per metre of depth"
    )
    metadata = _metadata(description, names, phases, frequency=3.0)
    return VoxelDesign("walker2d", occupancy, actuator, fibre, 0.01, metadata)


DESIGNS: dict[str, Callable[[], VoxelDesign]] = {
    "worm": worm,
    "quadruped": quadruped,
    "starfish": starfish,
    "jumper": jumper,
    "crawler2d": crawler2d,
    "walker2d": walker2d,
}


def build_creature(design: VoxelDesign) -> CreatureArrays:
    """Mesh a design and give each simplex its voxel's actuator and fibre."""
    dim = design.occupancy.ndim
    if not design.occupancy[:, 0].any():
        raise ValueError(
            f"{design.name}: no voxel in the bottom layer, so the lowest vertex would not be at y = 0"
        )
    extent = np.array(design.occupancy.shape) * design.voxel_size
    origin = -extent / 2
    origin[1] = 0.0
    mesh_type = TetMesh if dim == 3 else TriMesh
    mesh = mesh_type.from_voxels(design.occupancy, design.voxel_size, tuple(origin))
    vertices, elements = mesh.vertices.numpy(), mesh.elements.numpy()
    # Centroids lie strictly inside their voxel, so this finds it whatever order the mesher uses.
    centroid = vertices[elements].mean(axis=1)
    cell = tuple(np.floor((centroid - origin) / design.voxel_size).astype(np.int64).T)
    if not design.occupancy[cell].all():
        raise ValueError(f"{design.name}: element centroids fall outside the occupied voxels")
    actuators = design.actuator[cell].astype(np.int64)
    fibres = design.fibre[cell].astype(np.float64)
    fibres = fibres / np.linalg.norm(fibres, axis=-1, keepdims=True)
    # centre the bounding box horizontally (the grid is centred, but a shape need not fill it)
    horizontal = [axis for axis in range(dim) if axis != 1]
    vertices = vertices.copy()
    vertices[:, horizontal] -= (vertices[:, horizontal].min(axis=0) + vertices[:, horizontal].max(axis=0)) / 2
    metadata = {"name": design.name, "dim": dim, "voxel_size": design.voxel_size, **design.metadata}
    metadata["num_actuators"] = int(actuators.max()) + 1
    return CreatureArrays(design.name, vertices, elements, actuators, fibres, metadata)


def _write_text_atomically(path: Path, text: str) -> None:
    # Same pattern as `write_simplices`: readers never see a half-written sidecar.
    tmp = path.parent / f".tmp-{secrets.token_hex(6)}-{path.name}"
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_creature(creature: CreatureArrays, out: Path) -> tuple[Path, Path]:
    """Write ``NAME.vtu`` and ``NAME.json`` into `out`; returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    mesh_path, sidecar_path = out / f"{creature.name}.vtu", out / f"{creature.name}.json"
    cell_type = "tetra" if creature.vertices.shape[1] == 3 else "triangle"
    write_simplices(
        mesh_path,
        torch.from_numpy(creature.vertices),
        torch.from_numpy(creature.elements),
        cell_type,
        cell_data={"actuator": creature.actuators, "fibre": creature.fibres},
    )
    _write_text_atomically(sidecar_path, json.dumps(creature.metadata, indent=2) + "\n")
    return mesh_path, sidecar_path


def check(built: CreatureArrays, loaded: Creature) -> None:
    """The file holds what was built, and the creature is sound."""
    name = built.name
    assert np.allclose(loaded.mesh.vertices.numpy(), built.vertices, rtol=0, atol=1e-12), name
    assert np.array_equal(loaded.mesh.elements.numpy(), built.elements), f"{name}: elements changed"
    assert np.array_equal(loaded.actuators.numpy(), built.actuators), f"{name}: actuators changed"
    assert np.allclose(loaded.fibres.numpy(), built.fibres, rtol=0, atol=1e-12), f"{name}: fibres changed"
    volume = signed_volumes(loaded.mesh.vertices, loaded.mesh.elements)
    expected = built.metadata["voxel_size"] ** loaded.dim / math.factorial(loaded.dim)
    assert torch.allclose(volume, torch.full_like(volume, expected), rtol=1e-9), f"{name}: distorted elements"
    assert abs(float(loaded.mesh.vertices[:, 1].min())) < 1e-15, f"{name}: lowest vertex not at y = 0"
    counts = torch.bincount(loaded.actuators[loaded.actuators >= 0], minlength=loaded.num_actuators)
    assert bool((counts > 0).all()), f"{name}: actuators {torch.nonzero(counts == 0).tolist()} drive nothing"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=MESHES, help="output folder")
    parser.add_argument(
        "--only", nargs="+", choices=CREATURES, default=list(CREATURES), help="creatures to build"
    )
    args = parser.parse_args(argv)
    for name in args.only:
        built = build_creature(DESIGNS[name]())
        mesh_path, _ = write_creature(built, args.out)
        loaded = load_creature(name, args.out)
        check(built, loaded)
        print(
            f"{name:10s} {loaded.dim}D  {loaded.mesh.num_vertices:5d} vertices  "
            f"{loaded.mesh.num_elements:5d} elements  {loaded.num_actuators:2d} actuators  "
            f"body length {loaded.body_length:.3f} m  "
            f"{mesh_path.stat().st_size / 1024:.0f} KiB -> {mesh_path}"
        )


if __name__ == "__main__":
    main()
