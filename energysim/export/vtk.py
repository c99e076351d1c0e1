"""VTK output: single ``.vtu`` files and ``.pvd`` collections for ParaView / pyvista.

Every file is written atomically (temporary file in the same folder, flushed, then :func:`os.replace`,
then the folder flushed), so a crash mid-write leaves either the previous file or no file at the
destination, never a truncated one. Inputs may be torch tensors or numpy arrays; this module never
imports the solver. Time series that replace an older one whole are in `energysim.export.series`.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import meshio
import numpy as np

logger = logging.getLogger(__name__)

_CELL_TYPES = {3: "triangle", 4: "tetra"}

# mkstemp creates files with mode 0600; read the umask once (os.umask is process-global and racy)
# so that atomically written files get the same permissions as a plain open() would give them.
_UMASK = os.umask(0)
os.umask(_UMASK)


def to_numpy(x: Any, name: str = "array") -> np.ndarray:
    """Return ``x`` (torch tensor, numpy array or nested sequence) as a numpy array, detached and on CPU."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} could not be converted to an array: {err}") from err


def check_vertices(vertices: Any, name: str = "vertices") -> np.ndarray:
    """Validate vertex positions `[n, 2]` or `[n, 3]` and return them as float64 `[n, 3]` (2D: z = 0)."""
    v = to_numpy(vertices, name)
    if v.ndim != 2 or v.shape[1] not in (2, 3):
        raise ValueError(f"{name} must have shape [n, 2] or [n, 3], got {list(v.shape)}")
    if v.shape[0] == 0:
        raise ValueError(f"{name} is empty (n = 0)")
    if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
        raise ValueError(f"{name} must be numeric, got dtype {v.dtype}")
    v = v.astype(np.float64)
    if not np.all(np.isfinite(v)):
        bad = int(np.count_nonzero(~np.isfinite(v).all(axis=1)))
        raise ValueError(f"{name} contains NaN or inf in {bad} of {v.shape[0]} rows")
    if v.shape[1] == 2:
        v = np.hstack([v, np.zeros((v.shape[0], 1))])
    return v


def check_index_array(
    cells: Any, n_vertices: int | None, widths: Sequence[int], name: str = "cells"
) -> np.ndarray:
    """Validate an integer connectivity array `[m, k]` (k in ``widths``) against ``n_vertices`` vertices."""
    c = to_numpy(cells, name)
    if c.ndim != 2 or c.shape[1] not in widths:
        shapes = " or ".join(f"[m, {k}]" for k in widths)
        raise ValueError(f"{name} must have shape {shapes}, got {list(c.shape)}")
    if c.shape[0] == 0:
        raise ValueError(f"{name} is empty (m = 0)")
    if not np.issubdtype(c.dtype, np.integer):
        raise ValueError(f"{name} must be an integer array, got dtype {c.dtype}")
    c = c.astype(np.int64)
    lo, hi = int(c.min()), int(c.max())
    if lo < 0 or (n_vertices is not None and hi >= n_vertices):
        raise ValueError(f"{name} indices span [{lo}, {hi}], outside the valid range [0, {n_vertices})")
    return c


def check_data(data: Mapping[str, Any] | None, count: int, what: str) -> dict[str, np.ndarray]:
    """Validate per-point / per-cell arrays `[count]` or `[count, k]`; 2-vectors are padded to 3."""
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ValueError(f"{what}_data must be a dict name -> array, got {type(data).__name__}")
    out: dict[str, np.ndarray] = {}
    for key, value in data.items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"{what}_data names must be non-empty strings, got {key!r}")
        a = to_numpy(value, f"{what}_data[{key!r}]")
        if a.ndim not in (1, 2) or a.shape[0] != count:
            raise ValueError(
                f"{what}_data[{key!r}] must have shape [{count}] or [{count}, k] "
                f"(one row per {what}), got {list(a.shape)}"
            )
        if a.dtype == np.bool_:
            a = a.astype(np.uint8)  # VTK has no boolean array type
        elif not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"{what}_data[{key!r}] must be numeric, got dtype {a.dtype}")
        if a.ndim == 2 and a.shape[1] == 2:
            # ParaView only treats 3-component arrays as vectors (glyphs, warp by vector).
            a = np.hstack([a, np.zeros((count, 1), dtype=a.dtype)])
        out[key] = np.ascontiguousarray(a)
    return out


