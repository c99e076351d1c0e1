"""The viewer's HTTP server: answers its own host only, within time and size limits, on a bounded thread pool.

Every connection gets its own thread, but at most `ServerLimits.max_connections` at once; a connection
beyond that is answered 503 at once and closed, so idle sockets cannot pile up threads. The request
line and headers must arrive within `ServerLimits.head_timeout` seconds in all (a deadline, not a
per-read timeout, so a client that trickles a byte at a time is cut off too) and fit in
`ServerLimits.max_head_bytes`; a response whose client stops reading for `ServerLimits.send_timeout`
seconds is abandoned. Requests whose ``Host`` is not this server's (see `energysim.viewer.hosts`) get
421 and nothing else; HTTP/1.1 without ``Host`` gets 400. An HTTP/0.9 request line (``GET /`` with no
version) gets 400 and a close. `Server.close` wakes and ends every connection thread.

The server serves only GET and HEAD (other methods get 501): nothing a request does changes any
state, so there is no endpoint whose ``Origin`` would need checking.
"""

from __future__ import annotations

import errno
import http.client
import http.server
import io
import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any
from urllib.parse import urlsplit

from .hosts import HostAllowList

__all__ = ["Resource", "Server", "ServerLimits"]

logger = logging.getLogger(__name__)

# (body, content type, cache-control) of a URL path, or None for "not found".
Resource = Callable[[str], "tuple[bytes, str, str] | None"]

_DISCONNECTS = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError, TimeoutError)
_SEND_CHUNK = 64 * 1024  # bytes per send; send_timeout applies to each, so it bounds stalls, not size


@dataclass(frozen=True)
class ServerLimits:
    """Time and size limits of the viewer's server.

    Attributes:
        head_timeout: s allowed for a request's line and headers to arrive, from the moment the
            server starts waiting for them (for a new connection or for the next request on it).
        send_timeout: s a response may wait for the client to accept the next 64 KiB; a client that
            stops reading is dropped after this long.
        max_connections: connections served at once (one thread each); more are answered 503.
        max_request_line: bytes of the request line (method, path, version); longer gets 414.
        max_head_bytes: bytes of request line and headers together; more gets 431.
    """

    head_timeout: float = 5.0
    send_timeout: float = 10.0
    max_connections: int = 64
    max_request_line: int = 8192
    max_head_bytes: int = 65536

    def __post_init__(self) -> None:
        for name in ("head_timeout", "send_timeout"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (math.isfinite(value) and value > 0)
            ):
                raise ValueError(f"ServerLimits.{name} must be a finite number of seconds > 0, got {value!r}")
        for name in ("max_connections", "max_request_line", "max_head_bytes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ServerLimits.{name} must be an integer >= 1, got {value!r}")
        if self.max_head_bytes < self.max_request_line:
            raise ValueError(
                f"ServerLimits.max_head_bytes ({self.max_head_bytes}) must be at least max_request_line "
                f"({self.max_request_line}): the head includes the request line"
            )


class _HeadTooLarge(http.client.LineTooLong):
    """The request head outgrew `ServerLimits.max_head_bytes` (http.server answers LineTooLong with 431)."""

    def __init__(self, limit: int) -> None:
        http.client.HTTPException.__init__(self, f"request line and headers over {limit} bytes")


class _HeadReader(io.RawIOBase):
    """Reads a connection under the current request head's deadline and byte budget.

    Each read waits at most until the deadline, so the whole head, however it is split into
    packets, must arrive in time. Outside a head (no deadline) reads use the socket's own timeout.
    """

    def __init__(self, connection: socket.socket) -> None:
        super().__init__()
        self._connection = connection
        self._deadline: float | None = None
        self._budget: int | None = None
        self._limit = 0

    def start_head(self, timeout: float, max_bytes: int) -> None:
        self._deadline, self._budget, self._limit = time.monotonic() + timeout, max_bytes, max_bytes

    def end_head(self) -> None:
        self._deadline, self._budget = None, None

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        if self._deadline is not None:
            remaining = self._deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError("the request head did not arrive in time")
            self._connection.settimeout(remaining)
        view = memoryview(buffer).cast("B")
        if self._budget is not None:
            if self._budget <= 0:
                raise _HeadTooLarge(self._limit)
            view = view[: self._budget]
        count = self._connection.recv_into(view)
        if self._budget is not None:
            self._budget -= count
        return count


