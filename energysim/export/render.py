"""Off-screen pictures (PNG) and animations (GIF, MP4) of surfaces with pyvista.

pyvista is imported inside the functions so that ``import energysim`` stays fast. Rendering is always
off-screen (EGL, no X server needed); every output file is written atomically.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .vtk import atomic_output, check_index_array, check_vertices, to_numpy

# Must be set before vtk is first imported: the default X11 window fails on machines without a display.
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

logger = logging.getLogger(__name__)

_SURFACE_COLOR = "#8fb3d9"
_EDGE_COLOR = "#2b2b2b"
_GROUND_COLOR = "#d9d4c7"
_BACKGROUND = "white"
# Vertical on the right: a horizontal bar at the bottom tends to cover the ground contact.
_SCALAR_BAR = dict(color="black", vertical=True, position_x=0.88, position_y=0.1, height=0.8, width=0.05)
# Camera direction for 3D scenes (y is up): in front, a little to the right and above.
_VIEW_DIR = np.array([0.55, 0.45, 1.0]) / np.linalg.norm([0.55, 0.45, 1.0])


def _pyvista() -> Any:
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    try:
        import pyvista as pv
    except ImportError as error:
        raise ImportError(
            "rendering needs pyvista; install the render extra: pip install 'torch-energysim[render]'"
        ) from error

    pv.OFF_SCREEN = True
    return pv


def _check_window(window_size: Sequence[int]) -> tuple[int, int]:
    w = tuple(int(s) for s in window_size)
    if len(w) != 2 or min(w) <= 0:
        raise ValueError(f"window_size must be (width, height) in pixels, got {window_size!r}")
    return w[0], w[1]


def _check_geometry(vertices: Any, faces: Any, name: str = "vertices") -> tuple[np.ndarray, np.ndarray, bool]:
    """Return points `[n, 3]`, faces `[s, 3]` or segments `[s, 2]`, and whether the scene is planar (2D)."""
    width = to_numpy(vertices, name).shape[-1:]
    points = check_vertices(vertices, name)
    f = check_index_array(faces, points.shape[0], (2, 3), "faces")
    return points, f, width == (2,) or f.shape[1] == 2


def _check_scalars(scalars: Any, n: int, n_frames: int | None) -> np.ndarray | None:
    """Per-vertex scalars as `[frames, n]` (a single `[n]` array is repeated), or None."""
    if scalars is None:
        return None
    if isinstance(scalars, (list, tuple)):
        scalars = [to_numpy(a, "scalars") for a in scalars]
    s = to_numpy(scalars, "scalars")
    if s.ndim == 1 and s.shape[0] == n:
        s = np.broadcast_to(s, (n_frames or 1, n))
    elif not (n_frames is not None and s.shape == (n_frames, n)):
        expected = f"[{n}]" + (f" or [{n_frames}, {n}]" if n_frames is not None else "")
        raise ValueError(f"scalars must have shape {expected} (one value per vertex), got {list(s.shape)}")
    if not (np.issubdtype(s.dtype, np.floating) or np.issubdtype(s.dtype, np.integer)):
        raise ValueError(f"scalars must be numeric, got dtype {s.dtype}")
    return s.astype(np.float64)


def _check_ground(ground_height: Any) -> float | None:
    if ground_height is None:
        return None
    h = float(ground_height)
    if not np.isfinite(h):
        raise ValueError(f"ground_height must be finite, got {h}")
    return h


def _polydata(pv: Any, points: np.ndarray, faces: np.ndarray) -> Any:
    cells = np.hstack([np.full((faces.shape[0], 1), faces.shape[1]), faces]).ravel()
    if faces.shape[1] == 3:
        return pv.PolyData(points.copy(), faces=cells)
    return pv.PolyData(points.copy(), lines=cells)


def _bounds(points: np.ndarray, ground_height: float | None) -> np.ndarray:
    """Axis-aligned box `[xmin, xmax, ymin, ymax, zmin, zmax]`, padded so a degenerate box stays framable."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    if ground_height is not None:
        lo[1], hi[1] = min(lo[1], ground_height), max(hi[1], ground_height)
    diag = float(np.linalg.norm(hi - lo))
    pad = 0.02 * diag if diag > 0 else 0.5
    return np.column_stack([lo - pad, hi + pad]).ravel()


