"""The OnRobot RG2 as the URCap's XML-RPC service serves it, on the simulated cell's fingers.

``flgd.hardware.rg2.RG2XmlRpcDriver`` talks to this exactly as to the URCap on a controller (port 41414):
``rg_grip(tool_index, width_mm, force_N)`` starts a move and answers at once, ``rg_get_busy`` is true while
the fingers travel, ``rg_get_width`` is the opening between the finger pads in mm (0-110),
``rg_get_safety_failed`` reports a tripped safety switch and ``rg_stop`` halts the fingers.  Arguments are
checked as the driver sends them (int, double, double); anything else is an XML-RPC fault, never a
traceback to the client.

Why on the world's clock: the fingers travel in time, as the real ones do (110 mm in about 1 s).  A tick
registered with the world (``EmulatorWorld.add_tick``, run under ``world.lock`` before every physics step)
ramps the finger motors' target at :data:`FINGER_STROKE_SPEED`.  A closing grip ends where the pads meet an
object (the fingers stall behind the ramp; the squeeze goes on at the commanded force), and the busy flag drops
then, as the RG2's grip detection does.  The finger state is guarded by ``world.lock`` alone, so no second lock
can be taken in the wrong order.

Fault injection: :meth:`RG2Service.trip_safety` halts the fingers and refuses moves until
:meth:`RG2Service.reset_safety` (on the real tool: a power cycle).
"""

from __future__ import annotations

import logging
import threading
from socketserver import ThreadingMixIn
from typing import Any
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

from sim_cell.robot import RG2_STROKE_SPEED

__all__ = ["RG2Service", "RG2_PORT", "FINGER_STROKE_SPEED", "MAX_WIDTH_MM", "MAX_FORCE_N"]

log = logging.getLogger(__name__)

RG2_PORT = 41414
MAX_WIDTH_MM = 110.0
MAX_FORCE_N = 40.0
FINGER_STROKE_SPEED = RG2_STROKE_SPEED   # m/s of change in the opening: 110 mm in 1 s
STALL_SPEED = 2e-3            # m/s per finger below which the fingers count as stopped
STALL_TIME = 0.05             # s the fingers must stay stopped to count as stalled
GRIP_AFTER = 0.1              # s into a move before a stall behind the ramp counts as a grip
STALL_LAG = 0.003             # m by which the ramp may run ahead of stalled fingers before it is a grip
MOVE_LIMIT = 3.0              # s of simulated time after which a move ends whatever the fingers do


