"""A loopback OnRobot RG2: an XML-RPC server on 127.0.0.1 speaking the URCap's gripper functions."""

from __future__ import annotations

import threading
import time
from socketserver import ThreadingMixIn
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer


class _QuietHandler(SimpleXMLRPCRequestHandler):
    def log_message(self, *args) -> None:  # keep test output clean
        pass


class _ThreadingXMLRPCServer(ThreadingMixIn, SimpleXMLRPCServer):
    daemon_threads = True


class LoopbackRG2:
    """An XML-RPC server on 127.0.0.1 implementing the OnRobot URCap's RG2 functions.

    The fingers take ``move_time`` seconds to travel, at a steady speed; closing stops at
    ``object_width_mm`` when an object is between them.  ``delay`` makes every
    reply slow, ``fault`` makes calls answer with an XML-RPC fault.  ``slip_mm``:
    replies of the next ``rg_get_width`` calls (an object slipping out of the
    fingers after the grip: the width keeps falling), one per call.
    """

    def __init__(self, move_time: float = 0.03):
        self.calls: list[tuple] = []
        self.width_mm = 100.0
        self.object_width_mm: float | None = None
        self.move_time = move_time
        self.delay = 0.0
        self.fault: str | None = None
        self.safety_failed = False
        self.slip_mm: list[float] = []
        self._target = self._from = self.width_mm
        self._busy_until = 0.0
        self._lock = threading.Lock()
        self.server = _ThreadingXMLRPCServer(("127.0.0.1", 0), requestHandler=_QuietHandler, logRequests=False,
                                             allow_none=False)
        for name in ("rg_grip", "rg_get_busy", "rg_get_width", "rg_get_safety_failed", "rg_stop"):
            self.server.register_function(self._wrap(name, getattr(self, "_" + name)), name)
        self.port = self.server.server_address[1]
        self._thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05},
                                        daemon=True)
        self._thread.start()

    def _wrap(self, name, fn):
        def handler(*args):
            self.calls.append((name, *args))
            if self.delay:
                time.sleep(self.delay)
            if self.fault:
                raise ValueError(self.fault)  # SimpleXMLRPCServer answers with an XML-RPC Fault
            with self._lock:
                self._settle()
                return fn(*args)
        return handler

    def _settle(self) -> None:
        now = time.monotonic()
        if now >= self._busy_until:
            self.width_mm = self._target
        elif self.move_time > 0:   # on the way: the fingers travel at a steady speed
            done = 1.0 - (self._busy_until - now) / self.move_time
            self.width_mm = self._from + (self._target - self._from) * max(0.0, min(1.0, done))

    def _rg_grip(self, tool_index: int, width: float, force: float) -> int:
        if not isinstance(tool_index, int) or not isinstance(width, float) or not isinstance(force, float):
            raise TypeError(f"rg_grip(int, double, double) called with {tool_index!r}, {width!r}, {force!r}")
        target = width
        if self.object_width_mm is not None and width < self.object_width_mm:
            target = self.object_width_mm
        self._from, self._target = self.width_mm, target
        self._busy_until = time.monotonic() + self.move_time
        return 0

    def _rg_get_busy(self, tool_index: int) -> bool:
        return time.monotonic() < self._busy_until

    def _rg_get_width(self, tool_index: int) -> float:
        if self.slip_mm:
            self.width_mm = self._target = self._from = self.slip_mm.pop(0)
        return float(self.width_mm)

    def _rg_get_safety_failed(self, tool_index: int) -> bool:
        return self.safety_failed

    def _rg_stop(self, tool_index: int) -> int:
        self._target = self._from = self.width_mm   # halted where the fingers are
        self._busy_until = 0.0
        return 0

    def names(self) -> list[str]:
        return [c[0] for c in self.calls]

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=5)
