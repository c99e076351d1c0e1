"""Where the creature files are: the names of the shipped creatures, the package data folder
energysim/assets/creatures/ (through `importlib.resources`, so it is found in a source tree, an
installed wheel and a zipped package alike), the `$ENERGYSIM_MESHES` override, and local paths on
disk for files inside a zip archive.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from importlib.resources import as_file, files
from pathlib import Path
from typing import TYPE_CHECKING

from energysim.mesh.io import MeshFileNotFoundError

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

CREATURES = ("worm", "quadruped", "starfish", "jumper", "crawler2d", "walker2d")
MESHES_ENV = "ENERGYSIM_MESHES"
# the shipped files: package data of `energysim`, declared in pyproject.toml
ASSETS_PACKAGE = "energysim"
ASSETS_FOLDER = ("assets", "creatures")
MAKE_SCRIPT = "scripts/make_creatures.py"


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
def local_files(folder: Path | Traversable, names: tuple[str, ...]) -> Iterator[tuple[Path, ...]]:
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


__all__ = [
    "ASSETS_FOLDER",
    "ASSETS_PACKAGE",
    "CREATURES",
    "MAKE_SCRIPT",
    "MESHES_ENV",
    "default_meshes_dir",
    "local_files",
    "shipped_meshes_dir",
]
