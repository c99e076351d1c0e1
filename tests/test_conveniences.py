"""Conveniences around the core: rollout progress, a blocking and a notebook-embedded viewer, resting a body
on the ground from the top level, and `es.export` after a plain `import energysim`."""

from __future__ import annotations

import _thread
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import types
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

import energysim as es
from energysim.viewer import Viewer

ROOT = Path(__file__).resolve().parents[1]


def _falling_box() -> es.Scene:
    """A soft box under gravity, no contact: a few cheap Newton steps per rollout."""
    scene = es.Scene(es.TetMesh.box(size=(0.2, 0.2, 0.2), cells=(1, 1, 1)), dt=0.01)
    scene.add(es.NeoHookean(youngs_modulus=1e4, poissons_ratio=0.3))
    return scene


def _spun_state(scene: es.Scene) -> torch.Tensor:
    """The rest shape spinning about y, so that the elastic term does work during the rollout."""
    x = scene.rest_positions
    v = torch.stack([-x[:, 2], torch.zeros_like(x[:, 0]), x[:, 0]], dim=1)
    return scene.initial_state(x, v)


# -- rollout progress -------------------------------------------------------------------------------------


def test_progress_callback_reports_every_step_once_and_changes_no_state_or_gradient() -> None:
    scene, steps = _falling_box(), 6
    results = {}
    for label, progress, checkpoint_every in (
        ("silent", False, 0),
        ("callback", True, 0),
        ("silent, checkpointed", False, 2),
        ("callback, checkpointed", True, 2),
    ):
        calls: list[tuple[int, int]] = []
        state = _spun_state(scene).requires_grad_()
        states = es.rollout(
            scene,
            state,
            steps=steps,
            checkpoint_every=checkpoint_every,
            progress=(lambda step, total, calls=calls: calls.append((step, total))) if progress else False,
        )
        # a loss that reaches back through every step: the final height and spin
        loss = scene.split_state(states[-1])[0][:, 1].sum() + (states[-1] ** 2).sum()
        (gradient,) = torch.autograd.grad(loss, state)
        results[label] = (states.detach(), gradient)
        # each step once, in order, and none again when backward re-solves the checkpointed segments
        assert calls == ([(k, steps) for k in range(1, steps + 1)] if progress else [])
    reference_states, reference_gradient = results["silent"]
    # the body did move and spin: a bitwise comparison of states at rest would prove nothing
    assert (reference_states[-1] - reference_states[0]).abs().max() > 1e-3
    for label, (states, gradient) in results.items():
        assert torch.equal(states, reference_states), label
        assert torch.equal(gradient, reference_gradient), label


class _RecordingBar:
    """Stands in for `tqdm.tqdm`: records the total, every update and whether the bar was closed."""

    made: list[_RecordingBar] = []

    def __init__(self, total: int, **options: object) -> None:
        self.total, self.n, self.updates, self.closed = total, 0, [], False
        _RecordingBar.made.append(self)

    def update(self, count: int) -> None:
        self.updates.append(count)
        self.n += count

    def __enter__(self) -> _RecordingBar:
        return self

    def __exit__(self, *error: object) -> None:
        self.closed = True


@pytest.fixture
def recording_tqdm(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[_RecordingBar]]:
    _RecordingBar.made = []
    monkeypatch.setitem(sys.modules, "tqdm", types.SimpleNamespace(tqdm=_RecordingBar))
    yield _RecordingBar.made


def test_progress_true_moves_a_tqdm_bar_one_step_at_a_time(recording_tqdm: list[_RecordingBar]) -> None:
    scene = _falling_box()
    silent = es.rollout(scene, _spun_state(scene), steps=5)
    shown = es.rollout(scene, _spun_state(scene), steps=5, progress=True)
    assert torch.equal(shown, silent)
    (bar,) = recording_tqdm
    assert bar.total == 5 and bar.updates == [1] * 5 and bar.n == 5 and bar.closed


def test_progress_bar_is_closed_when_a_step_fails(recording_tqdm: list[_RecordingBar]) -> None:
    scene = _falling_box()
    bad_actions = torch.zeros(3, 1, dtype=torch.float64)  # the scene has no actuators
    with pytest.raises(ValueError):
        es.rollout(scene, _spun_state(scene), bad_actions, progress=True)
    (bar,) = recording_tqdm
    assert bar.closed


