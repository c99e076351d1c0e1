"""What the viewer page draws, packed into one binary message: surface, frames, scalars and markers.

The message (served as ``/trajectory.bin``) is

    b"ESV1" | uint32 header length (little-endian) | header JSON (UTF-8, space-padded to 4 bytes) | data

and the header's ``buffers`` give each array's ``offset`` (bytes from the start of the data, a multiple
of 4), ``dtype`` (``float32`` or ``uint32``, little-endian) and ``shape``. Arrays: ``faces`` `[s, 3]`
(indices into the drawn points), ``positions`` `[F, k, 3]` in m, and one ``field:<name>`` `[F, k]`
(per point) or `[F, s]` (per face) for each scalar field. A 3D mesh is drawn by its boundary triangles
and only its k boundary vertices are sent; a 2D mesh by all its triangles, in the z = 0 plane.

Nothing here imports the solver: the input is a mesh and plain arrays.
"""

from __future__ import annotations

import itertools
import json
import math
import numbers
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from energysim.mesh import SimplexMesh

MAGIC = b"ESV1"
MARKER_SHAPES = ("sphere", "box")


@dataclass(frozen=True)
class Surface:
    """The drawn triangles of a mesh.

    Attributes:
        point_ids: mesh vertex of each drawn point, shape `[k]`.
        faces: triangles as indices into the drawn points, shape `[s, 3]`.
        face_element: mesh element each triangle belongs to, shape `[s]`.
        num_vertices, num_elements, dim: of the mesh.
    """

    point_ids: np.ndarray
    faces: np.ndarray
    face_element: np.ndarray
    num_vertices: int
    num_elements: int
    dim: int

    @classmethod
    def of(cls, mesh: SimplexMesh) -> Surface:
        """Boundary triangles of a tet mesh, or every triangle of a 2D mesh."""
        elements = mesh.elements
        n, dim = mesh.num_vertices, mesh.dim
        if dim == 2:
            triangles = elements
            owner = torch.arange(mesh.num_elements)
        else:
            triangles = mesh.surface()
            owner = _facet_owner(elements, triangles, n)
        point_ids, local = torch.unique(triangles, return_inverse=True)
        return cls(
            point_ids=point_ids.numpy(),
            faces=local.reshape(-1, 3).numpy().astype(np.uint32),
            face_element=owner.numpy(),
            num_vertices=n,
            num_elements=mesh.num_elements,
            dim=dim,
        )


def _facet_owner(elements: torch.Tensor, facets: torch.Tensor, n: int) -> torch.Tensor:
    """Index of the element that has each boundary facet, shape `[s]`.

    A facet is keyed by its sorted vertex ids as one integer; boundary facets belong to exactly one element,
    so a sorted search over all elements' facet keys finds it.
    """
    d = elements.shape[1] - 1
    local = torch.tensor(list(itertools.combinations(range(d + 1), d)))
    all_facets = elements[:, local].reshape(-1, d).sort(dim=1).values
    weights = torch.tensor([n**p for p in reversed(range(d))], dtype=torch.int64)
    keys = (all_facets * weights).sum(1)
    order = torch.argsort(keys)
    wanted = (facets.sort(dim=1).values * weights).sum(1)
    found = order[torch.searchsorted(keys[order], wanted)]
    return found // local.shape[0]


def _as_array(value: Any, name: str) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().to("cpu", torch.float64).numpy()
    if isinstance(value, (list, tuple)) and value and isinstance(value[0], torch.Tensor):
        shapes = {tuple(v.shape) for v in value}
        if len(shapes) > 1:
            raise ValueError(f"{name}: the tensors in the list have different shapes {sorted(shapes)}")
        return torch.stack([v.detach().to("cpu", torch.float64) for v in value]).numpy()
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        kind = type(value).__name__
        raise TypeError(f"{name} must be numeric (a tensor, array or list), got {kind}") from err
    return array


