"""A live browser viewer: a small HTTP server that serves a three.js page and the trajectory it loops over.

    viewer = Viewer(scene)
    viewer.add_sphere("target", (2.0, 0.5, 0.0), 0.05, "red")
    viewer.serve(8080)                  # returns at once; open http://127.0.0.1:8080
    for it in range(iterations):
        ...
        viewer.loop_states(states)      # the open page switches to the new trajectory without a reload
    viewer.stop()

A script whose only job is to show a result ends with ``viewer.serve(8080, block=True)``: it serves until
Ctrl+C or `stop()` from another thread. In a notebook, a cell that ends with the viewer shows the page
inline (`Viewer._repr_html_`, serving on a free port first), as does ``viewer.show()`` with IPython.

The server serves a fixed set of names only: the page, its two scripts, the three.js licence, the
trajectory (``/trajectory.bin``, see `energysim.viewer.trajectory`) and ``/version``, which the page polls.
Every other path, including any with ``..``, gets 404; nothing is looked up on the file system. It
answers only requests addressed to its own host, within time, size and connection limits
(`energysim.viewer.httpd`).
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
from collections.abc import Mapping, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from energysim.mesh import SimplexMesh

from . import trajectory
from .httpd import Server, ServerLimits, open_server
from .notebook import EMBED_HEIGHT, EMBED_WIDTH, check_frame_size, iframe_html
from .page import page_assets
from .trajectory import Marker, Surface

if TYPE_CHECKING:
    from energysim.model.scene import Scene

logger = logging.getLogger(__name__)

# How often a blocked `serve`/`wait` wakes to notice Ctrl+C where a signal cannot interrupt a wait, s.
_WAKE_INTERVAL = 0.2

class Viewer:
    """Serves a scene's surface and a looping trajectory to a browser page (three.js, no network needed).

    Args:
        scene: a `Scene` (its mesh and time step are used) or a bare `SimplexMesh` (`TetMesh`: the
            boundary triangles are drawn; `TriMesh`: all triangles, in the z = 0 plane).
        ground_height: height y of the ground plane drawn, in m; None: no ground.
        frame_dt: default seconds between frames when the page plays in real time; default the
            scene's time step (1/60 s for a bare mesh).

    Until `loop_states` is called the page shows the rest shape. Thread-safe: `loop_states` and the
    marker methods may be called from any thread while pages download.
    """

    def __init__(
        self, scene: Scene | SimplexMesh, ground_height: float | None = 0.0, frame_dt: float | None = None
    ) -> None:
        mesh = scene if isinstance(scene, SimplexMesh) else getattr(scene, "mesh", None)
        if not isinstance(mesh, SimplexMesh):
            raise TypeError(f"Viewer needs a Scene or a SimplexMesh, got {type(scene).__name__}")
        if ground_height is not None:
            ground_height = trajectory.check_vector(ground_height, 1, "ground_height")[0]
        self._surface = Surface.of(mesh)
        self._ground_height = ground_height
        self._default_frame_dt = trajectory.check_frame_dt(
            frame_dt if frame_dt is not None else getattr(scene, "dt", 1.0 / 60.0)
        )
        self._assets = page_assets()
        # Writers (loop_states, markers) hold _write_lock while they pack; _lock only guards the swap of
        # the finished message, so downloads never wait for packing.
        self._write_lock = threading.Lock()
        self._lock = threading.Lock()
        # Names this viewer's content: a page left open across a restart on the same port sees a new
        # session even if the version numbers happen to agree.
        self._session = secrets.token_hex(8)
        self._version = 0
        self._markers: dict[str, Marker] = {}
        rest = mesh.vertices.numpy()[self._surface.point_ids]
        if mesh.dim == 2:
            rest = np.pad(rest, ((0, 0), (0, 1)))
        self._positions = rest[None]
        self._fields: dict[str, tuple[str, np.ndarray]] = {}
        self._frame_dt = self._default_frame_dt
        self._message = b""
        self._repack()
        self._server: Server | None = None
        self._thread: threading.Thread | None = None
        # serve and stop may run on different threads (a blocked serve, stop from a worker): one at a time.
        self._serve_lock = threading.RLock()
        self._stopped = threading.Event()
        self._stopped.set()

    # -- what is shown -------------------------------------------------------------------------------

    def loop_states(
        self,
        states: Any,
        vertex_scalars: Mapping[str, Any] | None = None,
        element_scalars: Mapping[str, Any] | None = None,
        frame_dt: float | None = None,
    ) -> int:
        """Replace the trajectory the page loops over; returns its version number.

        Args:
            states: flat states `[x.flatten(), v.flatten()]`, each shape `[2·n·d]`, as a list or a stack
                `[F, 2·n·d]` (tensor or array); positions in m. One flat state is a one-frame trajectory.
            vertex_scalars: name -> values per frame and vertex `[F, n]` (or `[n]` for every frame),
                e.g. muscle activation; the page offers each as a colouring.
            element_scalars: name -> values per frame and element `[F, m]` (or `[m]`), e.g. strain
                energy density in J/m³ from `energysim.viewer.strain_energy_density`.
            frame_dt: seconds between frames for real-time playback; default the viewer's.

        Raises ValueError for a wrong shape, an empty trajectory, non-finite values or a name used twice;
        the trajectory shown is then left as it was. Inputs are copied, so they may change afterwards.
        """
        positions = trajectory.frame_positions(states, self._surface)
        fields: dict[str, tuple[str, np.ndarray]] = {}
        for location, scalars in (("vertex", vertex_scalars), ("element", element_scalars)):
            for name, values in (scalars or {}).items():
                if not isinstance(name, str) or not name:
                    raise ValueError(f"scalar field names must be non-empty strings, got {name!r}")
                if name in fields:
                    raise ValueError(f"scalar field {name!r} is given both per vertex and per element")
                fields[name] = (
                    location,
                    trajectory.scalar_field(values, name, location, self._surface, positions.shape[0]),
                )
        dt = self._default_frame_dt if frame_dt is None else trajectory.check_frame_dt(frame_dt)
        with self._write_lock:
            self._positions, self._fields, self._frame_dt = positions, fields, dt
            return self._repack()

    def add_sphere(
        self, name: str, position: Sequence[float], radius: float, color: str | Sequence[float] = "red"
    ) -> None:
        """Draw (or move, if `name` exists) a sphere of `radius` m centred at `position` `[3]` m.

        `color`: ``#rrggbb``, ``#rgb``, a name such as ``"red"``, or an RGB triple in [0, 1].
        """
        self._set_marker(trajectory.make_marker(name, "sphere", position, [radius], color))

    def add_box(
        self,
        name: str,
        position: Sequence[float],
        size: Sequence[float],
        color: str | Sequence[float] = "gray",
    ) -> None:
        """Draw (or move) an axis-aligned box centred at `position` `[3]` m, edge lengths `size` `[3]` m."""
        self._set_marker(trajectory.make_marker(name, "box", position, size, color))

    def remove_marker(self, name: str) -> None:
        """Remove the sphere or box called `name`; KeyError if there is none."""
        with self._write_lock:
            if name not in self._markers:
                raise KeyError(f"no marker called {name!r}; markers: {sorted(self._markers)}")
            del self._markers[name]
            self._repack()

    def _set_marker(self, marker: Marker) -> None:
        with self._write_lock:
            self._markers[marker.name] = marker
            self._repack()

    def _repack(self) -> int:
        """Publish the current content under a new version; the caller holds _write_lock (or, in
        __init__, no other thread exists). Downloads in progress keep the bytes they started with."""
        version = self._version + 1
        message = trajectory.pack(
            self._session,
            version,
            self._surface,
            self._positions,
            self._fields,
            list(self._markers.values()),
            self._frame_dt,
            self._ground_height,
        )
        with self._lock:
            self._message, self._version = message, version
        return version

    @property
    def version(self) -> int:
        """Number of the content now served; it grows by one with every change."""
        with self._lock:
            return self._version

    def trajectory_bytes(self) -> bytes:
        """The message ``/trajectory.bin`` serves now (format in `energysim.viewer.trajectory`)."""
        with self._lock:
            return self._message

    # -- the server ----------------------------------------------------------------------------------

    def serve(
        self,
        port: int = 8080,
        host: str = "127.0.0.1",
        *,
        allowed_hosts: Sequence[str] = (),
        limits: ServerLimits | None = None,
        block: bool = False,
    ) -> str:
        """Start serving in a background (daemon) thread and return the page's URL, at once or, with
        `block`, once serving has ended.

        Args:
            port: TCP port; 0 picks a free one (see `port`).
            host: address to bind. The default serves this machine only; pass e.g. ``"0.0.0.0"`` to let
                other machines connect (the server has no authentication).
            allowed_hosts: further names the page may be opened under, as ``name`` or ``name:port``
                (e.g. this machine's DNS name when serving other machines, or the local port of a
                tunnel). Loopback names, the bound host and the IP address a client connected to are
                always accepted; requests naming any other host in ``Host`` get 421 (see
                `energysim.viewer.hosts`).
            limits: time, size and connection limits; default `ServerLimits()`.
            block: serve until Ctrl+C or `stop()` from another thread (see `wait`), then release the
                port and return. For a script that only shows its result: without it, the server
                thread ends with the script. The URL is logged at INFO level; choose the port (or call
                `serve` and then `wait`) to know it beforehand.

        Raises RuntimeError if already serving, OSError if the port is taken, ValueError or TypeError
        for a bad `port`, `allowed_hosts` entry, `limits` or `block`.
        """
        if not isinstance(block, bool):
            raise TypeError(f"block must be True or False, got {block!r}")
        with self._serve_lock:
            url = self._start(port, host, allowed_hosts, limits)
            stopped = self._stopped
        if block:
            self._wait_for(stopped)
        return url

    def _start(self, port: int, host: str, allowed_hosts: Sequence[str], limits: ServerLimits | None) -> str:
        """Check the arguments, bind and start the server thread; the caller holds _serve_lock."""
        if self._server is not None:
            raise RuntimeError(f"already serving at {self.url}; call stop() first")
        server = open_server(port, host, allowed_hosts, limits, self._resource)
        self._server = server
        self._stopped = threading.Event()
        self._thread = threading.Thread(
            target=server.serve_forever, args=(0.05,), name="energysim-viewer", daemon=True
        )
        self._thread.start()
        logger.info("viewer serving at %s", self.url)
        return self.url

    def wait(self) -> None:
        """Block until serving ends: `stop()` from another thread, or Ctrl+C, which stops the server
        (the port is then free) and returns normally instead of raising KeyboardInterrupt.

        Raises RuntimeError when not serving.
        """
        with self._serve_lock:
            if self._server is None:
                raise RuntimeError("the viewer is not serving; call serve() first")
            stopped = self._stopped
        self._wait_for(stopped)

    def _wait_for(self, stopped: threading.Event) -> None:
        """Block until `stopped` is set (by `stop`); Ctrl+C stops the server and returns."""
        try:
            # a timed wait, so that Ctrl+C is noticed even where a signal does not interrupt a lock
            while not stopped.wait(_WAKE_INTERVAL):
                pass
        except KeyboardInterrupt:
            logger.info("viewer: interrupted, stopping")
            self.stop()

    def stop(self) -> None:
        """Stop serving, end every open connection and close the listening socket, so the port can be
        bound again at once; a `serve(block=True)` or `wait` blocked in another thread then returns.

        Safe to call when not serving, and from any thread. Pages already open keep their last
        trajectory and show that the server is gone.
        """
        with self._serve_lock:
            server, thread = self._server, self._thread
            if server is None:
                return
            server.shutdown()
            server.close()
            if thread is not None:
                thread.join()
            self._server, self._thread = None, None
            self._stopped.set()

    # -- in a notebook -------------------------------------------------------------------------------

    def _repr_html_(self) -> str:
        """The page inline in a notebook, as an ``<iframe>`` of `url`; serves on a free loopback port
        first when not serving.

        The frame loads the URL in the notebook's browser, so that browser must reach this machine's
        server: a notebook on this machine, or a remote kernel with its port forwarded (`serve` first,
        with `allowed_hosts` when the forwarded port differs).
        """
        return iframe_html(self._ensure_serving(), EMBED_WIDTH, EMBED_HEIGHT)

    def show(self, width: int | str = EMBED_WIDTH, height: int = EMBED_HEIGHT) -> Any:
        """`IPython.display.IFrame` of the page, serving on a free loopback port first when not serving.

        Args:
            width: frame width, pixels (int) or a CSS length such as ``"100%"``.
            height: frame height, pixels.

        Raises ImportError when IPython is not installed (a notebook has it; a cell ending with the
        viewer shows the page without it), ValueError for a bad `width` or `height`.
        """
        check_frame_size(width, height)
        try:
            from IPython.display import IFrame
        except ImportError as err:
            raise ImportError(
                "Viewer.show() needs IPython (pip install 'torch-energysim[notebook]'); or end a notebook "
                "cell with the viewer, "
                f"or open {self.url if self.serving else 'the URL serve() returns'} in a browser"
            ) from err
        return IFrame(self._ensure_serving(), width=width, height=height)

    def _ensure_serving(self) -> str:
        """The URL, after starting the server on a free loopback port if it is not running."""
        with self._serve_lock:
            if self._server is None:
                self._start(0, "127.0.0.1", (), None)
            return self.url

    def _resource(self, path: str) -> tuple[bytes, str, str] | None:
        """``(body, content type, cache-control)`` served at URL `path`, or None (404)."""
        if path in self._assets:
            body, kind = self._assets[path]
            return body, kind, "no-cache"
        if path == "/trajectory.bin":
            return self.trajectory_bytes(), "application/octet-stream", "no-store"
        if path == "/version":
            body = json.dumps({"session": self._session, "version": self.version}).encode()
            return body, "application/json", "no-store"
        return None

    @property
    def serving(self) -> bool:
        """Whether the server is running."""
        return self._server is not None

    @property
    def host(self) -> str:
        """The address the server is bound to; RuntimeError when not serving."""
        return str(self._address()[0])

    @property
    def port(self) -> int:
        """The TCP port served (the one picked, after ``serve(0)``); RuntimeError when not serving."""
        return int(self._address()[1])

    @property
    def url(self) -> str:
        """``http://host:port/`` of the page; RuntimeError when not serving."""
        host = self.host
        if host in ("0.0.0.0", ""):
            host = "127.0.0.1"
        elif host == "::":
            host = "::1"
        return f"http://[{host}]:{self.port}/" if ":" in host else f"http://{host}:{self.port}/"

    def _address(self) -> tuple[Any, ...]:
        if self._server is None:
            raise RuntimeError("the viewer is not serving; call serve() first")
        return self._server.server_address

    def __enter__(self) -> Viewer:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.stop()

    def __repr__(self) -> str:
        where = self.url if self.serving else "not serving"
        return f"Viewer({self._surface.faces.shape[0]} faces, version {self.version}, {where})"
