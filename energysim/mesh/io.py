"""Mesh files through meshio: reading simplex cells out of any format, and atomic writes.

Every failure to read a file, from a missing path to a corrupt payload or contents that do not make a
valid mesh, is raised as one `MeshFileError` that names the file and says what is wrong, chained to the
error underneath. meshio ends the process (`sys.exit`) on some unreadable files; `read_meshio` calls
its readers so that this never escapes.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator, Mapping
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Any

import meshio
import numpy as np
import torch

from .tags import MeshTags, mesh_tags

if TYPE_CHECKING:
    from .simplex import SimplexMesh

# Longest excerpt of an underlying error message quoted in a MeshFileError.
_MAX_DETAIL = 200


class MeshFileError(ValueError):
    """A mesh file, or a file describing a mesh (a creature's JSON), that cannot be used.

    Raised for a missing path, a directory, an unknown extension, an empty, truncated or corrupt file,
    and for contents that do not make a valid mesh (no simplices, non-finite coordinates, indices out of
    range, repeated, overlapping or degenerate elements, missing or ill-typed keys). `path` is the file;
    `problem` says what is wrong; the message is ``"{path}: {problem}"``. The error underneath, if any,
    is chained as `__cause__`.
    """

    def __init__(self, path: str | PathLike[str], problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")

    def __reduce__(self) -> tuple[Any, ...]:
        return type(self), (self.path, self.problem)


class MeshFileNotFoundError(MeshFileError, FileNotFoundError):
    """A `MeshFileError` for a path where there is no file; also a `FileNotFoundError`."""


def _numpy(value: Any) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def _excerpt(error: BaseException) -> str:
    if isinstance(error, SystemExit):
        return "meshio could not parse it"
    text = " ".join(str(error).split())
    if not text and error.__context__ is not None:
        # meshio's vtu reader raises a bare ReadError while handling the XML parser's error.
        return _excerpt(error.__context__)
    text = text or "no details"
    if len(text) > _MAX_DETAIL:
        text = text[:_MAX_DETAIL] + "..."
    module = type(error).__module__.split(".")[0]
    # zlib.error and binascii.Error say little without their module.
    kind = type(error).__name__ if module in ("builtins", "meshio") else f"{module}.{type(error).__name__}"
    return f"{kind}: {text}"


def mesh_formats(path: str | PathLike[str]) -> list[str]:
    """The meshio formats the extension of `path` names (e.g. ``[".msh"] -> ["ansys", "gmsh"]``).

    Raises MeshFileError naming `path` if meshio knows no format for its extension.
    """
    path = Path(path)
    formats: list[str] = []
    extension = ""
    for suffix in reversed(path.suffixes):
        extension = (suffix + extension).lower()
        formats += meshio.extension_to_filetypes.get(extension, [])
    if not formats:
        raise MeshFileError(
            path,
            f"unknown mesh file extension {path.suffix or '(none)'!r}; "
            "use one meshio reads, e.g. .vtu, .vtk, .msh (gmsh) or .mesh (medit)",
        )
    return formats


def _read_as(path: Path, file_format: str) -> meshio.Mesh:
    # The format's own reader raises on bad input; meshio.read would print and call sys.exit instead.
    reader = getattr(getattr(meshio, "_helpers", None), "reader_map", {}).get(file_format)
    if reader is not None:
        return reader(str(path))
    return meshio.read(path, file_format=file_format)


def read_meshio(path: str | PathLike[str]) -> meshio.Mesh:
    """Read any meshio-supported file.

    Raises:
        MeshFileNotFoundError: nothing at `path` (also a FileNotFoundError).
        MeshFileError: `path` is a directory, has an unknown extension, is empty, or cannot be parsed
            (truncated, corrupt, wrong format); the message names `path` and each reader's complaint.
    """
    path = Path(path)
    if not path.exists():
        raise MeshFileNotFoundError(path, "no such mesh file")
    if not path.is_file():
        raise MeshFileError(path, "is not a regular file (a directory?); expected a mesh file")
    formats = mesh_formats(path)
    try:
        size = path.stat().st_size
    except OSError as error:
        raise MeshFileError(path, f"cannot be read ({_excerpt(error)})") from error
    if size == 0:
        raise MeshFileError(path, "is empty (0 bytes); expected a mesh file")
    failures: list[tuple[str, BaseException]] = []
    for file_format in formats:
        try:
            mesh = _read_as(path, file_format)
        except (Exception, SystemExit) as error:  # noqa: BLE001 - every parse failure becomes one error
            failures.append((file_format, error))
            continue
        if not isinstance(mesh, meshio.Mesh):
            raise MeshFileError(path, f"the {file_format} reader returned {type(mesh).__name__}, not a mesh")
        return mesh
    details = "; ".join(f"as {file_format}: {_excerpt(error)}" for file_format, error in failures)
    raise MeshFileError(
        path, f"is not a readable {' or '.join(formats)} file (truncated or corrupt?): {details}"
    ) from failures[-1][1]


@contextlib.contextmanager
def reading(path: str | PathLike[str]) -> Iterator[None]:
    """Turn any ValueError raised inside the block into a MeshFileError naming `path` (chained).

    Wrap the step from a file's arrays to a validated mesh, so that its errors (indices out of range,
    repeated or degenerate elements, ...) say which file they come from.
    """
    try:
        yield
    except MeshFileError:
        raise
    except (ValueError, IndexError, KeyError, TypeError) as error:
        raise MeshFileError(path, str(error) if isinstance(error, ValueError) else _excerpt(error)) from error


def _format_rows(rows: np.ndarray, limit: int = 10) -> str:
    values = rows.tolist()
    text = "[" + ", ".join(str(int(v)) for v in values[:limit]) + "]"
    return text + (f" and {len(values) - limit} more" if len(values) > limit else "")


def simplices_from_meshio(
    mesh: meshio.Mesh, cell_type: str, prune: bool = True, source: str = "mesh"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Concatenate all `cell_type` blocks ("tetra" or "triangle") of a meshio mesh, ignoring other cells.

    Returns `(vertices, elements)`: positions, shape `[n, 3]` (or `[n, 2]` if the file is planar), float64,
    in the file's units (m expected), and indices, shape `[m, 4]` or `[m, 3]`, int64. With `prune`, vertices
    no element uses are dropped and the elements renumbered. Raises ValueError naming `source` if there
    is no `cell_type` cell, if points are not finite (naming the file's point indices) or if an element
    references a point that does not exist (naming the element indices, counted over the `cell_type`
    blocks in file order).
    """
    corners = {"tetra": 4, "triangle": 3}[cell_type]
    blocks = [np.asarray(block.data) for block in mesh.cells if block.type == cell_type]
    if not blocks or sum(b.shape[0] for b in blocks) == 0:
        found = sorted({block.type for block in mesh.cells})
        raise ValueError(f"{source} has no {cell_type!r} cells (found cell types {found})")
    for block in blocks:
        if block.ndim != 2 or block.shape[1] != corners or not np.issubdtype(block.dtype, np.integer):
            raise ValueError(
                f"{source} has a {cell_type!r} block of shape {block.shape} and dtype {block.dtype}; "
                f"expected integer indices of shape [m, {corners}]"
            )
    elements = np.concatenate(blocks).astype(np.int64)
    vertices = np.asarray(mesh.points)
    if vertices.ndim != 2 or vertices.shape[1] not in (2, 3) or not np.issubdtype(vertices.dtype, np.number):
        raise ValueError(f"{source} has points of shape {vertices.shape}; expected [n, 2] or [n, 3]")
    vertices = vertices.astype(np.float64)
    n = vertices.shape[0]
    outside = np.flatnonzero(((elements < 0) | (elements >= n)).any(axis=1))
    if outside.size:
        raise ValueError(
            f"{source}: {cell_type} cells {_format_rows(outside)} reference point indices outside "
            f"[0, {n}) ({n} points)"
        )
    used, inverse = np.unique(elements, return_inverse=True)
    bad = used[~np.isfinite(vertices[used]).all(axis=1)]
    if bad.size:
        raise ValueError(f"{source}: points {_format_rows(bad)} have NaN or infinite coordinates")
    if prune:
        # Files often carry geometry points or lower-dimensional cells' vertices that no simplex uses.
        vertices = vertices[used]
        elements = inverse.reshape(elements.shape)
    return torch.from_numpy(np.ascontiguousarray(vertices)), torch.from_numpy(np.ascontiguousarray(elements))


