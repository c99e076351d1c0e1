"""A cheap RGB side view of a creature for `render_mode="rgb_array"`: numpy only, no OpenGL.

The camera looks along −z at the x–y plane (orthographic) and keeps the ground (y = 0) at a fixed
row. It either follows the body's centre of mass in x or stays on a fixed window of the world. The
ground is a band of 5 cm tiles laid in world coordinates, so under a following camera it scrolls
past the body by exactly the distance walked, and a moving creature looks as if it moves: the tiles
alternate light and dark and each carries a small brightness of its own (a hash of its index), so
the pattern never repeats and a shift of the ground can be measured across any distance.

Each pixel shows the nearest surface triangle (by mean depth), shaded by how squarely it faces the
camera and darkened with its distance behind the body's front. All triangles are rasterised at once
with array operations: a frame of the worm takes a few milliseconds, with no GL context to create.
"""

from __future__ import annotations

import numpy as np

from energysim.mesh import SimplexMesh

CAMERAS = ("follow", "fixed")
# edge of a ground tile in m
GROUND_TILE = 0.05
# fraction of the image height below the ground line
GROUND_ROWS = 0.2
_SKY = np.array([245, 245, 245], dtype=np.uint8)
# the light and the dark ground tile, before each tile's own brightness
_GROUND_LIGHT = np.array([222, 214, 196], dtype=np.float64)
_GROUND_DARK = np.array([184, 174, 154], dtype=np.float64)
# half-width of each tile's relative brightness offset: well below the light/dark contrast
_GROUND_JITTER = 0.05
_BODY = np.array([143, 179, 217], dtype=np.float64)
# shading of the face furthest behind the body's front, relative to the front
_DEPTH_SHADE = 0.7
# most (triangle, pixel) pairs tested at once
_MAX_CANDIDATES = 1 << 22