_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _check_finite(array: np.ndarray, name: str) -> None:
    """Finite, and finite once sent as float32."""
    bad = ~np.isfinite(array)
    if bad.any():
        frames = np.unique(np.nonzero(bad.reshape(bad.shape[0], -1))[0])[:10].tolist()
        raise ValueError(f"{name} has non-finite values (NaN or inf) in frames {frames}")
    if array.size and np.abs(array).max() > _FLOAT32_MAX:
        raise ValueError(f"{name} has values beyond float32's range (|value| > {_FLOAT32_MAX:.3g})")


def frame_positions(states: Any, surface: Surface) -> np.ndarray:
    """Drawn point positions `[F, k, 3]` (float64, m) from flat states `[F, 2·n·d]` (a list or a stack).

    One state `[2·n·d]` is one frame. States hold positions then velocities; velocities are not drawn.
    """
    array = _as_array(states, "states")
    n, d = surface.num_vertices, surface.dim
    width = 2 * n * d
    if array.ndim == 1 and array.shape[0] == width:
        array = array[None]
    if array.ndim != 2 or array.shape[1] != width:
        raise ValueError(
            f"states must be flat states of shape [{width}] (positions then velocities of {n} vertices in "
            f"{d}D), given as a list or a stack [F, {width}]; got shape {list(array.shape)}"
        )
    if array.shape[0] == 0:
        raise ValueError("states is empty: a trajectory needs at least one frame")
    positions = array[:, : n * d].reshape(-1, n, d)
    _check_finite(positions, "states' positions")
    points = positions[:, surface.point_ids]
    if d == 2:
        points = np.concatenate([points, np.zeros_like(points[..., :1])], axis=-1)
    return points


def scalar_field(values: Any, name: str, location: str, surface: Surface, num_frames: int) -> np.ndarray:
    """Per-frame values on the drawn points `[F, k]` (`location` "vertex") or faces `[F, s]` ("element").

    `values`: shape `[F, n]` / `[F, m]`, or `[n]` / `[m]` for the same values in every frame.
    """
    count = surface.num_vertices if location == "vertex" else surface.num_elements
    array = _as_array(values, f"scalar field {name!r}")
    if array.ndim == 1 and array.shape[0] == count:
        array = np.broadcast_to(array, (num_frames, count))
    if array.shape != (num_frames, count):
        raise ValueError(
            f"{location} scalar field {name!r} must have shape [{num_frames}, {count}] (one value per "
            f"frame and {location}) or [{count}]; got {list(array.shape)}"
        )
    _check_finite(array, f"scalar field {name!r}")
    index = surface.point_ids if location == "vertex" else surface.face_element
    return array[:, index]


@dataclass(frozen=True)
class Marker:
    """A sphere or box drawn at a fixed place: `position` `[3]` in m, `size` radius (sphere) or edge
    lengths `[3]` (box) in m, `color` a CSS hex colour ``#rrggbb``."""

    name: str
    shape: str
    position: tuple[float, ...]
    size: tuple[float, ...]
    color: str

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "shape": self.shape,
            "position": list(self.position),
            "size": list(self.size),
            "color": self.color,
        }


_NAMED_COLORS = {
    "red": "#d62728",
    "green": "#2ca02c",
    "blue": "#1f77b4",
    "orange": "#ff7f0e",
    "purple": "#9467bd",
    "black": "#000000",
    "white": "#ffffff",
    "gray": "#7f7f7f",
    "yellow": "#e6c619",
}


def check_color(color: str | Sequence[float]) -> str:
    """``#rrggbb`` from ``#rrggbb``, ``#rgb``, one of a few names, or an RGB triple in [0, 1]."""
    if isinstance(color, str):
        text = _NAMED_COLORS.get(color.lower(), color.lower())
        if len(text) == 4 and text.startswith("#"):
            text = "#" + "".join(c * 2 for c in text[1:])
        if len(text) == 7 and text.startswith("#") and all(c in "0123456789abcdef" for c in text[1:]):
            return text
        raise ValueError(
            f"color must be '#rrggbb', '#rgb', an RGB triple in [0, 1] or one of {sorted(_NAMED_COLORS)}; "
            f"got {color!r}"
        )
    rgb = check_vector(color, 3, "color")
    if any(not 0.0 <= c <= 1.0 for c in rgb):
        raise ValueError(f"color components must lie in [0, 1], got {list(rgb)}")
    return "#" + "".join(f"{round(255 * c):02x}" for c in rgb)


