"""OnRobot RG2 gripper drivers: the URCap's XML-RPC service, or a tool digital output.

Both implement ``flgd.hardware.gripper.GripperDriver``.  The measured finger width decides grasp success (FLG's
grasp reward), so a driver says whether it can measure it (``measures_width``).

XML-RPC (``gripper.driver: rg2_xmlrpc``).  The OnRobot URCap runs an XML-RPC
server on the robot controller, port 41414 (``gripper.xmlrpc_port``).  The
functions used here, as published OnRobot/URCap client code calls them:
  * ``rg_grip(tool_index: int, width_mm: float, force_N: float)`` starts a
    move (width 0..110 mm, force 0..40 N for the RG2);
  * ``rg_get_busy(tool_index) -> bool`` is true while the fingers move;
  * ``rg_get_width(tool_index) -> float`` is the finger opening in mm;
  * ``rg_get_safety_failed(tool_index) -> bool`` reports a tripped safety switch;
  * ``rg_stop(tool_index)`` halts the fingers.
The tool index is 0 for a single gripper.  Every call has a timeout
(``gripper.timeout``); slow replies, refused connections and XML-RPC faults
become :class:`GripperFault` with the host, port and function named.

Tool digital output (``gripper.driver: tool_digital_output``).  The RG2 is
wired so that a tool output closes it (``gripper.digital_output``; the UR
tool connector has outputs 0 and 1).  That wiring gives no width feedback:
ur_rtde's receive interface exposes no tool analog input, so this driver
*cannot* measure the width and grasp success needs another signal.
``width()`` raises :class:`GripperWidthUnavailable`, and ``UR5eCell``
refuses to run a learning cell with such a driver unless told otherwise.
"""

from __future__ import annotations

import http.client
import math
import socket
import time
import xmlrpc.client
from typing import Any, Callable

from flgd.config import CellConfig
from flgd.hardware.gripper import GripperDriver, GripperFault, GripperWidthUnavailable
from flgd.safety import GRIPPER_STROKE

__all__ = [
    "RG2XmlRpcDriver",
    "ToolDigitalOutputDriver",
    "make_gripper_driver",
    "RG2_MAX_FORCE",
]

RG2_MAX_FORCE = 40.0       # N
_BUSY_START_DELAY = 0.05   # s before the first busy poll: the URCap needs a moment to start the move
_WIDTH_SANITY_MM = (-5.0, 120.0)
_ALREADY_THERE = 0.0015    # m: fingers this close to a repeated width are not sent it (an RG2 stops within 1 mm)


def _check_command(width: float, force: float) -> None:
    if not (math.isfinite(width) and 0.0 <= width <= GRIPPER_STROKE):
        raise GripperFault(f"gripper width {width!r} m is outside [0, {GRIPPER_STROKE}] m")
    if not (math.isfinite(force) and 0.0 < force <= RG2_MAX_FORCE):
        raise GripperFault(f"gripper force {force!r} N is outside (0, {RG2_MAX_FORCE}] N")


class _TimeoutTransport(xmlrpc.client.Transport):
    """xmlrpc.client's transport with a socket timeout on connect and on every reply."""

    def __init__(self, timeout: float):
        super().__init__()
        self._timeout = timeout

    def make_connection(self, host: str) -> http.client.HTTPConnection:
        conn = super().make_connection(host)
        conn.timeout = self._timeout
        return conn


STOP_TIMEOUT = 1.0  # s for rg_stop's reply: a stop must not hold up the arm's stopL behind it