def _tile_brightness(index: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random number in [−1, 1) per integer tile index (a splitmix64 hash)."""
    with np.errstate(over="ignore"):
        k = index.astype(np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
        k = (k ^ (k >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        k = (k ^ (k >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        k ^= k >> np.uint64(31)
    return (k >> np.uint64(40)).astype(np.float64) / float(1 << 23) - 1.0


def check_window(window: object) -> tuple[float, float]:
    """`window` as `(x_min, x_max)` floats in m, or ValueError naming it."""
    try:
        low, high = (float(value) for value in window)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"window must be a pair (x_min, x_max) of numbers in m, got {window!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and high > low):
        raise ValueError(f"window must be finite with x_max > x_min (m), got {window!r}")
    return low, high


class SideViewRenderer:
    """Renders positions of `mesh`'s vertices as an RGB image `[height, width, 3]`, uint8.

    Args:
        mesh: the rest mesh (its surface triangles are drawn in 3D, its triangles in 2D).
        width, height: image size in pixels.
        span: width of the view in m; default 3 × the rest mesh's largest extent, or the width of
            `window`.
        camera: "follow": every frame is centred on the centre of mass's x; "fixed": the view stays
            on `window`, or without one on the `span`-wide window centred on the centre of mass of the
            first frame drawn after construction or `reset()`.
        window: `(x_min, x_max)` in m, the world range a fixed camera shows; only with "fixed".
        vertex_mass: mass of each vertex, shape `[n]`, in kg, weighting the centre of mass; None:
            the plain mean of the vertices.

    Attributes:
        pixels_per_metre: the scale of the image, the same along both axes.
        ground_row: the image row of the ground line y = 0 (a pixel's rows run from its top edge).
    """

    def __init__(
        self,
        mesh: SimplexMesh,
        width: int = 480,
        height: int = 270,
        span: float | None = None,
        *,
        camera: str = "follow",
        window: tuple[float, float] | None = None,
        vertex_mass: np.ndarray | None = None,
    ) -> None:
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2:
                raise ValueError(f"{name} must be an integer of at least 2 pixels, got {value!r}")
        if camera not in CAMERAS:
            raise ValueError(f"camera must be one of {CAMERAS}, got {camera!r}")
        self.window = None if window is None else check_window(window)
        if self.window is not None and camera != "fixed":
            raise ValueError(f"window = {window!r} is for camera='fixed'; a following camera has none")
        if self.window is not None and span is not None:
            raise ValueError(f"give span or window, not both: window {window!r} sets the span")
        self.faces = (mesh.surface() if mesh.dim == 3 else mesh.elements).cpu().numpy()
        self.num_vertices, self.dim = int(mesh.vertices.shape[0]), int(mesh.dim)
        if self.window is not None:
            self.span = self.window[1] - self.window[0]
        elif span is not None:
            self.span = float(span)
        else:
            low, high = mesh.bounding_box()
            self.span = 3.0 * float((high - low).max())
        if not (np.isfinite(self.span) and self.span > 0):
            raise ValueError(f"span must be finite and > 0 m, got {span!r}")
        self.vertex_weight = None
        if vertex_mass is not None:
            mass = np.asarray(vertex_mass, dtype=np.float64)
            if mass.shape != (self.num_vertices,) or not (np.isfinite(mass).all() and (mass > 0).all()):
                raise ValueError(
                    f"vertex_mass must hold {self.num_vertices} finite masses > 0 kg (one per vertex), "
                    f"got shape {list(mass.shape)}"
                )
            self.vertex_weight = mass / mass.sum()
        self.camera = camera
        self.width, self.height = int(width), int(height)
        self.pixels_per_metre = self.width / self.span
        self.ground_row = self.height * (1.0 - GROUND_ROWS)
        self._fixed_left = None if self.window is None else self.window[0]

    def reset(self) -> None:
        """Forget the window a fixed camera took from its first frame: the next frame sets it anew.
        A window given at construction stays."""
        self._fixed_left = None if self.window is None else self.window[0]

    def centre_x(self, positions: np.ndarray) -> float:
        """The centre of mass's x in m of vertex positions `[n, d]` (m)."""
        x = np.asarray(positions, dtype=np.float64)[:, 0]
        return float(x.mean() if self.vertex_weight is None else x @ self.vertex_weight)

    def view_left(self, positions: np.ndarray) -> float:
        """The world x in m at the left edge of the image of `positions` `[n, d]` (m); a fixed camera
        without a window takes it from the first frame it sees."""
        if self.camera == "follow":
            return self.centre_x(positions) - 0.5 * self.span
        if self._fixed_left is None:
            self._fixed_left = self.centre_x(positions) - 0.5 * self.span
        return self._fixed_left

    def render(self, positions: np.ndarray) -> np.ndarray:
        """The image `[height, width, 3]`, uint8, of vertex positions `[n, d]` (m).

        Raises:
            ValueError: where `positions` is not `[n, d]` of the mesh or has non-finite entries.
        """
        points = np.asarray(positions, dtype=np.float64)
        if points.shape != (self.num_vertices, self.dim):
            raise ValueError(
                f"positions must have shape [{self.num_vertices}, {self.dim}] (the mesh's vertices), "
                f"got {list(points.shape)}"
            )
        if not np.isfinite(points).all():
            bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
            raise ValueError(f"positions of vertices {bad[:10].tolist()} are not finite")
        scale = self.pixels_per_metre
        left = self.view_left(points)
        image = np.empty((self.height, self.width, 3), dtype=np.uint8)
        image[:] = _SKY
        self._draw_ground(image, left)
        columns = (points[:, 0] - left) * scale
        rows = self.ground_row - points[:, 1] * scale
        corners = np.stack([columns, rows], axis=-1)[self.faces]  # [s, 3, 2] pixel coordinates
        edge_a = corners[:, 1] - corners[:, 0]
        edge_b = corners[:, 2] - corners[:, 0]
        area = edge_a[:, 0] * edge_b[:, 1] - edge_a[:, 1] * edge_b[:, 0]
        face_depth = np.zeros(len(self.faces))
        shade = np.ones(len(self.faces))
        if self.dim == 3:
            world = points[self.faces]
            # |cos| of the angle between the face normal and the view axis: area in view / true area
            normal = np.cross(world[:, 1] - world[:, 0], world[:, 2] - world[:, 0])
            shade = 0.45 + 0.55 * np.abs(normal[:, 2]) / np.maximum(np.linalg.norm(normal, axis=-1), 1e-300)
            # faces further behind the body's front (smaller z) are darker: depth reads as relief
            face_depth = world[:, :, 2].mean(axis=1)
            depth_range = face_depth.max() - face_depth.min()
            if depth_range > 0:
                behind = (face_depth.max() - face_depth) / depth_range
                shade = shade * (1.0 - (1.0 - _DEPTH_SHADE) * behind)
        colours = (_BODY * shade[:, None]).clip(0, 255).astype(np.uint8)
        visible = np.abs(area) > 1e-12
        rows_hit, columns_hit, faces_hit = self._covered_pixels(corners[visible], area[visible])
        if faces_hit.size:
            depth_hit = face_depth[visible][faces_hit]
            # painter's order without a loop: per pixel, the nearest face (largest z) wins
            pixel = rows_hit * self.width + columns_hit
            order = np.lexsort((depth_hit, pixel))
            last = np.ones(order.size, dtype=bool)
            last[:-1] = pixel[order][1:] != pixel[order][:-1]
            winners = order[last]
            image[rows_hit[winners], columns_hit[winners]] = colours[visible][faces_hit[winners]]
        return image

    def _draw_ground(self, image: np.ndarray, left: float) -> None:
        """Fill the rows below the ground line with tiles `GROUND_TILE` wide and deep, laid in world
        coordinates from the view's left edge `left` (m)."""
        first_row = int(np.ceil(self.ground_row))
        if first_row >= self.height:
            return
        scale = self.pixels_per_metre
        column_x = left + (np.arange(self.width) + 0.5) / scale  # world x of the pixel centres
        column_tile = np.floor(column_x / GROUND_TILE).astype(np.int64)
        row_depth = (np.arange(first_row, self.height) + 0.5 - self.ground_row) / scale
        row_tile = np.floor(row_depth / GROUND_TILE).astype(np.int64)
        tile = column_tile[None, :] * 1_000_003 + row_tile[:, None]  # a unique id per tile
        dark = ((column_tile[None, :] + row_tile[:, None]) % 2 == 1)[..., None]
        brightness = 1.0 + _GROUND_JITTER * _tile_brightness(tile)[..., None]
        colour = np.where(dark, _GROUND_DARK, _GROUND_LIGHT) * brightness
        image[first_row:] = colour.clip(0, 255).astype(np.uint8)

    def _covered_pixels(
        self, corners: np.ndarray, area: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows, columns and face indices of the pixels whose centres lie in each triangle.

        All triangles are tested at once on a window the size of the largest bounding box, so the cost
        is a few array operations per frame rather than per triangle.

        Args:
            corners: triangle corners in pixel coordinates (column, row), shape `[s, 3, 2]`.
            area: twice their signed areas, shape `[s]` (non-zero).
        """
        low = np.floor(corners.min(axis=1)).astype(np.int64)  # [s, 2]
        high = np.ceil(corners.max(axis=1)).astype(np.int64)
        low = np.maximum(low, 0)
        high = np.minimum(high, [self.width - 1, self.height - 1])
        extent = (high - low + 1).clip(min=0)
        if not extent.size or extent.max() == 0:
            return (np.zeros(0, dtype=np.int64),) * 3
        span_columns, span_rows = (int(e) for e in extent.max(axis=0))
        chunk = max(1, _MAX_CANDIDATES // (span_columns * span_rows))
        if corners.shape[0] > chunk:  # a badly stretched triangle: bound the memory, a few passes
            rows, columns, faces = [], [], []
            for first in range(0, corners.shape[0], chunk):
                part = self._covered_pixels(corners[first : first + chunk], area[first : first + chunk])
                rows.append(part[0])
                columns.append(part[1])
                faces.append(part[2] + first)
            return np.concatenate(rows), np.concatenate(columns), np.concatenate(faces)
        offsets_columns, offsets_rows = np.meshgrid(np.arange(span_columns), np.arange(span_rows))
        columns = low[:, 0, None, None] + offsets_columns  # [s, H, W]
        rows = low[:, 1, None, None] + offsets_rows
        inside = (offsets_columns < extent[:, 0, None, None]) & (offsets_rows < extent[:, 1, None, None])
        sign = np.sign(area)[:, None, None]
        for k in range(3):
            start, end = corners[:, k], corners[:, (k + 1) % 3]
            cross = (end[:, 0] - start[:, 0])[:, None, None] * (rows + 0.5 - start[:, 1, None, None]) - (
                end[:, 1] - start[:, 1]
            )[:, None, None] * (columns + 0.5 - start[:, 0, None, None])
            inside &= cross * sign >= 0
        faces, _, _ = np.nonzero(inside)
        return rows[inside], columns[inside], faces


__all__ = ["CAMERAS", "GROUND_ROWS", "GROUND_TILE", "SideViewRenderer", "check_window"]