def apply_umask(mode: int) -> int:
    """`mode` with the process umask applied: the permissions a plain open() or mkdir() would give."""
    return mode & ~_UMASK


def prepare_folder(folder: str | os.PathLike[str], what: str = "folder") -> Path:
    """Create `folder` with its parents if needed and return it; a clear error when that is impossible.

    Raises:
        NotADirectoryError: `folder`, or a folder above it, is a file.
        PermissionError: `folder` cannot be created.
    """
    path = Path(folder)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{what} {str(path)!r} is a file, expected a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError) as err:
        blocking = next((p for p in path.parents if p.exists() and not p.is_dir()), path)
        raise NotADirectoryError(
            f"{what} {str(path)!r} cannot be created: {str(blocking)!r} is a file, expected a folder"
        ) from err
    except PermissionError as err:
        raise PermissionError(f"{what} {str(path)!r} cannot be created: {err.strerror}") from err
    return path


def fsync_folder(folder: str | os.PathLike[str]) -> None:
    """Flush a folder's entries to disk, so a file renamed into it survives a power loss (POSIX only)."""
    if os.name != "posix":
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_output(
    path: str | os.PathLike[str], temp_folder: str | os.PathLike[str] | None = None
) -> Iterator[Path]:
    """Yield a temporary path; on success it replaces ``path``, on error it is removed.

    The temporary file is made in `temp_folder` (default: the folder of ``path``; it must be on the same
    file system, for the rename to be atomic). Its name keeps the destination's suffix, since some
    writers pick the format from it.
    """
    dest = Path(path)
    prepare_folder(dest.parent, f"the folder of {dest.name}")
    temp_dir = dest.parent if temp_folder is None else Path(temp_folder)
    try:
        fd, tmp_name = tempfile.mkstemp(dir=temp_dir, prefix=f".{dest.stem}.", suffix=f".tmp{dest.suffix}")
    except PermissionError as err:
        message = f"cannot write {str(dest)!r}: its folder is not writable ({err.strerror})"
        raise PermissionError(message) from err
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # Flush to disk before the rename so a power loss cannot leave a renamed but empty file.
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, apply_umask(0o666))
        os.replace(tmp, dest)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_folder(dest.parent)


def check_field_data(field_data: Mapping[str, Any] | None) -> dict[str, np.ndarray]:
    """Validate whole-dataset values (name -> number or 1-D numbers) and return them as 1-D float64."""
    out: dict[str, np.ndarray] = {}
    for key, value in (field_data or {}).items():
        if not isinstance(key, str) or not key or any(c in key for c in "<>&\"'"):
            raise ValueError(f"field_data names must be non-empty strings without XML markup, got {key!r}")
        a = to_numpy(value, f"field_data[{key!r}]")
        if (
            a.ndim > 1
            or a.size == 0
            or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer))
        ):
            raise ValueError(f"field_data[{key!r}] must be a number or a 1-D array of numbers, got {a!r}")
        a = a.astype(np.float64).reshape(-1)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"field_data[{key!r}] must be finite, got {a.tolist()}")
        out[key] = a
    return out


def _field_data_xml(field_data: Mapping[str, np.ndarray]) -> bytes:
    arrays = "".join(
        f'<DataArray type="Float64" Name="{key}" NumberOfTuples="{a.size}" format="ascii">'
        f"{' '.join(repr(float(v)) for v in a)}</DataArray>\n"
        for key, a in field_data.items()
    )
    return f"<FieldData>\n{arrays}</FieldData>\n".encode()


