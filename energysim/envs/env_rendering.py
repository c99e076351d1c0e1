"""What the environments' `render()` draws: the render options, a grid of batch entries, the window.

`CreatureEnv` and `CreatureVectorEnv` hold one `EnvRenderer` each and only pass it their states: it
keeps a `SideViewRenderer` per entry drawn (each fixed camera takes its window from its own entry's
start), tiles their frames into a grid for the vector env, and in "human" mode shows the frame in a
`FrameWindow` instead of returning it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from torch import Tensor

from energysim.envs import display
from energysim.envs.core import CreatureSimulation
from energysim.envs.rendering import CAMERAS, SideViewRenderer, check_window

RENDER_MODES = ("human", "rgb_array")
# pixels between the tiles of a grid of frames, and their colour
GRID_GAP = 2
_GRID_GAP_COLOUR = np.array([60, 60, 60], dtype=np.uint8)


def _check_pixels(value: object, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2:
        raise ValueError(f"{name} must be an integer of at least 2 pixels, got {value!r}")


@dataclass(frozen=True)
class RenderOptions:
    """How the environments render.

    Attributes:
        width, height: size in pixels of one entry's frame.
        camera: "follow" (centred on the centre of mass in every frame: the tiled ground scrolls past)
            or "fixed" (the body walks across a still view).
        camera_window: `(x_min, x_max)` in m that a fixed camera shows; None: a window 3 body lengths
            wide centred where the episode starts. Only with camera="fixed".
        entries: how many batch entries a vector env draws, the first ones, tiled in a grid.
    """

    width: int = 480
    height: int = 270
    camera: str = "follow"
    camera_window: tuple[float, float] | None = None
    entries: int = 1

    def __post_init__(self) -> None:
        _check_pixels(self.width, "render_width")
        _check_pixels(self.height, "render_height")
        if self.camera not in CAMERAS:
            raise ValueError(f"camera must be one of {CAMERAS}, got {self.camera!r}")
        if self.camera_window is not None:
            if self.camera != "fixed":
                raise ValueError(
                    f"camera_window = {self.camera_window!r} is for camera='fixed', "
                    f"got camera={self.camera!r}"
                )
            object.__setattr__(self, "camera_window", check_window(self.camera_window))
        entries = self.entries
        if isinstance(entries, bool) or not isinstance(entries, (int, np.integer)) or entries < 1:
            raise ValueError(f"render_entries must be an integer >= 1, got {entries!r}")


def check_render_mode(render_mode: object) -> None:
    """Raise ValueError unless `render_mode` is None or one of `RENDER_MODES`."""
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {list(RENDER_MODES)}, got {render_mode!r}")


def available_render_modes() -> list[str]:
    """The render modes that work here: "human" only where a display is available
    (`display.display_problem`), so that an env checker trying every declared mode passes headless."""
    return list(RENDER_MODES) if display.display_problem() is None else ["rgb_array"]


def tile_frames(frames: list[np.ndarray]) -> np.ndarray:
    """Frames `[H, W, 3]` uint8 tiled row by row into a grid of ⌈√k⌉ columns, `GRID_GAP` pixels
    apart; one frame is returned as it is. Empty cells of the last row are the gap's colour."""
    if len(frames) == 1:
        return frames[0]
    height, width = frames[0].shape[:2]
    columns = math.ceil(math.sqrt(len(frames)))
    rows = math.ceil(len(frames) / columns)
    shape = (rows * height + (rows - 1) * GRID_GAP, columns * width + (columns - 1) * GRID_GAP, 3)
    grid = np.empty(shape, dtype=np.uint8)
    grid[:] = _GRID_GAP_COLOUR
    for index, frame in enumerate(frames):
        top = (index // columns) * (height + GRID_GAP)
        left = (index % columns) * (width + GRID_GAP)
        grid[top : top + height, left : left + width] = frame
    return grid


class EnvRenderer:
    """The frames of the first `options.entries` states of a batch, returned or shown.

    Args:
        simulation: the environment's simulation (mesh, vertex masses, state layout).
        render_mode: None, "rgb_array" or "human".
        options: sizes and camera.
        title: the window's title in "human" mode.

    Raises:
        ValueError: for an unknown render mode.
        RuntimeError: in "human" mode where no window can open (`FrameWindow`).
    """

    def __init__(
        self, simulation: CreatureSimulation, render_mode: str | None, options: RenderOptions, title: str
    ) -> None:
        check_render_mode(render_mode)
        if not isinstance(options, RenderOptions):
            raise TypeError(f"options must be RenderOptions, got {type(options).__name__}")
        self.simulation = simulation
        self.render_mode = render_mode
        self.options = options
        self.window = display.FrameWindow(title) if render_mode == "human" else None
        self._renderers: list[SideViewRenderer] | None = None

    def _build(self) -> list[SideViewRenderer]:
        if self._renderers is None:
            options = self.options
            mass = self.simulation.scene.vertex_mass.detach().cpu().numpy()
            self._renderers = [
                SideViewRenderer(
                    self.simulation.creature.mesh,
                    options.width,
                    options.height,
                    camera=options.camera,
                    window=options.camera_window,
                    vertex_mass=mass,
                )
                for _ in range(options.entries)
            ]
        return self._renderers

    def reset(self, entries: Iterable[int] | None = None) -> None:
        """A new episode of `entries` (None: all): their fixed cameras take their window anew."""
        if self._renderers is None:
            return
        chosen = range(len(self._renderers)) if entries is None else entries
        for index in chosen:
            if 0 <= index < len(self._renderers):
                self._renderers[int(index)].reset()

    def frame(self, states: Tensor) -> np.ndarray:
        """The image `[H, W, 3]` uint8 of the first entries of `states` `[B, 2·n·d]` (a grid for
        more than one, see `tile_frames`)."""
        renderers = self._build()
        positions = self.simulation.scene.split_state(states[: len(renderers)])[0]
        positions = positions.detach().cpu().numpy()
        return tile_frames([renderer.render(x) for renderer, x in zip(renderers, positions, strict=True)])

    def render(self, states: Tensor | None) -> np.ndarray | None:
        """The frame in "rgb_array" mode; in "human" mode it is shown and None returned. None without
        a render mode or before the first reset (`states` None)."""
        if self.render_mode is None or states is None:
            return None
        image = self.frame(states)
        if self.window is not None:
            self.window.show(image)
            return None
        return image

    def close(self) -> None:
        """Close the window, if any, and drop the renderers."""
        if self.window is not None:
            self.window.close()
        self._renderers = None


__all__ = [
    "GRID_GAP",
    "RENDER_MODES",
    "EnvRenderer",
    "available_render_modes",
    "RenderOptions",
    "check_render_mode",
    "tile_frames",
]
