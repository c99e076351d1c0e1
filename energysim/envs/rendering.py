"""A cheap RGB side view of a creature for `render_mode="rgb_array"`: numpy only, no OpenGL.

The camera looks along −z at the x–y plane (orthographic), follows the body's mean x and keeps the
ground (y = 0) at a fixed row, so frames of a rollout line up into a video. Each pixel shows the
nearest surface triangle (by mean depth), shaded by how squarely it faces the camera. All triangles
are rasterised at once with array operations: a frame of the worm takes a few milliseconds, with no
GL context to create.
"""

from __future__ import annotations

import numpy as np

from energysim.mesh import SimplexMesh

_SKY = np.array([245, 245, 245], dtype=np.uint8)
_GROUND = np.array([217, 212, 199], dtype=np.uint8)
_BODY = np.array([143, 179, 217], dtype=np.float64)
# fraction of the image height below the ground line
_GROUND_ROWS = 0.2
# most (triangle, pixel) pairs tested at once
_MAX_CANDIDATES = 1 << 22


class SideViewRenderer:
    """Renders positions of `mesh`'s vertices as an RGB image `[height, width, 3]`, uint8.

    Args:
        mesh: the rest mesh (its surface triangles are drawn in 3D, its triangles in 2D).
        width, height: image size in pixels.
        span: width of the view in m; default 3 × the rest mesh's largest extent.
    """

    def __init__(
        self, mesh: SimplexMesh, width: int = 480, height: int = 270, span: float | None = None
    ) -> None:
        if width < 2 or height < 2:
            raise ValueError(f"width and height must be at least 2 pixels, got {width} x {height}")
        self.faces = (mesh.surface() if mesh.dim == 3 else mesh.elements).cpu().numpy()
        low, high = mesh.bounding_box()
        self.span = float(span) if span is not None else 3.0 * float((high - low).max())
        if not (np.isfinite(self.span) and self.span > 0):
            raise ValueError(f"span must be finite and > 0 m, got {span}")
        self.width, self.height = int(width), int(height)

    def render(self, positions: np.ndarray) -> np.ndarray:
        """The image of vertex positions `[n, d]` (m)."""
        points = np.asarray(positions, dtype=np.float64)
        scale = self.width / self.span  # pixels per m
        ground_row = self.height * (1.0 - _GROUND_ROWS)
        columns = (points[:, 0] - points[:, 0].mean()) * scale + 0.5 * self.width
        rows = ground_row - points[:, 1] * scale
        depth = points[:, 2] if points.shape[1] == 3 else np.zeros(len(points))
        image = np.empty((self.height, self.width, 3), dtype=np.uint8)
        image[:] = _SKY
        image[int(np.ceil(ground_row)) :] = _GROUND
        corners = np.stack([columns, rows], axis=-1)[self.faces]  # [s, 3, 2] pixel coordinates
        edge_a = corners[:, 1] - corners[:, 0]
        edge_b = corners[:, 2] - corners[:, 0]
        area = edge_a[:, 0] * edge_b[:, 1] - edge_a[:, 1] * edge_b[:, 0]
        # |cos| of the angle between the face normal and the view axis: area in view / true area
        if points.shape[1] == 3:
            world = points[self.faces]
            normal = np.cross(world[:, 1] - world[:, 0], world[:, 2] - world[:, 0])
            facing = np.abs(normal[:, 2]) / np.maximum(np.linalg.norm(normal, axis=-1), 1e-300)
        else:
            facing = np.ones(len(self.faces))
        colours = (_BODY * (0.45 + 0.55 * facing)[:, None]).clip(0, 255).astype(np.uint8)
        visible = np.abs(area) > 1e-12
        rows_hit, columns_hit, faces_hit = self._covered_pixels(corners[visible], area[visible])
        if faces_hit.size:
            face_depth = depth[self.faces[visible]].mean(axis=1)[faces_hit]
            # painter's order without a loop: per pixel, the nearest face (largest z) wins
            pixel = rows_hit * self.width + columns_hit
            order = np.lexsort((face_depth, pixel))
            last = np.ones(order.size, dtype=bool)
            last[:-1] = pixel[order][1:] != pixel[order][:-1]
            winners = order[last]
            image[rows_hit[winners], columns_hit[winners]] = colours[visible][faces_hit[winners]]
        return image

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


__all__ = ["SideViewRenderer"]
