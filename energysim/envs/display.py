"""A window that shows RGB frames, for `render_mode="human"`: Tk from the standard library.

Tk needs no package beyond Python itself, opens in a few milliseconds and shows a frame as one PPM
image, so a human-mode env costs a frame's encoding and a redraw per step. Where there is no display
(a server, a container without X) the window cannot exist, and `FrameWindow` says so when it is
created rather than at the first frame.
"""

from __future__ import annotations

import logging
import os
import sys
from types import ModuleType

import numpy as np

logger = logging.getLogger(__name__)


def display_problem() -> str | None:
    """Why no window can open here, or None where a display looks available.

    On Linux and the other X11 systems Tk draws through the X server named by `DISPLAY` (Wayland
    sessions provide one through XWayland); macOS and Windows always have a display.
    """
    if sys.platform in ("darwin", "win32", "cygwin"):
        return None
    if not os.environ.get("DISPLAY"):
        wayland = (
            " (WAYLAND_DISPLAY is set, but Tk needs XWayland's DISPLAY)"
            if os.environ.get("WAYLAND_DISPLAY")
            else ""
        )
        return f"no display: the DISPLAY environment variable is not set{wayland}"
    return None


def ppm_bytes(frame: np.ndarray) -> bytes:
    """`frame` `[height, width, 3]` uint8 as a binary PPM (P6) image, the format Tk reads directly."""
    height, width = frame.shape[:2]
    return b"P6 %d %d 255 " % (width, height) + np.ascontiguousarray(frame, dtype=np.uint8).tobytes()


def _import_tkinter() -> ModuleType:
    try:
        import tkinter
    except ImportError as error:
        raise RuntimeError(
            "render_mode='human' needs tkinter, which this Python was built without; use "
            "render_mode='rgb_array' and show the frames yourself"
        ) from error
    return tkinter


class FrameWindow:
    """A Tk window that shows one RGB frame at a time.

    Args:
        title: the window's title.

    Raises:
        RuntimeError: where no display is available or Tk cannot open a window on it; the message
            says why and names `render_mode='rgb_array'` as the way to get frames without one.
    """

    def __init__(self, title: str) -> None:
        problem = display_problem()
        if problem is not None:
            raise RuntimeError(
                f"render_mode='human' needs a display to open a window, but there is {problem}; use "
                "render_mode='rgb_array' (e.g. with gymnasium.wrappers.RecordVideo) to get frames"
            )
        tkinter = _import_tkinter()
        try:
            self._root = tkinter.Tk()
        except tkinter.TclError as error:
            raise RuntimeError(
                f"render_mode='human' could not open a window on display {os.environ.get('DISPLAY')!r}: "
                f"{error}; use render_mode='rgb_array' to get frames without one"
            ) from error
        self._tkinter = tkinter
        self._root.title(title)
        self._label = tkinter.Label(self._root)
        self._label.pack()
        self._image = None
        self.frames_shown = 0

    def show(self, frame: np.ndarray) -> None:
        """Show `frame` `[height, width, 3]` uint8 and let Tk redraw the window. Once the window is
        closed (by `close()` or by its user) frames are dropped: the simulation goes on without it."""
        if self._root is None:
            return
        try:
            # keep a reference: Tk drops an image that Python no longer holds
            self._image = self._tkinter.PhotoImage(data=ppm_bytes(frame), format="PPM")
            self._label.configure(image=self._image)
            self._root.update_idletasks()
            self._root.update()
        except self._tkinter.TclError as error:
            logger.info("the render window was closed (%s); further frames are not shown", error)
            self._root = None
            return
        self.frames_shown += 1

    def close(self) -> None:
        """Close the window (a second call does nothing)."""
        if self._root is not None:
            try:
                self._root.destroy()
            except self._tkinter.TclError:  # already closed by its user
                pass
            self._root = None


__all__ = ["FrameWindow", "display_problem", "ppm_bytes"]
