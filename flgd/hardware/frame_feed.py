"""The emulated D415's frame feed: the wire format between ``flgd emulate``'s camera and the daemon.

Why a format of our own: librealsense has no network camera, so the emulator serves its rendered frames on a
loopback TCP port and the daemon (``camera.emulator: HOST:PORT``) pushes them into a software D415
(:mod:`flgd.hardware.software_d415`).  Both sides use this module, so the format is written down once.

The format (version 1), one TCP connection per camera:
  * On connect the feed sends one JSON line, the hello: ``{"feed": "flgd-d415", "version": 1,
    "width": W, "height": H, "fps": F, "intrinsics": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
    "depth_scale": metres per depth unit, "serial": "..."}``.
  * The client asks for each frame with the line ``frame``.  The feed answers one JSON line
    ``{"frame": N, "timestamp_ms": T, "sim_time": S, "color_bytes": W*H*3, "depth_bytes": W*H*2}``
    followed by exactly those bytes: the colour (RGB8, row-major) then the depth (Z16, little-endian).
    ``frame`` counts from 0; ``timestamp_ms`` is the feed's clock; ``sim_time`` the simulated world's.
  * A feed whose frames are stopped leaves the request unanswered, as a camera that stops delivering
    sends nothing; the client sees a read timeout and may go on waiting for the same answer.
Lines end with ``\\n`` and are at most :data:`MAX_LINE` bytes.
"""

from __future__ import annotations

import json
import socket
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["FeedError", "FeedStalled", "FeedHello", "FeedFrame", "FrameFeedClient", "hello_line", "frame_message",
           "FEED_NAME", "FEED_VERSION", "MAX_LINE", "FRAME_REQUEST"]

FEED_NAME = "flgd-d415"
FEED_VERSION = 1
MAX_LINE = 4096
FRAME_REQUEST = b"frame\n"


class FeedError(OSError):
    """The feed broke the format, or the connection closed."""


class FeedStalled(TimeoutError):
    """No answer within the timeout and nothing half-read: the request still stands."""


@dataclass(frozen=True)
class FeedHello:
    """What the feed says about its camera on connect."""

    width: int
    height: int
    fps: int
    intrinsics: np.ndarray
    depth_scale: float
    serial: str


@dataclass(frozen=True)
class FeedFrame:
    number: int
    timestamp_ms: float
    sim_time: float
    color: np.ndarray   # HxWx3 uint8, RGB
    depth: np.ndarray   # HxW uint16, raw units (x depth_scale = metres)


def hello_line(width: int, height: int, fps: int, intrinsics: np.ndarray, depth_scale: float, serial: str) -> bytes:
    """The feed's hello line (see the module docstring)."""
    return _line({"feed": FEED_NAME, "version": FEED_VERSION, "width": int(width), "height": int(height),
                  "fps": int(fps), "intrinsics": np.asarray(intrinsics, float).tolist(),
                  "depth_scale": float(depth_scale), "serial": str(serial)})


def frame_message(number: int, timestamp_ms: float, sim_time: float, color: np.ndarray, depth: np.ndarray) -> bytes:
    """One frame's header line and pixels (see the module docstring)."""
    color_bytes = np.ascontiguousarray(color, dtype=np.uint8).tobytes()
    depth_bytes = np.ascontiguousarray(depth, dtype="<u2").tobytes()
    return _line({"frame": int(number), "timestamp_ms": float(timestamp_ms), "sim_time": float(sim_time),
                  "color_bytes": len(color_bytes), "depth_bytes": len(depth_bytes)}) + color_bytes + depth_bytes


def _line(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode() + b"\n"


class FrameFeedClient:
    """One connection to a frame feed.  Every read waits at most ``timeout`` seconds."""

    def __init__(self, host: str, port: int, timeout: float):
        self.host, self.port = host, int(port)
        self._buf = bytearray()
        self._sock = socket.create_connection((host, self.port), timeout=timeout)
        try:
            self.hello = self._parse_hello(self._read_line())
        except BaseException:
            self.close()
            raise

    def request(self) -> None:
        """Ask for the next frame."""
        self._sock.sendall(FRAME_REQUEST)

    def receive(self) -> FeedFrame:
        """The answer to the last request; :class:`FeedStalled` when none came within the timeout."""
        head = self._json(self._read_line(), ("frame", "timestamp_ms", "sim_time", "color_bytes", "depth_bytes"))
        w, h = self.hello.width, self.hello.height
        if (head["color_bytes"], head["depth_bytes"]) != (w * h * 3, w * h * 2):
            raise FeedError(f"frame {head['frame']!r} carries {head['color_bytes']!r}+{head['depth_bytes']!r} bytes, "
                            f"expected {w * h * 3}+{w * h * 2} for {w}x{h}")
        color = np.frombuffer(self._read_exact(w * h * 3), np.uint8).reshape(h, w, 3)
        depth = np.frombuffer(self._read_exact(w * h * 2), "<u2").reshape(h, w).astype(np.uint16)
        return FeedFrame(int(head["frame"]), float(head["timestamp_ms"]), float(head["sim_time"]), color, depth)

    def close(self) -> None:
        """Close the connection (also ends a read waiting in another thread); safe to call twice."""
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass  # not connected any more
        self._sock.close()

    # -- internals
    def _parse_hello(self, line: bytes) -> FeedHello:
        hello = self._json(line, ("feed", "version", "width", "height", "fps", "intrinsics", "depth_scale", "serial"))
        if hello["feed"] != FEED_NAME or hello["version"] != FEED_VERSION:
            raise FeedError(f"{self.host}:{self.port} is not a {FEED_NAME} feed version {FEED_VERSION} "
                            f"(it says {hello['feed']!r} version {hello['version']!r})")
        try:
            k = np.asarray(hello["intrinsics"], float)
            out = FeedHello(int(hello["width"]), int(hello["height"]), int(hello["fps"]), k,
                            float(hello["depth_scale"]), str(hello["serial"]))
        except (TypeError, ValueError):
            out = None
        if out is None or k.shape != (3, 3) or min(out.width, out.height, out.fps) <= 0 or not out.depth_scale > 0:
            raise FeedError(f"{self.host}:{self.port}: unusable camera description {line[:200]!r}")
        return out

    def _json(self, line: bytes, keys: tuple[str, ...]) -> dict[str, Any]:
        try:
            obj = json.loads(line)
        except ValueError as exc:
            raise FeedError(f"{self.host}:{self.port} sent a line that is not JSON: {line[:80]!r}") from exc
        if not isinstance(obj, dict) or any(k not in obj for k in keys):
            raise FeedError(f"{self.host}:{self.port} sent {line[:80]!r}, expected the keys {', '.join(keys)}")
        return obj

    def _read_line(self) -> bytes:
        while b"\n" not in self._buf:
            if len(self._buf) > MAX_LINE:
                raise FeedError(f"{self.host}:{self.port} sent a line over {MAX_LINE} bytes")
            self._fill(stall_ok=not self._buf)
        line, _, rest = bytes(self._buf).partition(b"\n")
        self._buf[:] = rest
        return line

    def _read_exact(self, n: int) -> bytes:
        while len(self._buf) < n:
            self._fill(stall_ok=False)
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def _fill(self, stall_ok: bool) -> None:
        try:
            chunk = self._sock.recv(1 << 20)
        except socket.timeout as exc:
            if stall_ok:
                raise FeedStalled(f"no answer from {self.host}:{self.port}") from exc
            raise FeedError(f"{self.host}:{self.port} stopped in the middle of a message") from exc
        if not chunk:
            raise FeedError(f"{self.host}:{self.port} closed the connection")
        self._buf += chunk
