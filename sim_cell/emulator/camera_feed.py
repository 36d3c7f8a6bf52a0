"""The D415 of the emulated cell: the simulated camera's frames served on a loopback TCP port.

The daemon reads them with ``camera.emulator: HOST:PORT`` through a librealsense software device
(``flgd.hardware.d415``); the wire format is written down once, in :mod:`flgd.hardware.frame_feed`.

Frames are rendered on request, under ``world.lock``, by the cell's own ``SimCell.capture`` (colour, uint16
depth with the simulated D415's noise, the configured intrinsics and depth scale).  Why not at a fixed rate:
a render costs tens of milliseconds of the lock the arm and fingers step under.  So a request gets a fresh
render when the world has moved since the last one (the arm's or fingers' joints, an object's pose, an object
added or removed, or :meth:`invalidate`), no more often than ``max_render_hz``, and otherwise the last render
again with a new frame number -- never a picture of a world that has moved since.

Fault injection: :meth:`CameraFeed.stop_frames` leaves every request unanswered (a camera that stops
delivering; the daemon's frame timeout turns it into a CameraFault), :meth:`CameraFeed.resume_frames` answers
again.  A client that sends anything but ``frame`` is logged and its connection closed.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from typing import Any

import numpy as np
import pybullet as p

from flgd.cell import Frame
from flgd.hardware.frame_feed import FRAME_REQUEST, MAX_LINE, frame_message, hello_line
from flgd.hardware.software_d415 import EMULATED_SERIAL

__all__ = ["CameraFeed", "DEFAULT_MAX_RENDER_HZ"]

log = logging.getLogger(__name__)

DEFAULT_MAX_RENDER_HZ = 5.0
CHANGE_TOLERANCE = 1e-3   # m, rad or quaternion units of joint or object motion that needs a new render


class CameraFeed:
    """Frames of ``world.cell``'s camera on host:port (``world``: anything with ``cell`` and ``lock``).

    ``port`` 0 asks the system for a free port (``self.port`` is the one bound after :meth:`start`).
    """

    def __init__(self, world: Any, host: str = "127.0.0.1", port: int = 0, *,
                 max_render_hz: float = DEFAULT_MAX_RENDER_HZ):
        self.world = world
        self.host, self.port = host, int(port)
        self.max_render_hz = float(max_render_hz)
        self.frames_served = 0
        self.renders = 0
        cam = world.cell.config.camera
        self.fps = cam.fps
        self.serial = cam.serial or EMULATED_SERIAL
        self._delivering = True
        self._closing = False
        self._guard = threading.Condition()
        self._render_lock = threading.Lock()
        self._frame: Frame | None = None
        self._frame_state: tuple[int, tuple[int, ...], np.ndarray] | None = None
        self._version = 0
        self._last_render = float("-inf")
        self._clock_zero = time.monotonic()
        self._sock: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._conns: set[socket.socket] = set()

    # -- lifecycle
    def start(self) -> "CameraFeed":
        """Render a first frame (its size and intrinsics make the hello) and listen; an address in use is an
        OSError naming it."""
        self._current_frame()
        sock = socket.socket(socket.AF_INET6 if ":" in self.host else socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self.port))
            sock.listen(4)
        except OSError as exc:
            sock.close()
            raise OSError(exc.errno, f"camera feed: cannot listen on {self.host}:{self.port}: "
                                     f"{exc.strerror or exc}") from exc
        self._sock = sock
        self.port = sock.getsockname()[1]
        accept = threading.Thread(target=self._accept, name="camera-feed-accept", daemon=True)
        self._threads.append(accept)
        accept.start()
        return self

    def close(self) -> None:
        """Stop listening, close every connection and join the threads; safe to call twice."""
        with self._guard:
            self._closing = True
            self._guard.notify_all()
            conns, self._conns = list(self._conns), set()
        for conn in conns + ([self._sock] if self._sock else []):
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass  # already gone
            conn.close()
        self._sock = None
        for thread in self._threads:
            thread.join(timeout=5)
        self._threads = []

    def __enter__(self) -> "CameraFeed":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def address(self) -> str:
        """``HOST:PORT`` as ``camera.emulator`` takes it."""
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"

    # -- fault injection
    def stop_frames(self) -> None:
        """Leave frame requests unanswered from now on (a camera that stops delivering)."""
        with self._guard:
            self._delivering = False

    def resume_frames(self) -> None:
        with self._guard:
            self._delivering = True
            self._guard.notify_all()

    def invalidate(self) -> None:
        """The world changed without its clock moving (a teleport, a scene edit): render afresh next time."""
        with self._guard:
            self._version += 1

    # -- frames
    def _current_frame(self) -> Frame:
        """The last render if the world is unchanged since, else a fresh one (at most ``max_render_hz``)."""
        with self._render_lock:
            if self._frame is not None and not self._moved_since(self._frame_state):
                return self._frame
            if self.max_render_hz > 0:
                wait = self._last_render + 1.0 / self.max_render_hz - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            with self.world.lock:
                self._frame_state = self._world_state()
                self._frame = self.world.cell.capture()
            self._last_render = time.monotonic()
            self.renders += 1
            return self._frame

    def _world_state(self) -> tuple[int, tuple[int, ...], np.ndarray]:
        """What the picture depends on: the arm's and fingers' joints and every object's pose."""
        with self.world.lock:
            cell = self.world.cell
            robot, client = cell._robot, cell._client
            bodies = tuple(sorted(cell._world.objects))
            values = [*robot.joints(), robot.width()]
            for body in bodies:
                position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=client)
                values += [*position, *orientation]
            return self._version, bodies, np.asarray(values)

    def _moved_since(self, then: tuple[int, tuple[int, ...], np.ndarray] | None) -> bool:
        """Whether the world differs from ``then`` by more than :data:`CHANGE_TOLERANCE` anywhere (the world's
        clock never stops, and resting bodies creep by fractions of a millimetre)."""
        now = self._world_state()
        return then is None or now[:2] != then[:2] or float(np.max(np.abs(now[2] - then[2]))) > CHANGE_TOLERANCE

    def _hello(self) -> bytes:
        frame = self._current_frame()
        h, w = frame.depth.shape
        return hello_line(w, h, self.fps, frame.intrinsics, frame.depth_scale, self.serial)

    # -- connections
    def _accept(self) -> None:
        while True:
            try:
                conn, peer = self._sock.accept()
            except OSError:
                return  # closed
            with self._guard:
                if self._closing:
                    conn.close()
                    return
                self._conns.add(conn)
                self._threads = [t for t in self._threads if t.is_alive()]
                thread = threading.Thread(target=self._serve, args=(conn, peer), name="camera-feed-client",
                                          daemon=True)
                self._threads.append(thread)
            thread.start()

    def _serve(self, conn: socket.socket, peer: Any) -> None:
        try:
            conn.sendall(self._hello())
            reader = conn.makefile("rb")
            while True:
                line = reader.readline(MAX_LINE + 1)
                if not line:
                    return  # the client went away
                if line != FRAME_REQUEST:
                    log.warning("camera feed %s: %s sent %r, expected %r; closing that connection",
                                self.address, peer, line[:80], FRAME_REQUEST)
                    return
                if not self._wait_delivering():
                    return
                frame = self._current_frame()
                with self._guard:
                    number = self.frames_served
                    self.frames_served += 1
                stamp_ms = (time.monotonic() - self._clock_zero) * 1000.0
                conn.sendall(frame_message(number, stamp_ms, frame.timestamp, frame.color, frame.depth))
        except OSError as exc:
            if not self._closing:
                log.info("camera feed %s: connection from %s ended: %s", self.address, peer, exc)
        except Exception:  # noqa: BLE001 -- a failed render ends this connection, never the emulator
            log.exception("camera feed %s: cannot serve %s", self.address, peer)
        finally:
            with self._guard:
                self._conns.discard(conn)
            conn.close()

    def _wait_delivering(self) -> bool:
        """Block while frames are stopped; False once the feed closes."""
        with self._guard:
            while not self._delivering and not self._closing:
                self._guard.wait()
            return not self._closing
