"""The viewer's server against hostile or broken clients: foreign Host headers (DNS rebinding), idle and
trickling connections, connection floods, HTTP/0.9, oversized heads, odd paths, clients that stop reading.

All on real sockets on 127.0.0.1, with short limits so that each case takes well under a second or two.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from collections.abc import Iterator

import pytest

import energysim as es
from energysim.viewer import ServerLimits, Viewer
from energysim.viewer.hosts import HostAllowList, split_authority

CONNECTION_THREAD = "energysim-viewer-connection"
FAST = ServerLimits(head_timeout=0.5, send_timeout=0.5)
# Client-side waits: far above the server's limits, so a slow machine cannot fail a test that passes.
PATIENCE = 10.0


def _mesh(cells: int = 1) -> es.TetMesh:
    return es.TetMesh.box(size=(0.4, 0.4, 0.4), cells=(cells, cells, cells))


def connection_threads() -> int:
    return sum(thread.name == CONNECTION_THREAD for thread in threading.enumerate())


def wait_until(predicate, seconds: float = PATIENCE) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def exchange(viewer: Viewer, data: bytes, timeout: float = PATIENCE) -> bytes:
    """Send `data` on a new connection and read until the server closes it; b"" if it closes silently."""
    with socket.create_connection((viewer.host, viewer.port), timeout=timeout) as client:
        client.sendall(data)
        return read_to_close(client)


def read_to_close(client: socket.socket) -> bytes:
    chunks = []
    try:
        while chunk := client.recv(65536):
            chunks.append(chunk)
    except ConnectionResetError:
        pass
    return b"".join(chunks)


def status(response: bytes) -> int:
    assert response.startswith(b"HTTP/1."), response[:200]
    return int(response.split(b" ", 2)[1])


def body(response: bytes) -> bytes:
    return response.split(b"\r\n\r\n", 1)[1]


def get(viewer: Viewer, host: str | None, path: str = "/trajectory.bin", version: str = "HTTP/1.1") -> bytes:
    head = f"GET {path} {version}\r\n" + (f"Host: {host}\r\n" if host is not None else "")
    return exchange(viewer, (head + "\r\n").encode("utf-8"))


@pytest.fixture
def viewer() -> Iterator[Viewer]:
    with Viewer(_mesh()) as served:
        served.serve(0, limits=FAST)
        yield served


# -- whose requests it answers ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "host",
    [
        "evil.example",
        "evil.example:{port}",
        "localhost.evil.example:{port}",
        "127.0.0.1.nip.io:{port}",
        "localhost:{other}",
        "127.0.0.1:{other}",
        "[::2]:{port}",
        "evil.example@localhost:{port}",
        "localhost:{port}:{port}",
        "[::1:{port}",
        "localhost:-1",
        "localhost:99999",
        "",
        "\u00e9vil.example:{port}",
    ],
)
def test_requests_for_another_host_are_refused_without_data(viewer: Viewer, host: str) -> None:
    host = host.format(port=viewer.port, other=viewer.port + 1)
    message = viewer.trajectory_bytes()
    for method in ("GET", "HEAD"):
        response = exchange(viewer, f"{method} /trajectory.bin HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
        assert status(response) == 421, host
        assert b"ESV1" not in response and message[:64] not in response


def test_absolute_form_target_is_judged_by_its_own_host(viewer: Viewer) -> None:
    # the authority in the request target takes precedence over Host (RFC 9112, 3.2.2)
    good = f"127.0.0.1:{viewer.port}"
    refused = exchange(
        viewer, f"GET http://evil.example/trajectory.bin HTTP/1.1\r\nHost: {good}\r\n\r\n".encode()
    )
    assert status(refused) == 421 and b"ESV1" not in refused
    served = exchange(
        viewer, f"GET http://{good}/trajectory.bin HTTP/1.1\r\nHost: evil.example\r\n\r\n".encode()
    )
    assert status(served) == 200 and body(served) == viewer.trajectory_bytes()


def test_missing_or_repeated_host_on_http11_is_a_bad_request(viewer: Viewer) -> None:
    assert status(get(viewer, None)) == 400
    twice = f"GET /version HTTP/1.1\r\nHost: 127.0.0.1:{viewer.port}\r\nHost: evil.example\r\n\r\n"
    assert status(exchange(viewer, twice.encode())) == 400
    # HTTP/1.0 may omit Host; no browser does, so this opens nothing to a rebinding page
    response = get(viewer, None, version="HTTP/1.0")
    assert status(response) == 200 and body(response) == viewer.trajectory_bytes()


@pytest.mark.parametrize(
    "host",
    ["localhost:{port}", "127.0.0.1:{port}", "LocalHost:{port}", "localhost", "[::1]:{port}", "127.0.0.1:"],
)
def test_requests_for_its_own_host_are_served(viewer: Viewer, host: str) -> None:
    response = get(viewer, host.format(port=viewer.port))
    assert status(response) == 200 and body(response) == viewer.trajectory_bytes()


def test_allowed_hosts_add_names_and_name_port_pairs() -> None:
    with Viewer(_mesh()) as viewer:
        viewer.serve(0, allowed_hosts=["Viewer.LAN", "localhost:9000"], limits=FAST)
        port = viewer.port
        assert status(get(viewer, f"viewer.lan:{port}")) == 200
        assert status(get(viewer, "viewer.lan")) == 200
        assert status(get(viewer, "localhost:9000")) == 200  # e.g. the local end of ssh -L 9000:...:port
        assert status(get(viewer, "viewer.lan:9000")) == 421
        assert status(get(viewer, f"other.lan:{port}")) == 421


def test_a_server_bound_to_all_interfaces_answers_addresses_it_is_reached_at_and_listed_names() -> None:
    with Viewer(_mesh()) as viewer:
        viewer.serve(0, host="0.0.0.0", limits=FAST)
        port = viewer.port
        assert status(get(viewer, f"127.0.0.1:{port}")) == 200  # the address this connection arrived on
        assert status(get(viewer, f"localhost:{port}")) == 200
        assert status(get(viewer, f"0.0.0.0:{port}")) == 421  # the wildcard names no one
        assert status(get(viewer, f"127.0.0.2:{port}")) == 421  # an address, but not the one connected to
        assert status(get(viewer, f"workstation.lan:{port}")) == 421


def test_bad_allowed_hosts_and_limits_raise_naming_the_input() -> None:
    viewer = Viewer(_mesh())
    with pytest.raises(ValueError, match="allowed_hosts entry 'http://x.lan/'"):
        viewer.serve(0, allowed_hosts=["http://x.lan/"])
    with pytest.raises(ValueError, match="allowed_hosts entry 'x.lan:70000'"):
        viewer.serve(0, allowed_hosts=["x.lan:70000"])
    with pytest.raises(TypeError, match="list of host names.*'x.lan'"):
        viewer.serve(0, allowed_hosts="x.lan")
    with pytest.raises(TypeError, match="entries must be strings"):
        viewer.serve(0, allowed_hosts=[None])
    with pytest.raises(TypeError, match="limits must be a ServerLimits"):
        viewer.serve(0, limits={"head_timeout": 1.0})
    assert not viewer.serving
    for field, value in [
        ("head_timeout", 0.0),
        ("head_timeout", float("nan")),
        ("send_timeout", -1.0),
        ("max_connections", 0),
        ("max_request_line", 1.5),
        ("max_head_bytes", True),
    ]:
        with pytest.raises(ValueError, match=f"ServerLimits.{field} must be"):
            ServerLimits(**{field: value})
    with pytest.raises(ValueError, match="max_head_bytes .* at least max_request_line"):
        ServerLimits(max_request_line=4096, max_head_bytes=1024)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("localhost", ("localhost", None)),
        ("LOCALHOST:8080", ("localhost", 8080)),
        ("127.0.0.1:80", ("127.0.0.1", 80)),
        ("[::1]:8080", ("::1", 8080)),
        ("[0:0:0:0:0:0:0:1]", ("::1", None)),
        ("::1", ("::1", None)),
        ("[::ffff:127.0.0.1]:1", ("127.0.0.1", 1)),
        ("host.lan:", ("host.lan", None)),
    ],
)
def test_split_authority_reads_names_ports_and_ipv6_literals(text: str, expected: tuple) -> None:
    assert split_authority(text) == expected


@pytest.mark.parametrize(
    "text", ["", ":80", "[::1", "[nothost]:80", "a:b", "a:1:2", "x.lan:65536", "a b", "a/b"]
)
def test_split_authority_rejects_what_is_not_a_host(text: str) -> None:
    with pytest.raises(ValueError, match="host"):
        split_authority(text)


def test_allow_list_of_a_specific_address() -> None:
    allowed = HostAllowList.build("192.0.2.7", "192.0.2.7", 8080, ())
    assert allowed.allows("192.0.2.7:8080") and allowed.allows("localhost:8080")
    assert not allowed.allows("192.0.2.8:8080") and not allowed.allows("192.0.2.7:8081")
    assert allowed.allows("[::ffff:192.0.2.8]:8080", local_address="::ffff:192.0.2.8")


# -- time, size and connection limits ---------------------------------------------------------------------


def test_idle_connections_are_closed_within_the_timeout_and_others_are_served_meanwhile(
    viewer: Viewer,
) -> None:
    baseline = connection_threads()
    idle = [socket.create_connection((viewer.host, viewer.port), timeout=PATIENCE) for _ in range(50)]
    try:
        started = time.monotonic()
        assert wait_until(lambda: connection_threads() >= baseline + 50)
        assert status(get(viewer, f"localhost:{viewer.port}")) == 200
        for client in idle:
            assert read_to_close(client) == b""  # closed without an answer
        # head_timeout is 0.5 s; without it the reads above would wait for PATIENCE and more
        assert time.monotonic() - started < PATIENCE / 2
    finally:
        for client in idle:
            client.close()
    assert wait_until(lambda: connection_threads() == baseline)


def test_a_head_that_trickles_in_is_cut_off_at_the_deadline(viewer: Viewer) -> None:
    # one byte every 0.1 s: every single read is quick, the head as a whole is not
    request = f"GET /version HTTP/1.1\r\nHost: localhost:{viewer.port}\r\nX-Pad: {'a' * 40}\r\n\r\n".encode()
    with socket.create_connection((viewer.host, viewer.port), timeout=PATIENCE) as client:
        started = time.monotonic()
        sent = 0
        try:
            for byte in request:
                client.send(bytes([byte]))
                sent += 1
                time.sleep(0.1)
        except (BrokenPipeError, ConnectionResetError):
            pass
        assert sent < len(request), "the server waited for the whole trickled head"
        assert read_to_close(client) == b""
        assert time.monotonic() - started < PATIENCE / 2


def test_http09_request_line_gets_an_answer_at_once() -> None:
    with Viewer(_mesh()) as viewer:
        viewer.serve(0, limits=ServerLimits(head_timeout=30.0))  # the answer must not be the timeout
        for line in (b"GET /\r\n", b"GET /trajectory.bin\n"):
            started = time.monotonic()
            response = exchange(viewer, line)
            assert status(response) == 400 and b"ESV1" not in response
            assert time.monotonic() - started < 5.0  # far below head_timeout


def test_each_connection_serves_one_request_even_when_keep_alive_is_asked() -> None:
    # nothing is left idle between requests: the server answers HTTP/1.0 and closes
    with Viewer(_mesh()) as viewer:
        viewer.serve(0, limits=ServerLimits(head_timeout=30.0))
        started = time.monotonic()
        request = f"GET /version HTTP/1.1\r\nHost: localhost:{viewer.port}\r\nConnection: keep-alive\r\n\r\n"
        response = exchange(viewer, request.encode())
        assert status(response) == 200 and response.startswith(b"HTTP/1.0")
        assert time.monotonic() - started < 5.0  # closed by the server, not by the 30 s head timeout


def _ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as probe:
            probe.bind(("::1", 0))
    except OSError:
        return False
    return True


@pytest.mark.skipif(not _ipv6_loopback(), reason="this machine has no IPv6 loopback")
def test_ipv6_loopback_answers_its_bracketed_literal_only() -> None:
    with Viewer(_mesh()) as viewer:
        viewer.serve(0, host="::1", limits=FAST)
        assert viewer.url == f"http://[::1]:{viewer.port}/"
        assert status(get(viewer, f"[::1]:{viewer.port}")) == 200
        assert status(get(viewer, f"localhost:{viewer.port}")) == 200
        assert status(get(viewer, f"[::2]:{viewer.port}")) == 421
        assert status(get(viewer, f"evil.example:{viewer.port}")) == 421


def test_connections_beyond_the_limit_are_refused_at_once_with_503() -> None:
    limits = ServerLimits(head_timeout=1.0, max_connections=4)
    with Viewer(_mesh()) as viewer:
        viewer.serve(0, limits=limits)
        baseline = connection_threads()
        idle = [socket.create_connection((viewer.host, viewer.port), timeout=PATIENCE) for _ in range(4)]
        try:
            assert wait_until(lambda: connection_threads() == baseline + 4)
            extra = [
                socket.create_connection((viewer.host, viewer.port), timeout=PATIENCE) for _ in range(20)
            ]
            for client in extra:
                response = read_to_close(client)
                assert response == b"" or status(response) == 503  # a reset may overtake the 503
                client.close()
            assert connection_threads() <= baseline + 4
            # once the idle ones time out, the server answers again
            for client in idle:
                assert read_to_close(client) == b""
            assert wait_until(lambda: connection_threads() == baseline)
            assert status(get(viewer, f"localhost:{viewer.port}", "/version")) == 200
        finally:
            for client in idle:
                client.close()


@pytest.mark.parametrize(
    ("head", "code"),
    [
        ("GET /" + "a" * 9000 + " HTTP/1.1\r\nHost: localhost\r\n\r\n", 414),
        ("GET / HTTP/1.1\r\nHost: localhost\r\nX-Big: " + "a" * 70000 + "\r\n\r\n", 431),
        ("GET / HTTP/1.1\r\nHost: localhost\r\n" + "X-Many: aaaaaaaaaaaaaaaaaaaa\r\n" * 4000 + "\r\n", 431),
        # under http.server's own limits (100 headers, 64 KiB a line), over max_head_bytes in all
        ("GET / HTTP/1.1\r\nHost: localhost\r\n" + f"X-Many: {'a' * 1000}\r\n" * 90 + "\r\n", 431),
    ],
)
def test_oversized_request_heads_are_refused(viewer: Viewer, head: str, code: int) -> None:
    with socket.create_connection((viewer.host, viewer.port), timeout=PATIENCE) as client:
        try:
            client.sendall(head.encode())
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server answered and closed before taking it all
        response = read_to_close(client)
    assert response == b"" or status(response) == code
    assert status(get(viewer, f"localhost:{viewer.port}", "/version")) == 200


@pytest.mark.parametrize(
    "target",
    [b"/\xc3\xa9", b"/%C3%A9", b"/trajectory.bin\xc2\xa0", b"/\xff\xfe", b"/version%00", b"/../version"],
)
def test_non_ascii_and_odd_paths_get_404(viewer: Viewer, target: bytes) -> None:
    response = exchange(
        viewer, b"GET " + target + f" HTTP/1.1\r\nHost: localhost:{viewer.port}\r\n\r\n".encode()
    )
    assert status(response) == 404 and b"ESV1" not in response


def test_a_client_that_stops_reading_is_dropped_after_the_send_timeout(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.DEBUG, logger="energysim.viewer")
    mesh = _mesh(4)
    with Viewer(mesh) as viewer:
        viewer.serve(0, limits=FAST)
        state = es.Scene(mesh).initial_state()
        viewer.loop_states(state.expand(20000, -1))
        assert len(viewer.trajectory_bytes()) > 20_000_000  # far more than socket buffers hold (a few MB)
        baseline = connection_threads()
        with socket.create_connection((viewer.host, viewer.port), timeout=PATIENCE) as client:
            client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            client.sendall(f"GET /trajectory.bin HTTP/1.1\r\nHost: localhost:{viewer.port}\r\n\r\n".encode())
            # never read: the thread must give up on its own, with the download unfinished (the
            # thread may not have started yet when the count is first read, so wait for the log too)
            went_away = lambda: any("went away" in record.getMessage() for record in caplog.records)  # noqa: E731
            assert wait_until(went_away), caplog.text
            assert wait_until(lambda: connection_threads() == baseline)
            client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))


def test_stop_ends_open_connections_and_leaves_no_thread_behind() -> None:
    before = {thread.ident for thread in threading.enumerate()}
    viewer = Viewer(_mesh())
    viewer.serve(0, limits=ServerLimits(head_timeout=60.0))
    idle = [socket.create_connection((viewer.host, viewer.port), timeout=PATIENCE) for _ in range(10)]
    try:
        assert wait_until(lambda: connection_threads() >= 10)
        started = time.monotonic()
        viewer.stop()
        assert time.monotonic() - started < PATIENCE / 2  # not the 60 s head timeout
        for client in idle:
            assert read_to_close(client) == b""
    finally:
        for client in idle:
            client.close()
    assert {thread.ident for thread in threading.enumerate()} <= before
