"""A VTK time series that replaces an older one whole: frames in a folder of their own, then one rename.

Layout in `folder` for a series named ``frame``::

    frame.pvd                     the collection that ParaView and pyvista open
    frame.xdmf                    with `single_file="xdmf"`: the same series as one XDMF file
    frame.k3j_x9a2/               the frames that frame.pvd lists, in a folder of their own
        .energysim-series.json    marks the folder as written by this library, for this series name
        frame_00000.vtu, frame_00001.vtu, ...
        frame.h5                  with `single_file="xdmf"`: the arrays that frame.xdmf points to

A series gets a fresh folder ``{name}.<random>/`` when it starts; its frames are written there (each
atomically and flushed to disk). `VTKSeries.commit` then replaces ``{name}.pvd`` with one `os.replace`,
so at every instant the ``.pvd`` lists either the complete previous series or the complete new one,
whatever happens in between (an exception, a full disk, an interrupt, a killed process); so does the
``.xdmf``, written the same way just before the ``.pvd``. Only after that switch are the previous
series' frames removed.

Files are removed only from folders that carry the marker with this series' name, and there only the
frames, their temporary files and the marker: anything else in the output folder (a user's
``frame_00042.vtu``, ``notes.txt``, frames listed by a ``.pvd`` the library did not write) is never
touched, and a marked folder that still holds other files is kept. A crash leaves at most one marked
folder that no ``.pvd`` lists; the next commit of the same name removes it once the process that wrote
it has ended.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import logging
import math
import os
import re
import socket
import tempfile
import warnings
import weakref
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

from .vtk import (
    apply_umask,
    atomic_output,
    check_data,
    check_index_array,
    check_vertices,
    fsync_folder,
    prepare_folder,
    to_numpy,
    write_pvd,
    write_vtu,
)
from .xdmf import XdmfWriter, require_h5py

logger = logging.getLogger(__name__)

MARKER_NAME = ".energysim-series.json"
SINGLE_FILE_FORMATS = (None, "xdmf")
_MARKER_FORMAT = "energysim.vtk_series"
# Series folders of this process whose `VTKSeries` is still alive: another series must not take them
# for the leftovers of a crash, although the marker names this (running) process.
_LIVE_FOLDERS: set[str] = set()


def _frame_pattern(name: str) -> re.Pattern[str]:
    """Files the library writes into a series folder: frames and the temporaries of atomic writes."""
    stem = re.escape(name)
    frames = rf"{stem}_\d{{5}}\.vtu|\.{stem}_\d{{5}}\..+\.tmp\.vtu|{stem}\.h5"
    return re.compile(rf"{frames}|\.{stem}\..+\.tmp\.(pvd|xdmf)|\.\.energysim-series\..+\.tmp\.json")


def _read_marker(folder: Path) -> dict[str, Any] | None:
    """The marker of a series folder, or None when `folder` is not one the library wrote."""
    try:
        marker = json.loads((folder / MARKER_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or marker.get("format") != _MARKER_FORMAT:
        return None
    return marker


def _writer_has_ended(folder: Path, marker: Mapping[str, Any]) -> bool:
    """Whether the series writing `folder` is known to be gone (unknown: it is not)."""
    pid = marker.get("pid")
    if marker.get("host") != socket.gethostname() or not isinstance(pid, int) or pid <= 0:
        return False
    if os.name != "posix":
        return False  # os.kill(pid, 0) would end the process there rather than probe it
    if pid == os.getpid():
        return os.path.abspath(folder) not in _LIVE_FOLDERS
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False
    return False


def _listed_folders(pvd_path: Path) -> set[Path]:
    """Direct subfolders of the pvd's folder that hold files the ``.pvd`` lists (none when unreadable)."""
    if not pvd_path.is_file():
        return set()
    try:
        datasets = ET.parse(pvd_path).getroot().findall("./Collection/DataSet")
    except (OSError, ET.ParseError) as err:
        logger.warning("could not read the previous series %s (%s): its files are left alone", pvd_path, err)
        return set()
    folders = set()
    for dataset in datasets:
        parts = Path(dataset.get("file", "")).parts
        if len(parts) == 2 and parts[0] not in ("", ".", ".."):
            folders.add(pvd_path.parent / parts[0])
    return folders


_XDMF_REFERENCE = re.compile(r">\s*([^<>/]+)/[^<>/]+\.h5:/")


def _xdmf_folders(xdmf_path: Path) -> set[Path]:
    """Direct subfolders of the xdmf's folder whose HDF5 file the ``.xdmf`` points to."""
    if not xdmf_path.is_file():
        return set()
    try:
        text = xdmf_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        logger.warning("could not read %s (%s): the files it names are left alone", xdmf_path, err)
        return set()
    names = set(_XDMF_REFERENCE.findall(text)) - {".", ".."}
    return {xdmf_path.parent / name for name in names}