class Server(http.server.HTTPServer):
    """Serves `resource(path)` to GET and HEAD requests addressed to `allowed` hosts, within `limits`.

    Call `serve_forever` in a thread, then `shutdown` and `close`.
    """

    allow_reuse_address = True
    request_queue_size = 128  # waiting in the kernel costs no thread; a small backlog drops bursts

    def __init__(
        self,
        address: tuple[str, int],
        resource: Resource,
        limits: ServerLimits,
        allowed_hosts: tuple[str, ...],
    ) -> None:
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        self.resource = resource
        self.limits = limits
        self._slots = threading.BoundedSemaphore(limits.max_connections)
        self._lock = threading.Lock()
        self._connections: dict[socket.socket, threading.Thread] = {}
        super().__init__(address, _Handler)
        try:
            self.allowed = HostAllowList.build(
                address[0], self.server_address[0], self.server_address[1], allowed_hosts
            )
        except (TypeError, ValueError):
            self.server_close()
            raise

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            self._refuse_busy(request, client_address)
            return
        thread = threading.Thread(
            target=self._serve_connection,
            args=(request, client_address),
            name="energysim-viewer-connection",
            daemon=True,
        )
        with self._lock:
            self._connections[request] = thread
        try:
            thread.start()
        except BaseException:
            with self._lock:
                self._connections.pop(request, None)
            self._slots.release()
            raise

    def _serve_connection(self, request: socket.socket, client_address: Any) -> None:
        try:
            self.finish_request(request, client_address)
        except Exception:  # noqa: BLE001 - one connection's failure must not end the server
            self.handle_error(request, client_address)
        finally:
            with self._lock:  # off the list before it is closed, so close() never touches a closed socket
                self._connections.pop(request, None)
            self.shutdown_request(request)
            self._slots.release()

    def _refuse_busy(self, request: socket.socket, client_address: Any) -> None:
        """503 without a thread: the answer fits any fresh socket buffer, so sending never blocks."""
        logger.info("viewer: %d connections open; refusing %s", self.limits.max_connections, client_address)
        body = b"too many connections; try again\n"
        head = (
            "HTTP/1.0 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
            f"Content-Length: {len(body)}\r\nRetry-After: 1\r\nConnection: close\r\n\r\n"
        )
        try:
            request.setblocking(False)
            request.send(head.encode("ascii") + body)
        except OSError:
            pass
        self.shutdown_request(request)

    def close(self, timeout: float = 5.0) -> None:
        """Close the listening socket, wake every connection thread and wait up to `timeout` s for them."""
        self.server_close()
        with self._lock:
            threads = list(self._connections.values())
            for connection in self._connections:
                try:
                    connection.shutdown(socket.SHUT_RDWR)  # a blocked recv or send returns at once
                except OSError:
                    pass
        deadline = time.monotonic() + timeout
        for thread in threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        alive = sum(thread.is_alive() for thread in threads)
        if alive:
            logger.warning("viewer: %d connection threads still running %.1f s after close", alive, timeout)

    def handle_error(self, request: Any, client_address: Any) -> None:
        # A browser closing a tab mid-download is handled in the handler; anything here is a bug.
        logger.exception("viewer: error while serving %s", client_address)