def _build_scene(
    pv: Any,
    plotter: Any,
    points: np.ndarray,
    faces: np.ndarray,
    scalars: np.ndarray | None,
    bounds: np.ndarray,
    opts: dict[str, Any],
) -> Any:
    """Add surface, ground and title to ``plotter``, aim the camera at ``bounds``; return the surface mesh.

    ``opts``: flat, scalar_name, show_edges, cmap, ground_height, camera_position, title, antialias.
    """
    plotter.set_background(_BACKGROUND)
    if opts.get("antialias"):
        plotter.enable_anti_aliasing("ssaa")  # FXAA is not supported by EGL builds of VTK
    mesh = _polydata(pv, points, faces)
    segments = faces.shape[1] == 2
    kwargs: dict[str, Any] = {"show_edges": opts.get("show_edges", True) and not segments}
    kwargs.update(edge_color=_EDGE_COLOR, color=_EDGE_COLOR if segments else _SURFACE_COLOR)
    if segments:
        kwargs.update(line_width=6, render_lines_as_tubes=True)
    if scalars is not None:
        name = opts.get("scalar_name", "value")
        mesh.point_data[name] = scalars[0]
        lo, hi = float(scalars.min()), float(scalars.max())
        # One colour range for all frames, so equal colours mean equal values across an animation.
        clim = (lo, hi if hi > lo else lo + 1.0)
        kwargs.update(scalars=name, cmap=opts.get("cmap", "viridis"), clim=clim, color=None)
        kwargs["scalar_bar_args"] = dict(_SCALAR_BAR, title=name)
    plotter.add_mesh(mesh, **kwargs)

    x0, x1, y0, y1, z0, z1 = bounds
    h = opts.get("ground_height")
    if h is not None and opts["flat"]:
        line = pv.Line((2 * x0 - x1, h, 0.0), (2 * x1 - x0, h, 0.0))
        plotter.add_mesh(line, color="#6b6152", line_width=6)
    elif h is not None:
        size = 3.0 * max(x1 - x0, z1 - z0)
        plane = pv.Plane(
            center=((x0 + x1) / 2, h, (z0 + z1) / 2),
            direction=(0.0, 1.0, 0.0),
            i_size=size,
            j_size=size,
            i_resolution=12,
            j_resolution=12,
        )
        plotter.add_mesh(plane, color=_GROUND_COLOR, show_edges=True, edge_color="#b5ae9c", ambient=0.3)
    if opts.get("title"):
        plotter.add_text(opts["title"], position="upper_edge", font_size=12, color="black")

    camera = opts.get("camera_position")
    if camera is None:
        center = np.array([(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2])
        direction = np.array([0.0, 0.0, 1.0]) if opts["flat"] else _VIEW_DIR
        camera = [tuple(center + direction), tuple(center), (0.0, 1.0, 0.0)]
    plotter.camera_position = camera
    if camera is not opts.get("camera_position") or isinstance(camera, str):
        # Dolly along the view direction until the mesh box (all frames, ground height) is in view; the
        # large ground plane is left out, else it would shrink the mesh to a speck.
        plotter.renderer.reset_camera(render=False, bounds=bounds)
    # The clipping range must cover every frame and the ground, not only what is in the first frame.
    box = np.array(plotter.renderer.ComputeVisiblePropBounds())
    box[0::2], box[1::2] = np.minimum(box[0::2], bounds[0::2]), np.maximum(box[1::2], bounds[1::2])
    plotter.renderer.ResetCameraClippingRange(*box)
    return mesh


def render_png(
    path: str | os.PathLike[str],
    vertices: Any,
    faces: Any,
    scalars: Any = None,
    *,
    scalar_name: str = "value",
    window_size: tuple[int, int] = (960, 540),
    camera_position: Any = None,
    show_edges: bool = True,
    cmap: str = "viridis",
    ground_height: float | None = None,
    title: str | None = None,
) -> Path:
    """Render a surface off-screen to a PNG file (atomic) and return its path.

    Args:
        path: destination ``.png``.
        vertices: positions `[n, 3]`, or `[n, 2]` for a 2D mesh drawn in the z = 0 plane (y up).
        faces: triangles `[s, 3]` or segments `[s, 2]` (e.g. the boundary of a 2D mesh), vertex indices.
        scalars: optional per-vertex values `[n]`, coloured with ``cmap`` and a scalar bar ``scalar_name``.
        window_size: image `(width, height)` in pixels.
        camera_position: a pyvista view name (``"xy"``, ``"iso"``, ..., then fitted to the mesh) or
            `[(position), (focal point), (view up)]` used as given; default: from the front-right and
            above, y up (2D: looking down -z).
        ground_height: if given, a ground plane (2D: a line) is drawn at y = ground_height (length unit).
        title: optional text at the top of the picture.
    """
    points, f, flat = _check_geometry(vertices, faces)
    s = _check_scalars(scalars, points.shape[0], None)
    size = _check_window(window_size)
    h = _check_ground(ground_height)
    opts = dict(
        flat=flat,
        scalar_name=scalar_name,
        show_edges=show_edges,
        cmap=cmap,
        ground_height=h,
        camera_position=camera_position,
        title=title,
        antialias=True,
    )
    pv = _pyvista()
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        _build_scene(pv, plotter, points, f, s, _bounds(points, h), opts)
        image = plotter.screenshot(None, return_img=True)
    finally:
        plotter.close()
    from PIL import Image  # a pyvista dependency

    dest = Path(path)
    with atomic_output(dest) as tmp:
        Image.fromarray(np.ascontiguousarray(image)).save(tmp, format="PNG")
    logger.info("wrote %s (%dx%d)", dest, *size)
    return dest


def _check_frames(frames_vertices: Any) -> list[np.ndarray]:
    frames = [to_numpy(v, f"frames_vertices[{i}]") for i, v in enumerate(frames_vertices)]
    if not frames:
        raise ValueError("frames_vertices is empty: nothing to render")
    shape = frames[0].shape
    for i, v in enumerate(frames):
        if v.shape != shape:
            raise ValueError(
                f"frame {i} has shape {list(v.shape)}, frame 0 has {list(shape)}: all must match"
            )
    return frames


def _render_animation(
    kind: str,
    path: str | os.PathLike[str],
    frames: list[np.ndarray],
    faces: Any,
    scalars: Any,
    fps: float,
    window_size: tuple[int, int],
    camera_position: Any,
    ground_height: float | None,
) -> Path:
    points = [check_vertices(v, f"frames_vertices[{i}]") for i, v in enumerate(frames)]
    _, f, flat = _check_geometry(frames[0], faces, "frames_vertices[0]")
    s = _check_scalars(scalars, points[0].shape[0], len(points))
    size = _check_window(window_size)
    h = _check_ground(ground_height)
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    boxes = np.array([_bounds(p, h) for p in points])
    bounds = np.column_stack([boxes[:, 0::2].min(axis=0), boxes[:, 1::2].max(axis=0)]).ravel()
    opts = dict(flat=flat, ground_height=h, camera_position=camera_position)

    pv = _pyvista()
    dest = Path(path)
    with atomic_output(dest) as tmp:
        plotter = pv.Plotter(off_screen=True, window_size=list(size))
        try:
            mesh = _build_scene(pv, plotter, points[0], f, s, bounds, opts)

            def show_frames() -> Iterator[int]:
                # Only the mesh changes between frames; the camera and clipping range stay as set above.
                for k, p in enumerate(points):
                    mesh.points = p
                    if s is not None:
                        mesh.point_data["value"] = s[k]
                    plotter.render()
                    yield k

            if kind == "mp4":
                plotter.open_movie(str(tmp), framerate=fps, quality=7, macro_block_size=2)
            elif importlib.util.find_spec("imageio") is not None:
                plotter.open_gif(str(tmp), fps=fps)
            if plotter.mwriter is not None:
                for _ in show_frames():
                    plotter.write_frame()
            else:
                # Pillow (a pyvista dependency) writes the GIF when imageio is not installed.
                from PIL import Image

                it = (Image.fromarray(plotter.screenshot(None, return_img=True)) for _ in show_frames())
                first = next(it)
                first.save(tmp, format="GIF", save_all=True, append_images=it, duration=1000.0 / fps, loop=0)
            if plotter.mwriter is not None:
                # Closed here, not by plotter.close(), which would swallow an encoding error.
                plotter.mwriter.close()
                plotter.mwriter = None
        finally:
            plotter.close()
    logger.info("wrote %s (%d frames, %dx%d, %g fps)", dest, len(points), *size, fps)
    return dest


def render_gif(
    path: str | os.PathLike[str],
    frames_vertices: Sequence[Any],
    faces: Any,
    scalars: Any = None,
    *,
    fps: float = 20,
    window_size: tuple[int, int] = (640, 360),
    camera_position: Any = None,
    ground_height: float | None = None,
) -> Path:
    """Render an animated GIF of a sequence of vertex positions on fixed faces (atomic); return its path.

    The camera is fixed for the whole animation and frames the union bounding box of all frames (and the
    ground height). The GIF encoder merges identical consecutive frames into one longer frame.

    Args:
        path: destination ``.gif``.
        frames_vertices: `T` arrays `[n, 3]` or `[n, 2]` (or one array `[T, n, d]`), same `n` for all.
        faces: triangles `[s, 3]` or segments `[s, 2]`.
        scalars: optional per-vertex values `[n]` (all frames) or `[T, n]`, one colour range for all frames.
        fps: frames per second of playback.
        window_size, camera_position, ground_height: as in :func:`render_png`.
    """
    frames = _check_frames(frames_vertices)
    return _render_animation(
        "gif", path, frames, faces, scalars, fps, window_size, camera_position, ground_height
    )


def render_mp4(
    path: str | os.PathLike[str],
    frames_vertices: Sequence[Any],
    faces: Any,
    scalars: Any = None,
    *,
    fps: float = 20,
    window_size: tuple[int, int] = (640, 360),
    camera_position: Any = None,
    ground_height: float | None = None,
) -> Path | None:
    """Like :func:`render_gif` but writes an H.264 ``.mp4``; returns None if imageio-ffmpeg is missing.

    Inputs are validated (ValueError) even when the encoder is missing.
    """
    frames = _check_frames(frames_vertices)
    if importlib.util.find_spec("imageio") is None or importlib.util.find_spec("imageio_ffmpeg") is None:
        # Validate anyway so a caller's mistake surfaces on machines without ffmpeg too.
        _check_geometry(frames[0], faces, "frames_vertices[0]")
        logger.info("imageio-ffmpeg is not installed: skipping the movie %s", path)
        return None
    return _render_animation(
        "mp4", path, frames, faces, scalars, fps, window_size, camera_position, ground_height
    )
