"""The viewer page in a real browser: Debian's chromium, headless, driven by playwright, software WebGL.

Skips when playwright or chromium is missing (`scripts/setup_env.sh` installs both on CI: playwright from
the dev extra, chromium with apt-get). playwright never downloads a browser here: it launches the system
chromium through `executable_path`, in a fresh temporary profile.
"""

from __future__ import annotations

import io
import json
import shutil
import struct
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import torch

import energysim as es
from energysim.viewer import Viewer

sync_api = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed (pip install -e '.[dev]' installs it)"
)
Image = pytest.importorskip("PIL.Image", reason="Pillow is needed to read screenshots")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
if CHROMIUM is None:
    pytest.skip(
        "no chromium on PATH: scripts/setup_env.sh installs Debian's chromium with apt-get (as root)",
        allow_module_level=True,
    )

# Flags that work on these machines: no sandbox (root in a container), software GL, nothing phoning home.
FLAGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]
WIDTH, HEIGHT = 800, 500
TIMEOUT_MS = 30_000  # generous: the machine may be busy; a normal load takes about a second
SIZE = 0.4  # m, edge of the cube


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
        yield browser
        browser.close()


def _state(mesh: es.TetMesh, shift: tuple[float, float, float]) -> torch.Tensor:
    x = mesh.vertices + torch.tensor(shift, dtype=torch.float64)
    return torch.cat([x.reshape(-1), torch.zeros_like(x).reshape(-1)])


def _wait_for_version(page: Any, version: int) -> None:
    """Until a frame of `version` has been drawn and shown (two more animation frames: the page draws
    only when something changes, and the compositor presents a drawing one frame later)."""
    ready = f"window.__viewer && window.__viewer.renderedVersion >= {version}"
    page.wait_for_function(ready, timeout=TIMEOUT_MS)
    page.evaluate("new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))")


def _header(message: bytes) -> dict:
    (length,) = struct.unpack("<I", message[4:8])
    return json.loads(message[8 : 8 + length])


def _screenshot(page: Any) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB")).astype(np.int32)


def _body_region(page: Any, shift: tuple[float, float, float]) -> tuple[slice, slice]:
    """Rows and columns of the inner half of the cube's on-screen bounding box (inside its silhouette)."""
    corners = [
        (shift[0] + SIZE * (i - 0.5), shift[1] + SIZE * j, shift[2] + SIZE * (k - 0.5))
        for i in (0, 1)
        for j in (0, 1)
        for k in (0, 1)
    ]
    pixels = np.array([page.evaluate(f"window.__viewer.project({x}, {y}, {z})") for x, y, z in corners])
    (left, top), (right, bottom) = pixels.min(0), pixels.max(0)
    assert 0 <= left < right <= WIDTH and 0 <= top < bottom <= HEIGHT, "the cube is not fully in view"
    cx, cy, hw, hh = (left + right) / 2, (top + bottom) / 2, (right - left) / 4, (bottom - top) / 4
    return slice(round(cy - hh), round(cy + hh)), slice(round(cx - hw), round(cx + hw))


def _bluish(pixels: np.ndarray) -> float:
    """Fraction of pixels in the body's plain colour (#8fb3d9 shaded: blue well above red), not the
    background (#eef1f5) or the ground (#d9d4c7)."""
    return float(((pixels[..., 2] - pixels[..., 0]) > 30).mean())


def _yellowish(pixels: np.ndarray) -> float:
    return float(((pixels[..., 0] - pixels[..., 2]) > 60).mean())


def test_page_draws_the_body_and_follows_new_trajectories(browser: Any) -> None:
    mesh = es.TetMesh.box(size=(SIZE, SIZE, SIZE), cells=(2, 2, 2), origin=(-SIZE / 2, 0.0, -SIZE / 2))
    first, moved = (0.0, 0.0, 0.0), (0.6, 0.0, 0.0)
    with Viewer(mesh) as viewer:
        # the camera frames the first trajectory and the markers: a target behind the place the cube
        # moves to keeps that place in view
        viewer.add_sphere("target", (0.6, 0.2, -0.6), 0.08, "red")
        version = viewer.loop_states(_state(mesh, first))
        viewer.serve(0)
        page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT}, device_scale_factor=1)
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(viewer.url)
        _wait_for_version(page, version)
        before = _screenshot(page)
        rows0, cols0 = _body_region(page, first)

        # the cube is drawn where it is, in its own colour; the sky is background
        assert _bluish(before[rows0, cols0]) > 0.9
        background = np.array([0xEE, 0xF1, 0xF5])
        assert np.abs(before[rows0, cols0] - background).sum(-1).mean() > 60
        assert np.abs(before[10:40, WIDTH - 60 : WIDTH - 20] - background).max() <= 2

        # a new trajectory reaches the open page without a reload; the camera stays, so the cube moves
        version = viewer.loop_states(_state(mesh, moved))
        _wait_for_version(page, version)
        after = _screenshot(page)
        rows1, cols1 = _body_region(page, moved)
        assert cols1.start > cols0.stop, "the moved cube's region should lie right of the first one"
        assert _bluish(after[rows1, cols1]) > 0.9 and _bluish(before[rows1, cols1]) < 0.05
        assert _bluish(after[rows0, cols0]) < 0.05, "the cube is still drawn where it was"
        assert np.abs(after[rows0, cols0] - before[rows0, cols0]).sum(-1).mean() > 60

        # colouring by a per-element field: all at the top of the range but one, so the cube turns yellow
        values = torch.ones(mesh.num_elements, dtype=torch.float64)
        values[0] = 0.0
        version = viewer.loop_states(_state(mesh, moved), element_scalars={"strain energy density": values})
        _wait_for_version(page, version)
        drawn = page.evaluate("window.__viewer.framesDrawn")
        assert page.evaluate("window.__viewer.setField('strain energy density')")
        page.wait_for_function(f"window.__viewer.framesDrawn > {drawn}", timeout=TIMEOUT_MS)
        _wait_for_version(page, version)
        coloured = _screenshot(page)
        assert _yellowish(coloured[rows1, cols1]) > 0.7 and _bluish(coloured[rows1, cols1]) < 0.1
        assert page.evaluate("window.__viewer.error") is None and not errors, errors

        # the server goes away: the page says so, keeps its picture, and takes up a new server's content
        port = viewer.port
        viewer.stop()
        page.wait_for_function("window.__viewer.error !== null", timeout=TIMEOUT_MS)
    with Viewer(mesh) as restarted:
        restarted.serve(port)
        drawn = page.evaluate("window.__viewer.framesDrawn")
        session = _header(restarted.trajectory_bytes())["session"]
        shown = f"window.__viewer.session === '{session}' && window.__viewer.framesDrawn > {drawn}"
        page.wait_for_function(shown, timeout=TIMEOUT_MS)
        assert page.evaluate("window.__viewer.error") is None and not errors, errors
        page.close()