def open_server(
    port: int, host: str, allowed_hosts: Sequence[str], limits: ServerLimits | None, resource: Resource
) -> Server:
    """A `Server` bound to (`host`, `port`) serving `resource`, after checking the arguments as
    `Viewer.serve` documents them: ValueError or TypeError naming a bad one, OSError naming a port in use."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"port must be an integer in [0, 65535], got {port!r}")
    if not isinstance(host, str):
        raise TypeError(f"host must be a string such as '127.0.0.1', got {host!r}")
    if limits is None:
        limits = ServerLimits()
    elif not isinstance(limits, ServerLimits):
        raise TypeError(f"limits must be a ServerLimits, got {type(limits).__name__}")
    if isinstance(allowed_hosts, str):
        raise TypeError(f"allowed_hosts must be a list of host names, got the string {allowed_hosts!r}")
    try:
        return Server((host, port), resource, limits, tuple(allowed_hosts))
    except OSError as err:
        if err.errno == errno.EADDRINUSE:
            raise OSError(err.errno, f"port {port} on {host} is in use; pick another or port=0") from err
        raise


class _Handler(http.server.BaseHTTPRequestHandler):
    server: Server
    server_version = "energysim-viewer"
    sys_version = ""
    # Errors on a request line without a version are still answered with a status line.
    default_request_version = "HTTP/1.0"

    def setup(self) -> None:
        super().setup()
        self._reader = _HeadReader(self.connection)
        self.rfile = io.BufferedReader(self._reader)

    def handle_one_request(self) -> None:
        limits = self.server.limits
        self._reader.start_head(limits.head_timeout, limits.max_head_bytes)
        try:
            try:
                line = self.rfile.readline(limits.max_request_line + 1)
            except _HeadTooLarge:
                line = b"x" * (limits.max_request_line + 1)
            if len(line) > limits.max_request_line:
                self.requestline, self.request_version, self.command = "", "HTTP/1.0", ""
                self.close_connection = True
                self.send_error(
                    HTTPStatus.REQUEST_URI_TOO_LONG, f"request line over {limits.max_request_line} bytes"
                )
                return
            if not line:
                self.close_connection = True
                return
            self.raw_requestline = line
            if not self.parse_request():
                self.close_connection = True
                return
            self._reader.end_head()
            self.connection.settimeout(limits.send_timeout)
            method = getattr(self, "do_" + self.command, None)
            if method is None:
                self.close_connection = True
                self.send_error(HTTPStatus.NOT_IMPLEMENTED, f"Unsupported method ({self.command!r})")
                return
            method()
            self.wfile.flush()
        except _DISCONNECTS as err:
            logger.debug("viewer: connection from %s ended: %r", self.client_address, err)
            self.close_connection = True

    def parse_request(self) -> bool:
        words = str(self.raw_requestline, "iso-8859-1").split()
        if len(words) == 2:
            # HTTP/0.9 ("GET /"): no headers follow, so reading them would wait for the deadline.
            self.requestline = str(self.raw_requestline, "iso-8859-1").rstrip("\r\n")
            self.request_version, self.command = "HTTP/1.0", ""
            self.close_connection = True
            self.send_error(HTTPStatus.BAD_REQUEST, "HTTP/0.9 requests are not served; send HTTP/1.0 or 1.1")
            return False
        return super().parse_request() and self._addressed_here()

    def _addressed_here(self) -> bool:
        """Whether the request names this server; if not, the refusal has been sent."""
        hosts = self.headers.get_all("Host") or []
        target = urlsplit(self.path) if not self.path.startswith("/") else None
        if target is not None and target.scheme and target.netloc:
            host = target.netloc  # an absolute-form target names the host itself (RFC 9112, 3.2.2)
        elif len(hosts) > 1:
            self.send_error(HTTPStatus.BAD_REQUEST, "more than one Host header")
            return False
        elif not hosts:
            if self.request_version == "HTTP/1.0":
                return True  # HTTP/1.0 may omit Host; browsers always send it
            self.send_error(HTTPStatus.BAD_REQUEST, "HTTP/1.1 request without a Host header")
            return False
        else:
            host = hosts[0]
        if self.server.allowed.allows(host, self.connection.getsockname()[0]):
            return True
        logger.info("viewer: refused a request from %s for host %r", self.client_address, host)
        self.close_connection = True
        # The host goes into the escaped body only: a header may hold line breaks, a status line may not.
        self.send_error(
            HTTPStatus.MISDIRECTED_REQUEST,
            "this server does not answer for that host",
            f"Host {host!r} is not a name of this viewer. Open the URL it printed, or list the name in "
            "Viewer.serve(allowed_hosts=[...])",
        )
        return False

    def do_GET(self) -> None:  # noqa: N802 - http.server's naming
        self._respond(send_body=True)

    def do_HEAD(self) -> None:  # noqa: N802
        self._respond(send_body=False)

    def _respond(self, send_body: bool) -> None:
        # Exact match of the path (query ignored) against fixed names: no path is ever joined or
        # resolved, so "..", "%2e%2e", "//etc/passwd" and absolute-form targets all miss and get 404.
        found = self.server.resource(urlsplit(self.path).path)
        if found is None:
            self._send(404, b"not found\n", "text/plain; charset=utf-8", "no-store", send_body)
        else:
            self._send(200, *found, send_body)

    def _send(self, status: int, body: bytes, kind: str, cache: str, send_body: bool) -> None:
        try:
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", cache)
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            if send_body:
                view = memoryview(body)
                for start in range(0, len(view), _SEND_CHUNK):
                    self.wfile.write(view[start : start + _SEND_CHUNK])
        except _DISCONNECTS:
            logger.debug("viewer: client %s went away", self.client_address)
            self.close_connection = True

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - http.server's signature
        logger.debug("viewer %s: " + format, self.address_string(), *args)
