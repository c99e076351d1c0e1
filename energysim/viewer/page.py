"""The browser page the viewer serves: its files, shipped in `static/`, by URL path."""

from __future__ import annotations

import importlib.resources

# URL path -> (file in static/, content type). The page and its assets, nothing else.
ASSETS = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/viewer.js": ("viewer.js", "text/javascript; charset=utf-8"),
    "/three.bundle.min.js": ("three.bundle.min.js", "text/javascript; charset=utf-8"),
    "/THREE_LICENSE.txt": ("THREE_LICENSE.txt", "text/plain; charset=utf-8"),
}


def page_assets() -> dict[str, tuple[bytes, str]]:
    """URL path -> (the file's bytes, its content type), read from the package's `static/`."""
    static = importlib.resources.files(__package__) / "static"
    return {path: ((static / name).read_bytes(), kind) for path, (name, kind) in ASSETS.items()}
