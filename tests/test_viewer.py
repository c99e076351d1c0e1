"""The live viewer's server: what it serves, what it refuses, where it listens, and bad input."""

from __future__ import annotations

import http.client
import importlib
import json
import logging
import math
import socket
import struct
import sys
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

import energysim as es
from energysim.fem.kinematics import deformation_gradient, simplex_rest_frame
from energysim.fem.materials import lame_parameters, stable_neo_hookean_density
from energysim.viewer import Viewer, strain_energy_density


def _box_scene(cells: int = 2) -> es.Scene:
    scene = es.Scene(es.TetMesh.box(size=(0.4, 0.4, 0.4), cells=(cells, cells, cells)))
    scene.add(es.NeoHookean(youngs_modulus=1e5, poissons_ratio=0.3))
    return scene


def decode(message: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """Header and arrays of a ``/trajectory.bin`` message, read as the format's docstring defines it."""
    assert message[:4] == b"ESV1"
    (length,) = struct.unpack("<I", message[4:8])
    header = json.loads(message[8 : 8 + length])
    base = 8 + length
    assert base % 4 == 0
    arrays = {}
    for name, info in header["buffers"].items():
        dtype = {"float32": "<f4", "uint32": "<u4"}[info["dtype"]]
        count = math.prod(info["shape"])
        start = base + info["offset"]
        arrays[name] = np.frombuffer(message, dtype, count, start).reshape(info["shape"])
    return header, arrays


def _get(viewer: Viewer, path: str) -> tuple[int, bytes, http.client.HTTPResponse]:
    """GET `path` exactly as written (http.client normalises nothing), return status, body, response."""
    connection = http.client.HTTPConnection(viewer.host, viewer.port, timeout=10)
    try:
        connection.request("GET", path)
        response = connection.getresponse()
        return response.status, response.read(), response
    finally:
        connection.close()


@pytest.fixture
def served() -> Iterator[tuple[Viewer, es.Scene]]:
    scene = _box_scene()
    with Viewer(scene) as viewer:
        viewer.serve(0)
        yield viewer, scene


def _states(scene: es.Scene, frames: int, offset: float = 0.0) -> torch.Tensor:
    """`frames` states, frame f with the body shifted by (offset + f) cm in x and random velocities."""
    states = []
    for f in range(frames):
        x = scene.rest_positions + torch.tensor([0.01 * f + offset, 0.0, 0.0], dtype=torch.float64)
        states.append(scene.initial_state(x, torch.randn_like(x)))
    return torch.stack(states)


def _owner_by_search(elements: torch.Tensor, triangle: list[int]) -> int:
    owners = [e for e, tet in enumerate(elements.tolist()) if set(triangle) <= set(tet)]
    assert len(owners) == 1, "a boundary triangle belongs to exactly one tet"
    return owners[0]


# -- what is served ---------------------------------------------------------------------------------------


def test_trajectory_endpoint_returns_the_states_just_set(served) -> None:
    viewer, scene = served
    states = _states(scene, 5)
    states[:, : scene.num_dofs] += 0.003 * torch.randn(5, scene.num_dofs, dtype=torch.float64)
    element_values = torch.rand(5, scene.mesh.num_elements, dtype=torch.float64)
    vertex_values = torch.rand(scene.num_vertices, dtype=torch.float64)
    version = viewer.loop_states(
        list(states),
        vertex_scalars={"activation": vertex_values},
        element_scalars={"strain energy density": element_values},
        frame_dt=0.02,
    )
    status, body, response = _get(viewer, "/trajectory.bin")
    assert status == 200 and response.getheader("Content-Type") == "application/octet-stream"
    assert "no-store" in response.getheader("Cache-Control")
    header, arrays = decode(body)
    assert header["version"] == version and header["num_frames"] == 5 and header["frame_dt"] == 0.02

    x, _ = scene.split_state(states)
    faces = torch.as_tensor(arrays["faces"].astype(np.int64))
    points = torch.unique(scene.mesh.surface())  # the boundary vertices, each once
    assert arrays["positions"].shape == (5, len(points), 3)
    np.testing.assert_allclose(arrays["positions"], x[:, points].numpy(), rtol=1e-6, atol=1e-7)
    # each drawn triangle is a boundary triangle of the mesh, each boundary triangle drawn once
    drawn = points[faces]
    assert sorted(map(tuple, drawn.tolist())) == sorted(map(tuple, scene.mesh.surface().tolist()))

    fields = {f["name"]: f for f in header["fields"]}
    assert fields["activation"]["location"] == "point"
    np.testing.assert_allclose(
        arrays["field:activation"],
        np.broadcast_to(vertex_values[points].numpy(), (5, len(points))),
        rtol=1e-6,
    )
    owners = [_owner_by_search(scene.mesh.elements, t) for t in drawn.tolist()]
    np.testing.assert_allclose(
        arrays["field:strain energy density"], element_values[:, owners].numpy(), rtol=1e-6
    )
    assert fields["strain energy density"]["location"] == "face"
    # the colour range spans the values drawn (interior tets are never seen)
    drawn_values = element_values[:, owners]
    assert fields["strain energy density"]["min"] == pytest.approx(float(drawn_values.min()), rel=1e-6)
    assert fields["strain energy density"]["max"] == pytest.approx(float(drawn_values.max()), rel=1e-6)


def test_version_grows_with_every_change_and_markers_are_served(served) -> None:
    viewer, scene = served
    session = json.loads(_get(viewer, "/version")[1])["session"]
    assert json.loads(_get(viewer, "/version")[1]) == {"session": session, "version": viewer.version}
    before = viewer.version
    viewer.loop_states(_states(scene, 2))
    viewer.add_sphere("target", (2.0, 0.5, 0.0), 0.05, "red")
    viewer.add_box("wall", torch.tensor([1.0, 0.5, 0.0]), (0.1, 1.0, 1.0), (0.0, 0.5, 1.0))
    viewer.add_sphere("target", (2.0, 0.6, 0.0), 0.05, "#0f0")  # same name: moved, not added
    assert json.loads(_get(viewer, "/version")[1]) == {"session": session, "version": before + 4}
    header, _ = decode(_get(viewer, "/trajectory.bin")[1])
    # another viewer (e.g. after a restart on the same port) is told apart even at the same version
    assert header["session"] == session != decode(Viewer(scene).trajectory_bytes())[0]["session"]
    assert header["markers"] == [
        {
            "name": "target",
            "shape": "sphere",
            "position": [2.0, 0.6, 0.0],
            "size": [0.05],
            "color": "#00ff00",
        },
        {
            "name": "wall",
            "shape": "box",
            "position": [1.0, 0.5, 0.0],
            "size": [0.1, 1.0, 1.0],
            "color": "#0080ff",
        },
    ]
    viewer.remove_marker("wall")
    assert [m["name"] for m in decode(viewer.trajectory_bytes())[0]["markers"]] == ["target"]
    with pytest.raises(KeyError, match="no marker called 'wall'"):
        viewer.remove_marker("wall")


def test_rest_shape_is_shown_before_any_trajectory() -> None:
    scene = _box_scene()
    header, arrays = decode(Viewer(scene, ground_height=-1.0).trajectory_bytes())
    points = torch.unique(scene.mesh.surface())
    np.testing.assert_allclose(arrays["positions"][0], scene.rest_positions[points].numpy(), rtol=1e-6)
    assert header["num_frames"] == 1 and header["ground_height"] == -1.0
    assert header["frame_dt"] == pytest.approx(scene.dt)


def test_2d_mesh_draws_every_triangle_in_the_z0_plane() -> None:
    mesh = es.TriMesh.box(size=(1.0, 0.5), cells=(3, 2))
    viewer = Viewer(mesh, frame_dt=0.1)
    x = mesh.vertices + torch.tensor([0.2, 0.1], dtype=torch.float64)
    state = torch.cat([x.reshape(-1), torch.zeros(mesh.num_vertices * 2, dtype=torch.float64)])
    viewer.loop_states(state, element_scalars={"index": torch.arange(mesh.num_elements, dtype=torch.float64)})
    header, arrays = decode(viewer.trajectory_bytes())
    assert header["dim"] == 2 and header["num_faces"] == mesh.num_elements
    np.testing.assert_allclose(arrays["positions"][0, :, :2], x.numpy(), rtol=1e-6)
    assert (arrays["positions"][..., 2] == 0).all()
    np.testing.assert_array_equal(arrays["faces"], mesh.elements.numpy())
    np.testing.assert_array_equal(arrays["field:index"][0], np.arange(mesh.num_elements))


def test_page_and_its_assets_are_served(served) -> None:
    viewer, _ = served
    for path, kind in [
        ("/", "text/html"),
        ("/index.html", "text/html"),
        ("/viewer.js", "text/javascript"),
        ("/three.bundle.min.js", "text/javascript"),
        ("/THREE_LICENSE.txt", "text/plain"),
        ("/?reload=1", "text/html"),
    ]:
        status, body, response = _get(viewer, path)
        assert status == 200, path
        assert response.getheader("Content-Type").startswith(kind)
        assert int(response.getheader("Content-Length")) == len(body) > 0
    assert b'src="viewer.js"' in _get(viewer, "/")[1]
    assert b"MIT" in _get(viewer, "/THREE_LICENSE.txt")[1]
    # HEAD answers the headers only
    connection = http.client.HTTPConnection(viewer.host, viewer.port, timeout=10)
    connection.request("HEAD", "/viewer.js")
    response = connection.getresponse()
    assert response.status == 200 and response.read() == b"" and int(response.getheader("Content-Length")) > 0
    connection.close()


@pytest.mark.parametrize(
    "path",
    [
        "/../../../../etc/passwd",
        "/..%2f..%2f..%2fetc%2fpasswd",
        "/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
        "/%2E%2E/server.py",
        "/static/../server.py",
        "/../server.py",
        "/viewer.js/../server.py",
        "/..",
        "/.",
        "//etc/passwd",
        "/etc/passwd",
        "/static/index.html",
        "/static/",
        "/energysim/viewer/server.py",
        "/server.py",
        "/__init__.py",
        "/trajectory.json",
        "/index.html/",
        "http://127.0.0.1/../../etc/passwd",
        "/%00",
        "/nothing-here",
    ],
)
def test_paths_outside_the_allow_list_get_404(served, path: str) -> None:
    viewer, _ = served
    status, body, _ = _get(viewer, path)
    assert status == 404, path
    assert b"root:" not in body and b"import" not in body


def test_other_methods_are_refused(served) -> None:
    viewer, _ = served
    connection = http.client.HTTPConnection(viewer.host, viewer.port, timeout=10)
    connection.request("POST", "/trajectory.bin", body=b"x")
    assert connection.getresponse().status == 501
    connection.close()


# -- where it listens, and stopping ---------------------------------------------------------------------


def _non_loopback_address() -> str | None:
    """An address of this machine other than 127.x (connecting a UDP socket sends nothing)."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.connect(("10.254.254.254", 1))
        address = probe.getsockname()[0]
    except OSError:
        return None
    finally:
        probe.close()
    return None if address.startswith("127.") else address


def test_binds_loopback_by_default_and_other_hosts_only_when_told(served) -> None:
    viewer, _ = served
    assert viewer.host == "127.0.0.1"
    assert viewer.url == f"http://127.0.0.1:{viewer.port}/"
    other = _non_loopback_address()
    if other is not None:  # the default server is unreachable from another interface
        with pytest.raises(OSError):
            socket.create_connection((other, viewer.port), timeout=2).close()
    with Viewer(_box_scene(1)) as exposed:
        exposed.serve(0, host="0.0.0.0")
        assert exposed.host == "0.0.0.0"
        assert exposed.url == f"http://127.0.0.1:{exposed.port}/"
        if other is not None:
            socket.create_connection((other, exposed.port), timeout=2).close()


def test_stop_frees_the_port_at_once() -> None:
    viewer = Viewer(_box_scene(1))
    viewer.serve(0)
    port = viewer.port
    assert _get(viewer, "/trajectory.bin")[0] == 200  # a served connection leaves TIME_WAIT behind
    viewer.stop()
    assert not viewer.serving
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
    # as a new server would bind it: SO_REUSEADDR (allowed past TIME_WAIT, never past a live listener)
    probe = socket.socket()
    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    probe.bind(("127.0.0.1", port))
    probe.listen()
    probe.close()
    with Viewer(_box_scene(1)) as again:
        again.serve(port)
        assert again.port == port and _get(again, "/version")[0] == 200
    viewer.stop()  # stopping twice is harmless


def test_busy_port_and_double_serve_raise(served) -> None:
    viewer, _ = served
    with pytest.raises(RuntimeError, match="already serving"):
        viewer.serve(0)
    with pytest.raises(OSError, match="in use"):
        Viewer(_box_scene(1)).serve(viewer.port)
    with pytest.raises(ValueError, match="port"):
        Viewer(_box_scene(1)).serve(70000)
    with pytest.raises(RuntimeError, match="not serving"):
        _ = Viewer(_box_scene(1)).port


def test_context_manager_stops_the_server() -> None:
    with Viewer(_box_scene(1)) as viewer:
        viewer.serve(0)
        port = viewer.port
    assert not viewer.serving
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()


# -- concurrency and disconnects --------------------------------------------------------------------------


def test_concurrent_replacement_and_downloads_stay_consistent(served) -> None:
    # frame f of trajectory t has all x = t + f/100 and t + 1 frames, so any mix of two trajectories
    # inside one download would show up
    viewer, scene = served
    n, d = scene.num_vertices, scene.dim

    def trajectory(t: int) -> torch.Tensor:
        frames = torch.zeros(t + 1, 2 * n * d, dtype=torch.float64)
        x = frames[:, : n * d].view(t + 1, n, d)
        x[..., 0] = t + torch.arange(t + 1, dtype=torch.float64)[:, None] / 100
        return frames

    errors: list[str] = []
    done = threading.Event()

    def download() -> None:
        while not done.is_set():
            try:
                body = urllib.request.urlopen(viewer.url + "trajectory.bin", timeout=10).read()
                header, arrays = decode(body)
                x = arrays["positions"][..., 0]
                t = round(float(x[0, 0]))
                if header["num_frames"] != t + 1 and header["version"] > 1:
                    errors.append(f"version {header['version']}: {header['num_frames']} frames for t={t}")
                elif header["version"] > 1:
                    expected = t + np.arange(t + 1)[:, None] / 100
                    if not np.allclose(x, expected, atol=1e-5):
                        errors.append(f"version {header['version']}: positions of mixed trajectories")
            except Exception as err:  # noqa: BLE001 - any failure of a download is the finding
                errors.append(repr(err))

    threads = [threading.Thread(target=download) for _ in range(4)]
    for thread in threads:
        thread.start()
    try:
        for t in range(1, 60):
            viewer.loop_states(trajectory(t % 12 + 1))
    finally:
        done.set()
        for thread in threads:
            thread.join(timeout=20)
    assert not errors, errors[:5]


def test_client_disconnects_mid_download_are_harmless(caplog: pytest.LogCaptureFixture) -> None:
    scene = _box_scene(4)
    with Viewer(scene) as viewer:
        viewer.serve(0)
        # a few MB, more than the socket buffers take at once
        frames = scene.initial_state().expand(20000, -1)
        viewer.loop_states(frames)
        assert len(viewer.trajectory_bytes()) > 20_000_000
        caplog.set_level(logging.DEBUG, logger="energysim.viewer")
        for _ in range(3):
            client = socket.create_connection((viewer.host, viewer.port), timeout=5)
            client.sendall(f"GET /trajectory.bin HTTP/1.1\r\nHost: 127.0.0.1:{viewer.port}\r\n\r\n".encode())
            assert client.recv(1024).startswith(b"HTTP/1.0 200")
            # replace the trajectory while the download is in progress, then drop the connection with a
            # reset (linger 0) rather than a polite close
            viewer.loop_states(_states(scene, 2, offset=1.0))
            client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            client.close()
        half_open = socket.create_connection((viewer.host, viewer.port), timeout=5)
        half_open.sendall(b"GET /traj")  # a request line that never ends, then gone
        half_open.close()
        header, arrays = decode(urllib.request.urlopen(viewer.url + "trajectory.bin", timeout=10).read())
        assert header["num_frames"] == 2 and arrays["positions"][0, :, 0].min() >= 1.0
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    assert any("went away" in r.getMessage() for r in caplog.records), "no download was cut short"


def test_unknown_path_after_stop_is_refused_not_hung() -> None:
    viewer = Viewer(_box_scene(1))
    url = viewer.serve(0)
    viewer.stop()
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(url + "version", timeout=2)


# -- bad input --------------------------------------------------------------------------------------------


def test_bad_states_raise_and_leave_the_trajectory_as_it_was() -> None:
    scene = _box_scene(1)
    viewer = Viewer(scene)
    good = _states(scene, 3)
    viewer.loop_states(good)
    version, message = viewer.version, viewer.trajectory_bytes()
    width = 2 * scene.num_dofs
    with pytest.raises(ValueError, match=rf"shape \[{width}\].*got shape \[3, {width - 1}\]"):
        viewer.loop_states(good[:, :-1])
    with pytest.raises(ValueError, match="empty"):
        viewer.loop_states(torch.zeros(0, width, dtype=torch.float64))
    with pytest.raises(ValueError, match="got shape"):
        viewer.loop_states([])
    bad = good.clone()
    bad[2, 5] = math.nan
    bad[1, 0] = math.inf
    with pytest.raises(ValueError, match=r"non-finite .* frames \[1, 2\]"):
        viewer.loop_states(bad)
    huge = good.clone()
    huge[0, 0] = 1e300
    with pytest.raises(ValueError, match="float32's range"):
        viewer.loop_states(huge)
    with pytest.raises(ValueError, match="different shapes"):
        viewer.loop_states([good[0], good[1, :-3]])
    with pytest.raises(TypeError, match="numeric"):
        viewer.loop_states("states")
    with pytest.raises(ValueError, match=r"element scalar field 'psi' must have shape \[3, 6\]"):
        viewer.loop_states(good, element_scalars={"psi": torch.zeros(3, 5)})
    with pytest.raises(ValueError, match="non-finite"):
        viewer.loop_states(good, vertex_scalars={"a": torch.full((scene.num_vertices,), math.nan)})
    with pytest.raises(ValueError, match="both per vertex and per element"):
        viewer.loop_states(
            good, vertex_scalars={"a": torch.zeros(scene.num_vertices)}, element_scalars={"a": torch.zeros(6)}
        )
    with pytest.raises(ValueError, match="frame_dt"):
        viewer.loop_states(good, frame_dt=0.0)
    assert viewer.version == version and viewer.trajectory_bytes() == message
    # velocities are not drawn, so they may be anything finite or not
    free_velocities = good.clone()
    free_velocities[:, scene.num_dofs :] = math.nan
    viewer.loop_states(free_velocities)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda v: v.add_sphere("s", (0, 0, 0), 0.0), "radius must be > 0"),
        (lambda v: v.add_sphere("s", (0, 0, 0), math.nan), "radius must be 1 finite"),
        (lambda v: v.add_sphere("s", (0, 0), 0.1), "position must be 3 finite"),
        (lambda v: v.add_sphere("s", (0, 0, math.inf), 0.1), "position must be 3 finite"),
        (lambda v: v.add_sphere("s", (0, 0, 0), 0.1, "reddish"), "color must be"),
        (lambda v: v.add_sphere("s", (0, 0, 0), 0.1, "#12345g"), "color must be"),
        (
            lambda v: v.add_sphere("s", (0, 0, 0), 0.1, (1.0, 0.5, 2.0)),
            r"color components must lie in \[0, 1\]",
        ),
        (lambda v: v.add_sphere("", (0, 0, 0), 0.1), "non-empty string"),
        (lambda v: v.add_box("b", (0, 0, 0), (1, 1)), "size must be 3 finite"),
        (lambda v: v.add_box("b", (0, 0, 0), (1, -1, 1)), "size must be > 0"),
    ],
)
def test_bad_markers_raise(call, match: str) -> None:
    viewer = Viewer(_box_scene(1))
    with pytest.raises(ValueError, match=match):
        call(viewer)
    assert viewer.version == 1


def test_bad_construction_raises() -> None:
    with pytest.raises(TypeError, match="Scene or a SimplexMesh"):
        Viewer(torch.zeros(3))
    with pytest.raises(ValueError, match="ground_height"):
        Viewer(_box_scene(1), ground_height=math.nan)
    with pytest.raises(ValueError, match="frame_dt"):
        Viewer(_box_scene(1), frame_dt=-1.0)


# -- the strain-energy colouring --------------------------------------------------------------------------


def test_strain_energy_density_is_zero_for_rigid_motions_and_matches_the_density_for_uniform_strain() -> None:
    scene = _box_scene()
    rest = scene.rest_positions
    angle = 0.7
    rotation = torch.tensor(
        [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]],
        dtype=torch.float64,
    )
    F = torch.tensor([[1.1, 0.05, 0.0], [0.0, 0.95, 0.02], [0.01, 0.0, 1.03]], dtype=torch.float64)
    states = [scene.initial_state(rest @ rotation.T + 0.3), scene.initial_state(rest @ F.T)]
    density = strain_energy_density(scene, states)
    assert density.shape == (2, scene.mesh.num_elements)
    assert density[0].abs().max() < 1e-6  # J/m^3, against about 1e3 for the strained frame
    mu, lam = lame_parameters(torch.tensor(1e5, dtype=torch.float64), torch.tensor(0.3, dtype=torch.float64))
    expected = stable_neo_hookean_density(F, mu, lam)
    torch.testing.assert_close(density[1], expected.expand(scene.mesh.num_elements), rtol=1e-10, atol=1e-8)
    # and the same through the element deformation gradients computed from scratch
    inverse, _ = simplex_rest_frame(rest, scene.mesh.elements)
    per_element = stable_neo_hookean_density(
        deformation_gradient((rest @ F.T)[scene.mesh.elements], inverse), mu, lam
    )
    torch.testing.assert_close(density[1], per_element, rtol=1e-10, atol=1e-8)


def test_strain_energy_density_needs_an_elastic_term() -> None:
    scene = es.Scene(es.TetMesh.box(cells=(1, 1, 1)))
    with pytest.raises(ValueError, match="no NeoHookean term"):
        strain_energy_density(scene, [scene.initial_state()])


# -- the live example -------------------------------------------------------------------------------------


def _throw_to_target():
    scripts = str(Path(__file__).resolve().parents[1] / "scripts")
    if scripts not in sys.path:
        sys.path.insert(0, scripts)
    return importlib.import_module("throw_to_target")


@pytest.fixture
def one_thread() -> Iterator[None]:
    # a mesh this small gains nothing from intra-op threads, which only slow a busy machine down
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_throw_to_target_serve_shows_every_iteration(monkeypatch, capsys, one_thread) -> None:
    script = _throw_to_target()
    shown: list[Viewer] = []
    real_viewer = script.Viewer

    def recording_viewer(*args, **kwargs) -> Viewer:
        shown.append(real_viewer(*args, **kwargs))
        return shown[-1]

    def look_at_the_page() -> None:
        """Stands in for waiting for Ctrl+C: what the page shows at the end."""
        viewer = shown[0]
        header, arrays = decode(_get(viewer, "/trajectory.bin")[1])
        assert header["num_frames"] == 11 and header["ground_height"] == -script.BALL_RADIUS
        assert [m["name"] for m in header["markers"]] == ["target"]
        # the last flight ends with the ball's surface around the target
        centre = arrays["positions"][-1].mean(0)
        assert np.linalg.norm(centre - np.array(script.TARGET)) < 0.02
        (speed,) = header["fields"]
        assert speed["name"] == "speed (m/s)" and speed["location"] == "point"
        # the whole ball moves at one velocity, which gravity changes by g h per step
        speeds = arrays["field:speed (m/s)"]
        assert speeds.shape == (11, header["num_points"])
        np.testing.assert_allclose(speeds, speeds[:, :1].repeat(speeds.shape[1], 1), rtol=1e-5)

    monkeypatch.setattr(script, "Viewer", recording_viewer)
    monkeypatch.setattr(script, "wait_for_interrupt", look_at_the_page)
    assert script.main(["--steps", "10", "--resolution", "2", "--serve", "0"]) == 0
    out = capsys.readouterr().out
    assert "viewer: open http://127.0.0.1:" in out and "evaluations" in out
    evaluations = int(out.split(" evaluations")[0].rsplit(" ", 1)[1])
    assert shown[0].version == 2 + evaluations  # the rest shape, the target, one trajectory per evaluation
    assert not shown[0].serving