class _QuietHandler(SimpleXMLRPCRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:
        log.debug("rg2 xml-rpc: " + format, *args)


class _Server(ThreadingMixIn, SimpleXMLRPCServer):
    daemon_threads = True
    allow_reuse_address = True


class RG2Service:
    """The RG2's XML-RPC service on the fingers of ``world.cell`` (an ``EmulatorWorld``: its clock moves them)."""

    def __init__(self, world: Any, host: str = "127.0.0.1", port: int = RG2_PORT):
        self.world = world
        self.host, self.port = host, int(port)
        self.calls: list[str] = []             # names of the functions called, for tests and logs
        # the finger state, guarded by world.lock
        self._safety_failed = False
        self._busy = False
        self._goal = 0.0          # m, the commanded opening
        self._ramp = 0.0          # m, the opening the finger motors are driven to now
        self._force = MAX_FORCE_N
        self._moving_for = 0.0    # s of simulated time into the current move
        self._stalled_for = 0.0   # s the fingers have been stopped during it
        self._server: _Server | None = None
        self._thread: threading.Thread | None = None

    # -- lifecycle
    def start(self) -> "RG2Service":
        """Listen on host:port and join the world's clock; an address in use is an OSError naming it."""
        try:
            server = _Server((self.host, self.port), requestHandler=_QuietHandler, logRequests=False,
                             allow_none=False)
        except OSError as exc:
            raise OSError(exc.errno, f"RG2 XML-RPC service: cannot listen on {self.host}:{self.port}: "
                                     f"{exc.strerror or exc}") from exc
        for name in ("rg_grip", "rg_get_busy", "rg_get_width", "rg_get_safety_failed", "rg_stop"):
            server.register_function(self._logged(name, getattr(self, "_" + name)), name)
        self._server = server
        self.port = server.server_address[1]
        with self.world.lock:
            self._goal = self._ramp = self._robot.finger_target_width()
            self.world.add_tick(self._tick)
        self._thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="rg2-xmlrpc", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving, leave the world's clock, close the socket; safe to call twice."""
        self.world.remove_tick(self._tick)
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def __enter__(self) -> "RG2Service":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- fault injection
    def trip_safety(self) -> None:
        """The tool's safety switch trips: the fingers halt where they are and moves are refused."""
        with self.world.lock:
            self._safety_failed = True
            self._halt()

    def reset_safety(self) -> None:
        """Clear the trip (on the real tool: a power cycle of the tool)."""
        with self.world.lock:
            self._safety_failed = False

    @property
    def busy(self) -> bool:
        return self._busy

    # -- the URCap's functions
    def _logged(self, name: str, fn: Any) -> Any:
        def handler(*args: Any) -> Any:
            self.calls.append(name)
            return fn(*args)
        handler.__name__ = name
        return handler

    def _rg_grip(self, tool_index: int, width_mm: float, force_n: float) -> int:
        _check_tool(tool_index)
        if isinstance(width_mm, bool) or isinstance(force_n, bool) \
                or not isinstance(width_mm, (int, float)) or not isinstance(force_n, (int, float)):
            raise TypeError(f"rg_grip(int tool_index, double width, double force): got {width_mm!r}, {force_n!r}")
        if not 0.0 <= width_mm <= MAX_WIDTH_MM:
            raise ValueError(f"rg_grip: width {width_mm!r} mm is outside [0, {MAX_WIDTH_MM:g}] mm")
        if not 0.0 < force_n <= MAX_FORCE_N:
            raise ValueError(f"rg_grip: force {force_n!r} N is outside (0, {MAX_FORCE_N:g}] N")
        with self.world.lock:
            if self._safety_failed:
                return 0  # a tripped tool does not move; rg_get_safety_failed says why
            self._goal, self._force = width_mm / 1000.0, float(force_n)
            self._ramp = self._robot.width()   # from where the fingers are, not where the last ramp ended
            self._moving_for = self._stalled_for = 0.0
            self._busy = True
        return 0

    def _rg_get_busy(self, tool_index: int) -> bool:
        _check_tool(tool_index)
        return self._busy

    def _rg_get_width(self, tool_index: int) -> float:
        _check_tool(tool_index)
        with self.world.lock:
            width = self._robot.width()
        return float(min(max(width * 1000.0, 0.0), MAX_WIDTH_MM))

    def _rg_get_safety_failed(self, tool_index: int) -> bool:
        _check_tool(tool_index)
        return self._safety_failed

    def _rg_stop(self, tool_index: int) -> int:
        _check_tool(tool_index)
        with self.world.lock:
            self._halt()
        return 0

    # -- the fingers (under world.lock)
    @property
    def _robot(self) -> Any:
        return self.world.cell._robot

    def _halt(self) -> None:
        """Hold the fingers where they are now."""
        robot = self._robot
        self._goal = self._ramp = robot.width()
        robot.command_gripper(self._goal, self._force)
        self._busy = False

    def _tick(self, dt: float) -> None:
        """Before a physics step: end the move if the fingers arrived or stalled on an object, else ramp on."""
        if not self._busy:
            return
        robot, goal = self._robot, self._goal
        width = robot.width()
        self._moving_for += dt
        self._stalled_for = self._stalled_for + dt if robot.finger_speed() < STALL_SPEED else 0.0
        stalled = self._stalled_for >= STALL_TIME
        gripped = stalled and self._moving_for >= GRIP_AFTER and abs(self._ramp - width) > STALL_LAG
        at_goal = self._ramp == goal
        if (at_goal and (abs(width - goal) < 1e-3 or stalled)) or gripped or self._moving_for >= MOVE_LIMIT:
            robot.command_gripper(goal, self._force)   # a grip squeezes on at the commanded force
            self.world.cell._world.set_solver()
            self._busy = False
            return
        step = FINGER_STROKE_SPEED * dt
        self._ramp = goal if abs(goal - self._ramp) <= step else self._ramp + (step if goal > self._ramp else -step)
        robot.command_gripper(self._ramp, self._force)
        self.world.cell._world.set_solver()


def _check_tool(tool_index: int) -> None:
    if isinstance(tool_index, bool) or not isinstance(tool_index, int) or tool_index != 0:
        raise ValueError(f"tool_index {tool_index!r}: this RG2 is tool 0 (a single gripper)")