def test_progress_true_without_tqdm_logs_about_every_tenth_and_the_last_step(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setitem(sys.modules, "tqdm", None)  # `import tqdm` then raises ImportError
    scene = _falling_box()
    with caplog.at_level(logging.INFO, logger="energysim.integrators.rollout"):
        es.rollout(scene, _spun_state(scene), steps=23, progress=True)
    lines = [r.getMessage() for r in caplog.records if r.name == "energysim.integrators.rollout"]
    # every ceil(23 / 10) = 3 steps, and the last
    assert lines == [f"rollout: step {k}/23" for k in (*range(3, 23, 3), 23)]


@pytest.mark.parametrize("progress", ["yes", 1, None])
def test_progress_of_the_wrong_kind_is_refused(progress: object) -> None:
    scene = _falling_box()
    with pytest.raises(TypeError, match="progress must be True, False or a callable"):
        es.rollout(scene, scene.initial_state(), steps=1, progress=progress)


# -- the viewer: blocking and in a notebook -----------------------------------------------------------------


def _port_is_free(port: int) -> bool:
    """Nothing listens on `port` any more, and a new viewer can serve it at once."""
    try:
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
    except OSError:
        pass
    else:
        return False
    with Viewer(_falling_box()) as again:
        return again.serve(port) == f"http://127.0.0.1:{port}/"


def _when_serving(viewer: Viewer, then: object) -> threading.Thread:
    """A thread that waits until `viewer` answers ``/version``, records what it served, then calls `then`."""
    seen: dict[str, object] = {}

    def run() -> None:
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                port = viewer.port
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/version", timeout=5) as response:
                    seen["status"], seen["port"] = response.status, port
                break
            except (RuntimeError, OSError):
                time.sleep(0.02)
        time.sleep(0.3)  # the caller is now inside its wait, not between starting and waiting
        then()

    thread = threading.Thread(target=run, daemon=True)
    thread.seen = seen  # type: ignore[attr-defined]
    thread.start()
    return thread


def test_blocking_serve_serves_until_stop_from_another_thread_then_frees_the_port() -> None:
    viewer = Viewer(_falling_box())
    helper = _when_serving(viewer, viewer.stop)
    started = time.monotonic()
    url = viewer.serve(0, block=True)
    helper.join(5)
    seen = helper.seen  # type: ignore[attr-defined]
    assert seen["status"] == 200  # it served while blocked
    assert url == f"http://127.0.0.1:{seen['port']}/"
    assert time.monotonic() - started < 10 and not viewer.serving
    assert _port_is_free(seen["port"])


def test_blocking_serve_ends_on_ctrl_c_and_frees_the_port() -> None:
    viewer = Viewer(_falling_box())
    helper = _when_serving(viewer, _thread.interrupt_main)  # what Ctrl+C does to the main thread
    # a simulated Ctrl+C does nothing where SIGINT has another handler than Python's (a library
    # may have set one): install Python's for the test, and stop the viewer after a while if the
    # interrupt never came, so that the test fails instead of hanging
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    watchdog = threading.Timer(30.0, viewer.stop)
    watchdog.start()
    started = time.monotonic()
    try:
        viewer.serve(0, block=True)
    except KeyboardInterrupt:  # pragma: no cover - the failure this test is for
        pytest.fail("serve(block=True) let Ctrl+C escape instead of stopping")
    finally:
        watchdog.cancel()
        signal.signal(signal.SIGINT, previous)
    assert time.monotonic() - started < 30.0, "Ctrl+C did not stop the blocking serve"
    helper.join(5)
    seen = helper.seen  # type: ignore[attr-defined]
    assert seen["status"] == 200 and not viewer.serving
    assert _port_is_free(seen["port"])


def test_wait_and_bad_block_are_refused_when_they_cannot_work() -> None:
    viewer = Viewer(_falling_box())
    with pytest.raises(RuntimeError, match="not serving"):
        viewer.wait()
    with pytest.raises(TypeError, match="block must be True or False"):
        viewer.serve(0, block="yes")  # type: ignore[arg-type]
    assert not viewer.serving


def test_notebook_html_is_an_iframe_of_the_page_served_on_a_free_port() -> None:
    with Viewer(_falling_box()) as viewer:
        html = viewer._repr_html_()  # not serving yet: starts on a free loopback port
        assert viewer.serving and viewer.host == "127.0.0.1"
        assert html.startswith('<iframe src="http://127.0.0.1:') and html.endswith("</iframe>")
        src = html.split('src="', 1)[1].split('"', 1)[0]
        assert src == viewer.url
        with urllib.request.urlopen(src, timeout=5) as response:
            assert response.status == 200 and b"<html" in response.read().lower()
        # shown again: the same server, not a second one
        assert viewer._repr_html_() == html


def test_show_returns_an_ipython_iframe_of_the_url(monkeypatch: pytest.MonkeyPatch) -> None:
    made = []

    def iframe(src: str, width: object, height: object) -> tuple:
        made.append((src, width, height))
        return made[-1]

    display = types.SimpleNamespace(IFrame=iframe)
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(display=display))
    monkeypatch.setitem(sys.modules, "IPython.display", display)
    with Viewer(_falling_box()) as viewer:
        viewer.serve(0)
        assert viewer.show(width=640, height=360) == (viewer.url, 640, 360)
        with pytest.raises(ValueError, match="height must be a positive number of pixels"):
            viewer.show(height=0)
        with pytest.raises(ValueError, match="width must be"):
            viewer.show(width='100%" onload="x')


