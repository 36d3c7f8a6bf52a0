"""The UR arm's documented recovery sequence (``URRecovery.recover``), a part of ``flgd.hardware.ur_arm.URArm``.

Recovery sequence (:meth:`URArm.recover`), in this order:
  1. after a lost link (an interface disconnected, or ur_rtde's process ended:
     flgd/hardware/rtde_process.py) drop every interface and open fresh ones,
     as a restarted service would; ur_rtde's own ``reconnect`` is not used:
     against a dropped link its control interface kept failing ("write:
     Broken pipe") until the process was restarted;
  2. refuse while an emergency stop is engaged (or a safeguard stop, a safety
     violation/fault, recovery mode, or the arm is not powered on): those need
     a person at the cell;
  3. after a protective stop, wait until at least 5 s have passed since it
     happened (the controller refuses to unlock sooner), then
     ``unlockProtectiveStop`` on the dashboard server;
  4. ``closeSafetyPopup``;
  5. confirm the safety mode is NORMAL;
  6. open the RTDE control (and IO) interfaces if they are not open;
  7. re-upload the control script if it is not running, and confirm it runs;
  8. read the installation's TCP if the script was re-uploaded (a blended path
     runs in a fresh script, which starts with it), then set the TCP again (a
     new script starts with the installation's TCP).
Moving home is the cell's job (a checked ``plan_home``).  A pending stop
request refuses recovery (before, during the protective-stop wait, and
before the fault is cleared) with :class:`flgd.cell.StopPending`.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable, Protocol

from flgd.cell import CellFault, StopPending
from flgd.hardware.rtde_process import RTDEFactory
from flgd.hardware.ur_modes import (EMERGENCY, NEEDS_A_PERSON, NORMAL, PROTECTIVE, ROBOT_MODES, ROBOT_RUNNING,
                                    SAFETY_MODES)

__all__ = ["URRecovery", "PROTECTIVE_STOP_UNLOCK_DELAY", "DASHBOARD_TIMEOUT_MS"]

log = logging.getLogger("flgd.hardware.ur_arm")

PROTECTIVE_STOP_UNLOCK_DELAY = 5.0  # s; the controller refuses "unlock protective stop" sooner
_UNLOCK_MARGIN = 0.2                # s on top of it, for clock differences with the controller
CONFIRM_TIMEOUT = 3.0               # s to see NORMAL safety mode / a running script after recovery
DASHBOARD_TIMEOUT_MS = 2000
UNLOCK_WAIT_STEP = 0.05             # s; the protective-stop wait looks for a stop request this often


class _Arm(Protocol):
    """What the recovery uses of the arm it is part of (``flgd.hardware.ur_arm.URArm``)."""

    host: str
    tcp: list[float]
    control: Any
    io: Any
    receive: Any
    dashboard: Any
    _factory: RTDEFactory
    _lock: threading.RLock
    _stop_requested: threading.Event
    _fault: str | None
    _protective_since: float | None
    _poll: float
    _clock: Callable[[], float]
    _sleep: Callable[[float], None]

    def _call(self, iface: Any, method: str, *args: Any) -> Any: ...
    def _require(self, ok: object, what: str) -> None: ...
    def _open_control(self) -> None: ...
    def _read_installation_tcp(self) -> None: ...
    def connect(self) -> None: ...
    def _refuse_if_stopped(self, when: str) -> None: ...
    def _wait_for_unlock(self) -> None: ...
    def _link_lost(self) -> bool: ...
    def _reopen(self) -> None: ...
    def _confirm(self, condition: Callable[[], bool], message: Callable[[], str]) -> None: ...


class URRecovery:
    """The recovery steps of ``URArm`` (its connections, clock and fault latch are the arm's own)."""

    _fault: str | None              # why the arm is latched (None: it is not)
    _protective_since: float | None  # when the protective stop being recovered from began (the arm's clock)

    def _refuse_if_stopped(self: _Arm, when: str) -> None:
        if self._stop_requested.is_set():
            raise StopPending(f"UR {self.host}: recovery refused {when}: a stop was requested; the arm was not "
                              f"moved and stays in FAULT until a reset after the stop")

    def recover(self: _Arm) -> None:
        """Run the recovery sequence (module docstring); raise CellFault if it cannot complete.

        Raises StopPending, and leaves the fault latched, when a stop request is
        pending or arrives during the sequence: a recovery must never clear a stop.
        """
        with self._lock:
            self._refuse_if_stopped("before it started")
            if self._link_lost():
                self._reopen()
            if self._call(self.receive, "isEmergencyStopped"):
                raise CellFault(f"UR {self.host}: emergency stop engaged: release it at the cell and "
                                f"reset again (recovery refused)")
            mode = int(self._call(self.receive, "getSafetyMode"))
            if mode in EMERGENCY:
                raise CellFault(f"UR {self.host}: safety mode {SAFETY_MODES[mode]}: release the emergency stop "
                                f"and reset again (recovery refused)")
            if mode in NEEDS_A_PERSON:
                raise CellFault(f"UR {self.host}: {NEEDS_A_PERSON[mode]} (recovery refused)")
            if not self._call(self.dashboard, "isConnected"):
                self._call(self.dashboard, "connect", DASHBOARD_TIMEOUT_MS)
            if mode == PROTECTIVE or self._call(self.receive, "isProtectiveStopped"):
                if self._protective_since is None:
                    self._protective_since = self._clock()
                self._wait_for_unlock()
                try:
                    self._call(self.dashboard, "unlockProtectiveStop")
                except CellFault as exc:
                    raise CellFault(f"UR {self.host}: the dashboard refused to unlock the protective stop: "
                                    f"{exc}") from exc
            self._call(self.dashboard, "closeSafetyPopup")
            self._confirm(lambda: int(self._call(self.receive, "getSafetyMode")) == NORMAL,
                          lambda: f"safety mode is "
                                  f"{SAFETY_MODES.get(int(self._call(self.receive, 'getSafetyMode')))}, "
                                  f"expected NORMAL after recovery")
            robot_mode = int(self._call(self.receive, "getRobotMode"))
            if robot_mode != ROBOT_RUNNING:
                raise CellFault(f"UR {self.host}: robot mode {ROBOT_MODES.get(robot_mode, robot_mode)}: power on "
                                f"and release the brakes on the pendant, then reset again")
            if self.control is None:
                self._open_control()
            reuploaded = not self._call(self.control, "isProgramRunning")
            if reuploaded:
                self._require(self._call(self.control, "reuploadScript"), "reuploadScript")
            self._confirm(lambda: bool(self._call(self.control, "isProgramRunning")),
                          lambda: "the ur_rtde control script does not run after re-upload")
            if reuploaded:
                self._read_installation_tcp()
            self._require(self._call(self.control, "setTcp", list(self.tcp)), "setTcp")
            self._refuse_if_stopped("at its end")
            self._fault = None
            self._protective_since = None

    def _wait_for_unlock(self: _Arm) -> None:
        """Wait out the controller's 5 s before an unlock, in short steps, so a stop request cuts it short."""
        assert self._protective_since is not None   # set by recover() before it waits
        deadline = self._protective_since + PROTECTIVE_STOP_UNLOCK_DELAY + _UNLOCK_MARGIN
        while True:
            self._refuse_if_stopped("during the protective-stop wait")
            left = deadline - self._clock()
            if left <= 0:
                return
            self._sleep(min(left, UNLOCK_WAIT_STEP))

    def _link_lost(self: _Arm) -> bool:
        """Whether an interface is gone: never opened, its process ended, or its connection dropped."""
        for iface in (self.receive, self.dashboard, self.control, self.io):
            if iface is not None and getattr(iface, "process_alive", True) is False:
                return True
        if self.receive is None or self.dashboard is None:
            return True
        try:
            return not (self._call(self.receive, "isConnected")
                        and (self.control is None or self._call(self.control, "isConnected"))
                        and (self.io is None or self._call(self.io, "isConnected")))
        except CellFault:
            return True

    def _reopen(self: _Arm) -> None:
        """Drop every interface (and ur_rtde's process) and open fresh ones; CellFault if the controller cannot
        be reached.  A robot that is not ready leaves the control interface closed, for the steps that follow."""
        log.warning("UR %s: the link to the controller was lost; opening fresh connections", self.host)
        restart = getattr(self._factory, "restart", None)
        if restart is not None:
            restart()  # ends ur_rtde's process: its interfaces go with it, whatever state their threads are in
        else:
            for iface in (self.control, self.io, self.receive, self.dashboard):
                if iface is not None:
                    try:
                        self._call(iface, "disconnect")
                    except CellFault:
                        pass  # the link is gone already
        self.control = self.io = self.receive = self.dashboard = None
        self.connect()

    def _confirm(self: _Arm, condition: Callable[[], bool], message: Callable[[], str]) -> None:
        deadline = self._clock() + CONFIRM_TIMEOUT
        while not condition():
            if self._clock() > deadline:
                raise CellFault(f"UR {self.host}: {message()}")
            self._sleep(self._poll)