def write_vtu(
    path: str | os.PathLike[str],
    vertices: Any,
    cells: Any,
    point_data: Mapping[str, Any] | None = None,
    cell_data: Mapping[str, Any] | None = None,
    field_data: Mapping[str, Any] | None = None,
) -> Path:
    """Write an unstructured-grid ``.vtu`` file (binary, atomic) and return its path.

    Args:
        path: destination file (parent folders are created).
        vertices: positions `[n, 3]` or `[n, 2]` (2D is written with z = 0), in the simulation's length unit.
        cells: vertex indices `[m, 4]` (tetrahedra, needs 3D vertices) or `[m, 3]` (triangles).
        point_data: name -> `[n]` or `[n, k]`; `[n, 2]` vectors are padded with a zero z component.
        cell_data: name -> `[m]` or `[m, k]`; `[m, 2]` vectors are padded likewise.
        field_data: name -> a number or 1-D numbers that belong to the whole dataset; ParaView takes
            ``TimeValue`` as the frame's time.
    """
    v_in = to_numpy(vertices, "vertices")
    points = check_vertices(v_in)
    conn = check_index_array(cells, points.shape[0], (3, 4))
    if conn.shape[1] == 4 and v_in.shape[1] == 2:
        raise ValueError("4-node cells are written as tetrahedra and need 3D vertices [n, 3], got [n, 2]")
    pdata = check_data(point_data, points.shape[0], "point")
    cdata = check_data(cell_data, conn.shape[0], "cell")
    fdata = check_field_data(field_data)
    mesh = meshio.Mesh(
        points,
        [(_CELL_TYPES[conn.shape[1]], conn)],
        point_data=pdata,
        cell_data={k: [a] for k, a in cdata.items()},
    )
    dest = Path(path)
    with atomic_output(dest) as tmp:
        # Looked up on the module at call time so tests can monkeypatch meshio.write.
        meshio.write(tmp, mesh, file_format="vtu", binary=True)
        if fdata:
            # meshio's vtu writer leaves field data out: it goes first in the dataset, as VTK writes it
            text = tmp.read_bytes()
            head, mark, tail = text.partition(b"<UnstructuredGrid>\n")
            if not mark:
                raise RuntimeError(f"unexpected .vtu layout from meshio in {tmp}: no <UnstructuredGrid>")
            tmp.write_bytes(head + mark + _field_data_xml(fdata) + tail)
    return dest


def write_pvd(
    path: str | os.PathLike[str],
    entries: Sequence[tuple[float, str | os.PathLike[str]]],
    *,
    temp_folder: str | os.PathLike[str] | None = None,
) -> Path:
    """Write a ParaView collection (``.pvd``) listing ``(time, file)`` pairs, atomically.

    Args:
        path: destination ``.pvd`` file.
        entries: `(time, file)` with strictly increasing finite times (simulation time unit, usually s);
            relative files are taken relative to the pvd's folder, absolute ones are made relative to it.
        temp_folder: where the temporary file is written before the rename (as in `atomic_output`).
    """
    dest = Path(path)
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
        "  <Collection>",
    ]
    previous = -math.inf
    for time, file in entries:
        t = float(time)
        if not math.isfinite(t):
            raise ValueError(f"pvd times must be finite, got {t}")
        if t <= previous:
            raise ValueError(f"pvd times must be strictly increasing, got {t} after {previous}")
        previous = t
        f = Path(file)
        if f.is_absolute():
            f = Path(os.path.relpath(f, dest.parent.resolve()))
        # repr() round-trips the float exactly; posix separators keep the file portable.
        lines.append(f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(f.as_posix())}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    with atomic_output(dest, temp_folder) as tmp:
        tmp.write_text("\n".join(lines), encoding="utf-8")
    return dest