class RG2XmlRpcDriver(GripperDriver):
    """The RG2 through the OnRobot URCap's XML-RPC server on the controller."""

    measures_width = True

    def __init__(self, host: str, port: int = 41414, *, timeout: float = 5.0, tool_index: int = 0,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 poll_interval: float = 0.02):
        if not host:
            raise GripperFault("robot.host is empty: the RG2 XML-RPC service runs on the UR controller")
        self.host, self.port, self.timeout = host, int(port), float(timeout)
        self.tool_index = int(tool_index)
        self._clock, self._sleep, self._poll = clock, sleep, poll_interval
        self._moving: str | None = None   # the command the fingers may still be finishing (a move went on early)
        self._last_width: float | None = None   # the width last sent: only a repeat of it may already be there
        self._proxy = self._new_proxy(timeout)

    def _new_proxy(self, timeout: float) -> xmlrpc.client.ServerProxy:
        return xmlrpc.client.ServerProxy(f"http://{self.host}:{self.port}/", transport=_TimeoutTransport(timeout),
                                         allow_none=False)

    def _rpc(self, function: str, *args: Any, proxy: xmlrpc.client.ServerProxy | None = None) -> Any:
        where = f"RG2 XML-RPC {function} at {self.host}:{self.port}"
        try:
            return getattr(proxy or self._proxy, function)(self.tool_index, *args)
        except (socket.timeout, TimeoutError) as exc:
            raise GripperFault(f"{where}: no reply within {self.timeout} s (gripper.timeout)") from exc
        except ConnectionRefusedError as exc:
            raise GripperFault(f"{where}: connection refused (is the OnRobot URCap installed and running, "
                               f"and gripper.xmlrpc_port right?)") from exc
        except xmlrpc.client.Fault as exc:
            raise GripperFault(f"{where}: fault {exc.faultCode}: {exc.faultString}") from exc
        except xmlrpc.client.ProtocolError as exc:
            raise GripperFault(f"{where}: HTTP {exc.errcode} {exc.errmsg}") from exc
        except (OSError, http.client.HTTPException, xmlrpc.client.ResponseError) as exc:
            raise GripperFault(f"{where}: {type(exc).__name__}: {exc}") from exc

    def move(self, width: float, force: float, proceed_after: float = 0.0) -> None:
        _check_command(width, force)
        if self._moving is not None:   # the last move went on before the fingers stopped: they finish first
            self._wait_stopped(f"the earlier {self._moving}, which the plan went on from before it ended")
        repeat = self._last_width is not None and abs(self._last_width - width) <= _ALREADY_THERE
        start = self.width() if repeat or proceed_after > 0.0 else math.nan
        if repeat and abs(start - width) <= _ALREADY_THERE:
            self._check_safety()   # an open gripper told to open again: no move, but a tripped tool is a fault
            return
        self._last_width = None
        self._rpc("rg_grip", float(width * 1000.0), float(force))
        self._last_width = width
        command = f"rg_grip({width * 1000:.1f} mm, {force:.0f} N)"
        self._sleep(_BUSY_START_DELAY)
        deadline = self._clock() + self.timeout
        if proceed_after > 0.0:
            while self._rpc("rg_get_busy") and self._clock() <= deadline:
                if abs(self.width() - start) >= proceed_after:
                    self._moving = command
                    return
                self._sleep(self._poll)
        self._wait_stopped(command, deadline)

    def _wait_stopped(self, command: str, deadline: float | None = None) -> None:
        """Until the busy flag drops (by ``deadline``, or ``timeout`` from now), then the safety switch's state."""
        self._moving = None
        deadline = self._clock() + self.timeout if deadline is None else deadline
        while self._rpc("rg_get_busy"):
            if self._clock() > deadline:
                self.stop()
                raise GripperFault(f"RG2 at {self.host}:{self.port}: still moving {self.timeout} s after {command}")
            self._sleep(self._poll)
        self._check_safety()

    def _check_safety(self) -> None:
        if self._rpc("rg_get_safety_failed"):
            raise GripperFault(f"RG2 at {self.host}:{self.port}: safety switch tripped; power-cycle the tool "
                               f"(rg_get_safety_failed is true)")

    def width(self) -> float:
        raw = self._rpc("rg_get_width")
        if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw) \
                or not _WIDTH_SANITY_MM[0] <= raw <= _WIDTH_SANITY_MM[1]:
            raise GripperFault(f"RG2 at {self.host}:{self.port}: rg_get_width returned {raw!r}, expected a "
                               f"width in mm within {list(_WIDTH_SANITY_MM)}")
        return max(0.0, float(raw)) / 1000.0

    def stop(self) -> None:
        """Send rg_stop over a connection of its own, best effort.

        Why its own: stop comes from a signal handler or another thread while the main thread may be
        waiting for a reply on the shared connection; http.client cannot put a second request on it
        (the stop would be lost) and xmlrpc then closes it under the waiting call.
        """
        self._last_width = None
        proxy = self._new_proxy(min(self.timeout, STOP_TIMEOUT))
        try:
            self._rpc("rg_stop", proxy=proxy)
        except GripperFault:
            pass  # best effort: the caller is already handling a stop or fault
        finally:
            proxy("close")()

    def close(self) -> None:
        self._proxy("close")()


class ToolDigitalOutputDriver(GripperDriver):
    """Close = tool output high, open = low.  No width feedback (see the module docstring)."""

    measures_width = False

    def __init__(self, set_output: Callable[[int, bool], None], output: int, open_width: float,
                 closed_width: float, *, settle_time: float = 1.0, sleep: Callable[[float], None] = time.sleep):
        if output not in (0, 1):
            raise GripperFault(f"gripper.digital_output: got {output!r}, expected 0 or 1 (the UR tool connector "
                               f"has two digital outputs)")
        self._set_output = set_output
        self.output = output
        self._threshold = (open_width + closed_width) / 2.0
        self._settle = settle_time
        self._sleep = sleep

    def move(self, width: float, force: float, proceed_after: float = 0.0) -> None:
        _check_command(width, force)
        # The force is set on the gripper itself in this wiring; only open/close can be commanded.
        self._set_output(self.output, width < self._threshold)
        self._sleep(self._settle)  # no busy signal: give the fingers their travel time

    def width(self) -> float:
        raise GripperWidthUnavailable(
            "gripper.driver 'tool_digital_output' cannot measure the finger width (no feedback on this wiring), "
            "so grasp success needs another signal; use gripper.driver 'rg2_xmlrpc' with the OnRobot URCap")


def make_gripper_driver(config: CellConfig, set_tool_output: Callable[[int, bool], None], *,
                        clock: Callable[[], float] = time.monotonic,
                        sleep: Callable[[float], None] = time.sleep) -> GripperDriver:
    """The driver named by ``gripper.driver``."""
    gr = config.gripper
    if gr.driver == "rg2_xmlrpc":
        return RG2XmlRpcDriver(config.robot.host, gr.xmlrpc_port, timeout=gr.timeout, clock=clock, sleep=sleep)
    if gr.driver == "tool_digital_output":
        return ToolDigitalOutputDriver(set_tool_output, gr.digital_output, gr.open_width, gr.closed_width,
                                       sleep=sleep)
    raise GripperFault(f"gripper.driver {gr.driver!r} in {config.source} is not a real-cell driver; "
                       f"expected 'rg2_xmlrpc' or 'tool_digital_output'")