def _remove_series_folder(folder: Path, name: str) -> None:
    """Remove what the library wrote in a marked series folder of `name`; keep anything else.

    The marker goes last, so an interrupted removal still leaves a folder recognisably the library's.
    """
    marker = None if folder.is_symlink() else _read_marker(folder)
    if marker is None or marker.get("name") != name:
        return
    pattern = _frame_pattern(name)
    try:
        for entry in folder.iterdir():
            if pattern.fullmatch(entry.name) and entry.is_file() and not entry.is_symlink():
                entry.unlink()
        (folder / MARKER_NAME).unlink()
        folder.rmdir()
    except OSError as err:
        # The new series is already in place; what is left here is only clutter, never a loss.
        others = sorted(p.name for p in folder.iterdir()) if folder.is_dir() else []
        level = logging.INFO if err.errno == errno.ENOTEMPTY else logging.WARNING
        logger.log(level, "left %s in place (%s); it holds %s", folder, err.strerror or err, others[:5])


class VTKSeries:
    """Writes one ``.vtu`` per frame into a folder of its own; `commit` publishes them as ``{name}.pvd``.

    ParaView and pyvista (``pyvista.get_reader(series.pvd_path)``) open the ``.pvd`` as a time series.
    Until `commit` the ``.pvd`` (if any) still lists the previous series, complete; `commit` switches it
    to this one in one atomic rename and then removes the previous series' frames (see the module
    docstring for the layout and what is ever removed). `commit` may be called again after more frames
    to publish them too. As a context manager the series is committed on a normal exit and discarded
    when an exception leaves the block.

    Args:
        folder: output folder (created with its parents).
        cells: connectivity `[m, 4]` (tetrahedra) or `[m, 3]` (triangles), shared by all frames.
        name: file stem: frames are ``{name}.<random>/{name}_{k:05d}.vtu``, the collection ``{name}.pvd``.
        single_file: "xdmf": also write the series as ``{name}.xdmf`` beside the ``.pvd``, its arrays in
            ``{name}.<random>/{name}.h5`` (needs h5py), published by `commit` with the ``.pvd``;
            None: the ``.pvd`` only.

    Raises:
        ValueError: a bad `name`, `cells` or `single_file`.
        ImportError: `single_file="xdmf"` without h5py.
        NotADirectoryError: `folder` (or a folder above it) is a file.
        PermissionError: `folder` cannot be written.
    """

    def __init__(
        self, folder: str | os.PathLike[str], cells: Any, name: str = "frame", single_file: str | None = None
    ) -> None:
        if not isinstance(name, str) or not name or any(s in name for s in ("/", "\\", os.sep)):
            raise ValueError(f"name must be a non-empty file stem without path separators, got {name!r}")
        if single_file not in SINGLE_FILE_FORMATS:
            raise ValueError(f"single_file must be one of {SINGLE_FILE_FORMATS}, got {single_file!r}")
        if single_file == "xdmf":
            require_h5py()
        self.cells = check_index_array(cells, None, (3, 4))
        self.xdmf: XdmfWriter | None = None
        self.folder = prepare_folder(folder)
        self.name = name
        self.frames: list[tuple[float, Path]] = []
        try:
            self.series_folder = Path(tempfile.mkdtemp(prefix=f"{name}.", dir=self.folder))
        except PermissionError as err:
            raise PermissionError(f"folder {str(self.folder)!r} is not writable: {err.strerror}") from err
        key = os.path.abspath(self.series_folder)
        _LIVE_FOLDERS.add(key)
        weakref.finalize(self, _LIVE_FOLDERS.discard, key)
        # frames written and frames published: a series dropped with frames it never published says
        # so, since the .pvd still lists the previous series and the new frames are invisible
        self._counts = [0, 0]
        weakref.finalize(self, _warn_unpublished, self._counts, str(self.series_folder), name)
        try:
            os.chmod(self.series_folder, apply_umask(0o777))  # mkdtemp makes it private (0700)
            host = socket.gethostname()
            marker = {"format": _MARKER_FORMAT, "name": name, "pid": os.getpid(), "host": host}
            with atomic_output(self.series_folder / MARKER_NAME) as tmp:
                tmp.write_text(json.dumps(marker, indent=1) + "\n", encoding="utf-8")
            if single_file == "xdmf":
                self.xdmf = XdmfWriter(self.series_folder / f"{name}.h5", self.cells)
        except BaseException:
            with contextlib.suppress(OSError):
                (self.series_folder / MARKER_NAME).unlink(missing_ok=True)
                self.series_folder.rmdir()
            raise

    @property
    def pvd_path(self) -> Path:
        """Path of the ``.pvd`` collection file."""
        return self.folder / f"{self.name}.pvd"

    @property
    def xdmf_path(self) -> Path:
        """Path of the single-file series ``{name}.xdmf`` (written only with `single_file="xdmf"`)."""
        return self.folder / f"{self.name}.xdmf"

    def _referenced(self) -> set[Path]:
        """Series folders that the published ``.pvd`` or ``.xdmf`` point to."""
        return _listed_folders(self.pvd_path) | _xdmf_folders(self.xdmf_path)

    def __len__(self) -> int:
        return len(self.frames)

    def __enter__(self) -> VTKSeries:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if kind is not None:
            self.discard()
            return
        try:
            self.commit()
        except BaseException:
            self.discard()  # keeps the frames if the .pvd already lists them
            raise

    def write(
        self,
        time: float,
        vertices: Any,
        point_data: Mapping[str, Any] | None = None,
        cell_data: Mapping[str, Any] | None = None,
        field_data: Mapping[str, Any] | None = None,
    ) -> Path:
        """Write the next frame at ``time`` (strictly after the previous one) into the series' folder.

        A failed write leaves no file behind; the next call retries the same frame index.

        Args:
            time: simulation time of the frame (usually s); tensors of one element are accepted.
            vertices: positions `[n, 3]` or `[n, 2]`.
            point_data, cell_data, field_data: as in :func:`write_vtu` (the ``.xdmf`` leaves
                field data out: its frames carry their time).

        Returns:
            The path of the frame's ``.vtu`` file.
        """
        t_arr = to_numpy(time, "time")
        if t_arr.size != 1:
            raise ValueError(f"time must be a single number, got shape {list(t_arr.shape)}")
        t = float(t_arr.reshape(()))
        if not math.isfinite(t):
            raise ValueError(f"time must be finite, got {t}")
        if self.frames and t <= self.frames[-1][0]:
            raise ValueError(f"time must increase from frame to frame, got {t} after {self.frames[-1][0]}")
        if not (self.series_folder / MARKER_NAME).is_file():
            raise RuntimeError(f"the series folder {self.series_folder} is gone (discarded or replaced)")
        frame_path = self.series_folder / f"{self.name}_{len(self.frames):05d}.vtu"
        write_vtu(frame_path, vertices, self.cells, point_data, cell_data, field_data)
        if self.xdmf is not None:
            points = check_vertices(vertices)
            try:
                self.xdmf.write(
                    t,
                    points,
                    check_data(point_data, points.shape[0], "point"),
                    check_data(cell_data, self.cells.shape[0], "cell"),
                )
            except BaseException:
                frame_path.unlink(missing_ok=True)
                raise
        self.frames.append((t, frame_path))
        self._counts[0] = len(self.frames)
        logger.debug("wrote frame %d (t = %g) to %s", len(self.frames) - 1, t, frame_path)
        return frame_path

    def commit(self) -> Path:
        """Point ``{name}.pvd`` at this series' frames (one atomic rename), then remove the previous series.

        Returns:
            The path of the ``.pvd``.

        Raises:
            ValueError: no frame was written.
        """
        if not self.frames:
            raise ValueError(f"series {self.name!r} in {self.folder} has no frames: nothing to commit")
        if self.xdmf is not None:
            self.xdmf.flush()
        fsync_folder(self.series_folder)  # the frames' names are on disk before the .pvd lists them
        previous = self._referenced() - {self.series_folder}
        # The temporary .pvd (and .xdmf) is made in the series folder, so a crash before the rename
        # leaves it only where the library recognises it as its own.
        if self.xdmf is not None:
            text = self.xdmf.xml(f"{self.series_folder.name}/{self.name}.h5")
            with atomic_output(self.xdmf_path, self.series_folder) as tmp:
                tmp.write_text(text, encoding="utf-8")
        elif _xdmf_folders(self.xdmf_path) & previous:
            # an .xdmf of an older series of this name would outlive the frames it points to
            self.xdmf_path.unlink()
        entries = [(t, path.relative_to(self.folder)) for t, path in self.frames]
        write_pvd(self.pvd_path, entries, temp_folder=self.series_folder)
        self._counts[1] = len(self.frames)
        logger.info("wrote %s (%d frames in %s)", self.pvd_path, len(self.frames), self.series_folder.name)
        for old in sorted(previous):
            _remove_series_folder(old, self.name)
        self._remove_orphans()
        return self.pvd_path

    def discard(self) -> None:
        """Remove this series' frames and folder, unless the ``.pvd`` or ``.xdmf`` lists them already."""
        if self.series_folder in self._referenced():
            return
        if self.xdmf is not None:
            self.xdmf.close()
        _remove_series_folder(self.series_folder, self.name)
        self.frames.clear()
        self._counts[:] = [0, 0]

    def _remove_orphans(self) -> None:
        """Remove marked folders of this name that no ``.pvd`` lists and whose writer has ended."""
        listed = self._referenced()
        for candidate in self.folder.glob(f"{glob.escape(self.name)}.*"):
            if candidate in listed or not candidate.is_dir() or candidate.is_symlink():
                continue
            marker = _read_marker(candidate)
            if marker is None or marker.get("name") != self.name:
                continue
            if _writer_has_ended(candidate, marker):
                logger.info("removing %s, left by an export that did not finish", candidate)
                _remove_series_folder(candidate, self.name)


def _warn_unpublished(counts: list[int], series_folder: str, name: str) -> None:
    written, published = counts
    if written > published:
        warnings.warn(
            f"VTK series {name!r} was dropped with {written - published} frame(s) in {series_folder} that "
            f"its {name}.pvd does not list: call commit() after the last write, or use the series as a "
            "`with` block",
            UserWarning,
            stacklevel=2,
        )


__all__ = ["MARKER_NAME", "SINGLE_FILE_FORMATS", "VTKSeries"]