def test_show_without_ipython_says_what_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "IPython", None)
    monkeypatch.setitem(sys.modules, "IPython.display", None)
    viewer = Viewer(_falling_box())
    with pytest.raises(ImportError, match=r"Viewer.show\(\) needs IPython"):
        viewer.show()
    assert not viewer.serving  # nothing was started for a display that cannot happen


# -- resting a body on the ground ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("height", "normal", "barrier_distance"),
    [(-0.3, (0.0, 1.0, 0.0), 0.01), (0.25, (0.0, 1.0, 0.0), None), (0.1, (0.3, 1.0, -0.2), 0.004)],
)
def test_resting_state_puts_a_box_scene_at_half_the_barrier_distance_and_moves_nothing_else(
    height: float, normal: tuple[float, float, float], barrier_distance: float | None
) -> None:
    scene = es.Scene(es.TetMesh.box(size=(0.4, 0.2, 0.3), cells=(2, 1, 2), origin=(0.0, 0.5, 0.0)))
    scene.add(es.NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    scene.add(es.Ground(height, normal=normal, barrier_distance=barrier_distance))
    (ground,) = [term for term in scene.terms if isinstance(term, es.Ground)]
    expected_gap = 0.5 * (barrier_distance if barrier_distance is not None else ground.barrier_distance)
    given_v = torch.randn(scene.num_vertices, 3, dtype=torch.float64)
    before = scene.rest_positions.clone()

    normal_64 = torch.tensor(normal, dtype=torch.float64)
    unit = normal_64 / torch.linalg.vector_norm(normal_64)
    for velocities in (None, given_v):
        state = es.resting_state(scene, velocities=velocities)
        assert state.shape == (2 * scene.num_dofs,)
        x, v = (part.reshape(scene.num_vertices, 3) for part in scene.split_state(state))
        # the lowest vertex along the normal, measured independently of the ground's own distance
        torch.testing.assert_close((x @ unit).min(), torch.tensor(height + expected_gap, dtype=torch.float64))
        # one rigid shift along the normal, the same for every vertex: the shape is untouched
        shift = x - scene.rest_positions
        torch.testing.assert_close(shift, shift[:1].expand_as(shift), rtol=0, atol=1e-12)
        torch.testing.assert_close(shift[0], (shift[0] @ unit) * unit, rtol=0, atol=1e-12)
        expected_v = torch.zeros_like(x) if velocities is None else given_v
        assert torch.equal(v, expected_v)
    assert torch.equal(scene.rest_positions, before)  # the scene is not changed


def test_resting_state_without_a_ground_names_what_is_missing() -> None:
    scene = es.Scene(es.TetMesh.box(cells=(1, 1, 1)))
    with pytest.raises(ValueError, match="expected one Ground term"):
        es.resting_state(scene)


# -- es.export after import energysim ----------------------------------------------------------------------


def test_export_is_reachable_after_a_plain_import_and_gymnasium_is_not_loaded() -> None:
    probe = (
        "import sys\n"
        "import energysim as es\n"
        "assert 'gymnasium' not in sys.modules, 'import energysim loaded gymnasium'\n"
        "assert 'energysim.export' not in sys.modules, 'es.export was not lazy'\n"
        "assert callable(es.export.export_rollout)\n"
        "assert 'gymnasium' not in sys.modules, 'es.export loaded gymnasium'\n"
        "print(es.export.export_rollout.__module__)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().startswith("energysim.export")