def check_vector(value: Any, length: int, name: str) -> tuple[float, ...]:
    """`length` finite floats from a number, sequence, array or tensor; ValueError otherwise."""
    array = _as_array(value, name).reshape(-1)
    if array.shape != (length,) or not np.isfinite(array).all():
        raise ValueError(f"{name} must be {length} finite numbers, got {value!r}")
    return tuple(float(v) for v in array)


def make_marker(name: str, shape: str, position: Any, size: Any, color: str | Sequence[float]) -> Marker:
    """A validated `Marker`; `size` is a radius > 0 for a sphere, three edge lengths > 0 for a box."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"marker name must be a non-empty string, got {name!r}")
    if shape not in MARKER_SHAPES:
        raise ValueError(f"marker shape must be one of {MARKER_SHAPES}, got {shape!r}")
    pos = check_vector(position, 3, "position")
    extent = check_vector(size, 1 if shape == "sphere" else 3, "radius" if shape == "sphere" else "size")
    if any(s <= 0 for s in extent):
        raise ValueError(f"{'radius' if shape == 'sphere' else 'size'} must be > 0 m, got {list(extent)}")
    return Marker(name, shape, pos, extent, check_color(color))


def pack(
    session: str,
    version: int,
    surface: Surface,
    positions: np.ndarray,
    fields: Mapping[str, tuple[str, np.ndarray]],
    markers: Sequence[Marker],
    frame_dt: float,
    ground_height: float | None,
) -> bytes:
    """The message the page reads (see the module docstring). `session` names the viewer, `version` this
    content of it; `fields`: name -> ("vertex" | "element", values `[F, k]` or `[F, s]`) as
    `scalar_field` returns them."""
    arrays: list[tuple[str, np.ndarray]] = [
        ("faces", surface.faces.astype("<u4")),
        ("positions", positions.astype("<f4")),
    ]
    field_info = []
    for name, (location, values) in fields.items():
        data = values.astype("<f4")
        arrays.append((f"field:{name}", data))
        low, high = float(data.min()), float(data.max())
        field_info.append(
            {"name": name, "location": "point" if location == "vertex" else "face", "min": low, "max": high}
        )
    buffers, offset = {}, 0
    for name, data in arrays:
        buffers[name] = {"offset": offset, "dtype": data.dtype.name, "shape": list(data.shape)}
        offset += data.nbytes  # every dtype is 4 bytes wide, so offsets stay aligned
    header = {
        "session": session,
        "version": version,
        "num_frames": int(positions.shape[0]),
        "num_points": int(positions.shape[1]),
        "num_faces": int(surface.faces.shape[0]),
        "dim": surface.dim,
        "frame_dt": frame_dt,
        "ground_height": ground_height,
        "fields": field_info,
        "markers": [m.to_json() for m in markers],
        "buffers": buffers,
    }
    text = json.dumps(header, allow_nan=False).encode()
    text += b" " * (-len(text) % 4)
    return b"".join([MAGIC, struct.pack("<I", len(text)), text, *(data.tobytes() for _, data in arrays)])


def check_frame_dt(frame_dt: float) -> float:
    """Seconds between frames when played in real time; finite and > 0."""
    if isinstance(frame_dt, bool) or not isinstance(frame_dt, numbers.Real):
        raise ValueError(f"frame_dt must be a finite number > 0 s, got {frame_dt!r}")
    if not (math.isfinite(frame_dt) and frame_dt > 0):
        raise ValueError(f"frame_dt must be a finite number > 0 s, got {frame_dt!r}")
    return float(frame_dt)