def read_simplices(
    path: str | PathLike[str], cell_type: str, prune: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Read the `cell_type` cells of the file at `path`; see `simplices_from_meshio` for the result.

    Every failure is a MeshFileError naming `path` (see `read_meshio`).
    """
    mesh = read_meshio(path)
    with reading(path):
        return simplices_from_meshio(mesh, cell_type, prune, source="the file")


def read_tagged_simplices(
    path: str | PathLike[str], cell_type: str, prune: bool = True
) -> tuple[torch.Tensor, torch.Tensor, MeshTags]:
    """`read_simplices` and the file's vertex sets, element sets and cell data (`energysim.mesh.tags`),
    numbered like the returned vertices and elements. Every failure is a MeshFileError naming `path`."""
    mesh = read_meshio(path)
    with reading(path):
        vertices, elements = simplices_from_meshio(mesh, cell_type, prune, source="the file")
        return vertices, elements, mesh_tags(mesh, cell_type, prune, source="the file")


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
    """Load a TetMesh if the file at `path` has "tetra" cells, else a TriMesh if it has "triangle" cells.

    The mesh keeps the file's vertex sets, element sets and cell data (`energysim.mesh.tags`).

    Every failure (see `read_meshio`), and contents that do not make a valid mesh, raise a MeshFileError
    naming `path`.
    """
    # Imported here because simplex.py imports this module for TetMesh.load / SimplexMesh.save.
    from .simplex import TetMesh, TriMesh

    mesh = read_meshio(path)
    cell_types = {block.type for block in mesh.cells}
    with reading(path):
        for cell_type, kind in (("tetra", TetMesh), ("triangle", TriMesh)):
            if cell_type in cell_types:
                vertices, elements = simplices_from_meshio(mesh, cell_type, prune, source="the file")
                tags = mesh_tags(mesh, cell_type, prune, source="the file")
                return kind(vertices, elements, **tags._asdict())
    raise MeshFileError(path, f"has neither tetra nor triangle cells (found cell types {sorted(cell_types)})")


__all__ = [
    "MeshFileError",
    "MeshFileNotFoundError",
    "load_mesh",
    "mesh_formats",
    "read_meshio",
    "read_simplices",
    "read_tagged_simplices",
    "reading",
    "simplices_from_meshio",
    "write_simplices",
]
