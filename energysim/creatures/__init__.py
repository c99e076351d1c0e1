"""The shipped soft creatures: voxel bodies with fibre muscles, read from the package data in
energysim/assets/creatures/.

`scripts/make_creatures.py` makes every creature NAME as ``NAME.vtu`` (the rest mesh, x forward, y up, the
lowest vertex at y = 0, with cell data ``actuator`` (−1 passive) and ``fibre``) beside ``NAME.json`` (a
description, the suggested material, muscle and open-loop gait). `load_creature` reads them back through
`importlib.resources`, so they load from a source tree, an installed wheel and a zipped package alike.

Modules: `creature` (the `Creature` record, its muscles, gait and scene), `shipped_files` (the names and
where the files are), `sidecar` and `cell_data` (reading and checking the two files), `loading`
(`load_creature`), `resting` (a start in contact with the ground).
"""

from energysim.creatures.creature import STANDARD_GRAVITY, Creature
from energysim.creatures.loading import load_creature
from energysim.creatures.resting import resting_state, scene_ground
from energysim.creatures.shipped_files import (
    ASSETS_FOLDER,
    ASSETS_PACKAGE,
    CREATURES,
    MAKE_SCRIPT,
    MESHES_ENV,
    default_meshes_dir,
    shipped_meshes_dir,
)

__all__ = [
    "ASSETS_FOLDER",
    "ASSETS_PACKAGE",
    "CREATURES",
    "MAKE_SCRIPT",
    "MESHES_ENV",
    "STANDARD_GRAVITY",
    "Creature",
    "default_meshes_dir",
    "load_creature",
    "resting_state",
    "scene_ground",
    "shipped_meshes_dir",
]
