"""A time series in one XDMF file with its arrays in one HDF5 file (ParaView's "Xdmf3 Reader").

`XdmfWriter` appends frames (moving points, fixed cells, point and cell arrays) to an HDF5 file and
renders the XDMF text that lists them; `energysim.export.series.VTKSeries` keeps both beside its
``.vtu`` frames and publishes them with the same all-or-nothing switch. Needs h5py
(``pip install torch-energysim[xdmf]``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

_TOPOLOGY = {3: "Triangle", 4: "Tetrahedron"}


def require_h5py() -> object:
    """The h5py module; ImportError saying how to install it when it is missing."""
    try:
        import h5py
    except ImportError as err:
        raise ImportError(
            "single_file='xdmf' writes its arrays with h5py, which is not installed: "
            "pip install h5py (or torch-energysim[xdmf])"
        ) from err
    return h5py


def _attribute_type(array: np.ndarray) -> str:
    width = 1 if array.ndim == 1 else array.shape[1]
    return {1: "Scalar", 3: "Vector", 9: "Tensor"}.get(width, "Matrix")


def _data_item(array: np.ndarray, reference: str) -> str:
    kind = "Float" if np.issubdtype(array.dtype, np.floating) else "Int"
    dims = " ".join(str(d) for d in array.shape)
    return (
        f'<DataItem Dimensions="{dims}" NumberType="{kind}" Precision="{array.dtype.itemsize}" '
        f'Format="HDF">{reference}</DataItem>'
    )


class XdmfWriter:
    """Frames appended to one HDF5 file; `xml` lists those written so far.

    Args:
        h5_path: the HDF5 file to create.
        cells: connectivity `[m, 3]` (triangles) or `[m, 4]` (tetrahedra), shared by all frames.
    """

    def __init__(self, h5_path: str | os.PathLike[str], cells: np.ndarray) -> None:
        h5py = require_h5py()
        self.h5_path = Path(h5_path)
        self.cells = np.ascontiguousarray(cells, dtype=np.int64)
        self._file = h5py.File(self.h5_path, "w")  # type: ignore[attr-defined]
        self._file.create_dataset("cells", data=self.cells)
        self._grids: list[tuple[float, int, dict[str, np.ndarray], dict[str, np.ndarray], int]] = []

    def write(
        self,
        time: float,
        points: np.ndarray,
        point_data: Mapping[str, np.ndarray],
        cell_data: Mapping[str, np.ndarray],
    ) -> None:
        """Append a frame: `points` `[n, 3]` (m), arrays `[n]`/`[n, k]` and `[m]`/`[m, k]`, checked."""
        k = len(self._grids)
        if f"frame_{k:05d}" in self._file:  # left by a write that failed: retried whole
            del self._file[f"frame_{k:05d}"]
        group = self._file.create_group(f"frame_{k:05d}")
        group.create_dataset("points", data=points)
        for prefix, data in (("point", point_data), ("cell", cell_data)):
            for name, value in data.items():
                group.create_dataset(f"{prefix}/{name}", data=value)
        self._grids.append((float(time), k, dict(point_data), dict(cell_data), points.shape[0]))

    def flush(self) -> None:
        """Put everything written so far on disk."""
        self._file.flush()
        with open(self.h5_path, "rb+") as handle:
            os.fsync(handle.fileno())

    def close(self) -> None:
        if self._file:
            self._file.close()

    def xml(self, h5_reference: str) -> str:
        """The XDMF text for the frames so far; `h5_reference`: the HDF5 file as seen from the XDMF file."""
        m, corners = self.cells.shape
        lines = [
            '<?xml version="1.0"?>',
            '<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">',
            "  <Domain>",
            '    <Grid Name="series" GridType="Collection" CollectionType="Temporal">',
        ]
        ref = h5_reference
        for time, k, point_data, cell_data, n in self._grids:
            frame = f"{ref}:/frame_{k:05d}"
            lines += [
                f'      <Grid Name="frame_{k:05d}" GridType="Uniform">',
                f'        <Time Value="{time!r}"/>',
                f'        <Topology TopologyType="{_TOPOLOGY[corners]}" NumberOfElements="{m}">',
                f"          {_data_item(self.cells, f'{ref}:/cells')}",
                "        </Topology>",
                '        <Geometry GeometryType="XYZ">',
                f"          {_data_item(np.empty((n, 3)), f'{frame}/points')}",
                "        </Geometry>",
            ]
            for center, prefix, data in (("Node", "point", point_data), ("Cell", "cell", cell_data)):
                for name, value in data.items():
                    lines += [
                        f"        <Attribute Name={quoteattr(name)} AttributeType="
                        f'"{_attribute_type(value)}" Center="{center}">',
                        f"          {_data_item(value, f'{frame}/{prefix}/{name}')}",
                        "        </Attribute>",
                    ]
            lines.append("      </Grid>")
        lines += ["    </Grid>", "  </Domain>", "</Xdmf>", ""]
        return "\n".join(lines)


__all__ = ["XdmfWriter", "require_h5py"]
