"""The viewer's page inline in a notebook: the ``<iframe>`` element and the checks of its size."""

from __future__ import annotations

import html

# Size of the inline page unless told otherwise: CSS width, height in pixels.
EMBED_WIDTH = "100%"
EMBED_HEIGHT = 480


def check_frame_size(width: object, height: object) -> None:
    """ValueError unless `width` is a positive int or a CSS length and `height` a positive int."""
    positive = isinstance(width, int) and not isinstance(width, bool) and width > 0
    css = isinstance(width, str) and bool(width) and all(c.isalnum() or c in ".%" for c in width)
    if not (positive or css):
        raise ValueError(
            f"width must be a positive number of pixels or a CSS length such as '100%', got {width!r}"
        )
    if isinstance(height, bool) or not isinstance(height, int) or height <= 0:
        raise ValueError(f"height must be a positive number of pixels, got {height!r}")


def iframe_html(url: str, width: int | str, height: int) -> str:
    """An ``<iframe>`` element showing `url`, `width` (pixels or CSS length) by `height` pixels."""
    width_css = f"{width}px" if isinstance(width, int) else width
    return (
        f'<iframe src="{html.escape(url, quote=True)}" '
        f'style="width: {html.escape(width_css, quote=True)}; height: {height}px; border: 0" '
        'title="energysim viewer"></iframe>'
    )
