"""The UR5e arm through ur_rtde: checked linear moves, fault detection and the documented recovery.

ur_rtde reports most failures by returning False (or by raising from deep in
C++), so every call goes through one wrapper and every return value is
checked.  Any fault -- protective stop, emergency stop, lost connection, a
control script that stopped, an unexplained False -- is *latched*: no motion
command is sent again until :meth:`URArm.recover` has run the recovery
sequence and succeeded.

Moves are sent asynchronously (``moveL(..., asynchronous=True)``) and watched
by polling, so the motion runs on the controller while the calling thread
stays free to notice faults, and :meth:`URArm.stop_motion` (from a SIGTERM
handler or another thread) can send ``stopL`` at once.

A stop request is a *latch* too: once :meth:`URArm.stop_motion` has run, no
plan starts (:meth:`URArm.begin`), no move is sent and no recovery runs until
the owner clears it on purpose (:meth:`URArm.clear_stop`).  Neither a new plan
nor a recovery may clear it: a stop that arrives a moment before either would
otherwise be forgotten and the arm would move after it.

The recovery sequence (:meth:`URArm.recover`) is ``flgd.hardware.ur_recovery``'s.
"""

from __future__ import annotations

import logging

import math
import threading
import time
from typing import Any, Callable, NoReturn, Sequence

import numpy as np

from flgd.cell import CellFault
from flgd.hardware.rtde_process import IsolatedRTDEFactory, RTDEFactory
from flgd.hardware.ur_modes import NORMAL, PROTECTIVE, REDUCED, ROBOT_MODES, ROBOT_RUNNING, SAFETY_MODES
from flgd.hardware.ur_poses import for_tcp, move_duration, pose_error
from flgd.hardware.ur_recovery import DASHBOARD_TIMEOUT_MS, PROTECTIVE_STOP_UNLOCK_DELAY, URRecovery

__all__ = [
    "URArm",
    "RTDEFactory",
    "PoseWatch",
    "PoseUnreachable",
    "MotionStopped",
    "SAFETY_MODES",
    "PROTECTIVE_STOP_UNLOCK_DELAY",
]

log = logging.getLogger(__name__)

# Called with the TCP pose [x, y, z, rx, ry, rz] at every poll of a running move (``URArm.move_linear``).
PoseWatch = Callable[[list[float]], None]

STOP_DECELERATION = 10.0            # m/s^2 for stopL (ur_rtde's default)
CAUSE_SETTLE_TIME = 0.1             # s to let the receive stream show why the control script stopped
POSITION_TOLERANCE = 0.002          # m between a finished move and its target
ORIENTATION_TOLERANCE = 0.02        # rad
START_GRACE = 0.5                   # s for an accepted move to show up as running
MOVE_TIMEOUT_MARGIN = 5.0           # s beyond twice the trapezoidal move time
STALLED_CLOCK_FACTOR = 5.0          # a move's wall-clock limit in multiples of its limit on the controller's clock


class PoseUnreachable(Exception):
    """The controller says a target is outside its safety limits or reach; nothing was sent."""


class MotionStopped(Exception):
    """A move was halted on request (``stop_motion``)."""


class URArm(URRecovery):
    """One UR arm: connections, checked moves, fault latch, recovery."""

    def __init__(self, host: str, tcp_offset: Sequence[float], *, factory: RTDEFactory | None = None,
                 use_io: bool = False, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, poll_interval: float = 0.008):
        if not host:
            raise CellFault("robot.host is empty: set the UR controller's address in the cell config")
        self.host = host
        self.tcp = [float(v) for v in tcp_offset] + [0.0, 0.0, 0.0]
        if factory is None:
            factory = IsolatedRTDEFactory()
        self._factory = factory
        self._use_io = use_io
        self._clock = clock
        self._sleep = sleep
        self._poll = poll_interval
        self._lock = threading.RLock()  # ur_rtde interfaces are not thread-safe
        self._stop_requested = threading.Event()
        self._fault: str | None = None
        self._protective_since: float | None = None
        self.installation_tcp: list[float] | None = None   # read when a control script starts (_read_installation_tcp)
        self.control: Any = None
        self.receive: Any = None
        self.io: Any = None
        self.dashboard: Any = None

    # ------------------------------------------------------------------ plumbing
    def _call(self, iface: Any, method: str, *args: Any) -> Any:
        """One ur_rtde call under the lock; an exception becomes a CellFault naming the call."""
        if iface is None:
            raise CellFault(f"UR {self.host}: not connected (needed for {method})")
        with self._lock:
            try:
                return getattr(iface, method)(*args)
            except Exception as exc:  # ur_rtde raises RuntimeError and friends from C++
                raise CellFault(f"UR {self.host}: {method} failed: {type(exc).__name__}: {exc}") from exc

    def _require(self, ok: object, what: str) -> None:
        """ur_rtde signals failure by returning False: turn that into a latched fault."""
        if ok is not True:
            reason = self.fault_reason()
            detail = f" ({reason})" if reason else ""
            self._latch(f"{what} returned {ok!r}{detail}")

    def _latch(self, reason: str) -> NoReturn:
        self._fault = self._fault or reason
        raise CellFault(f"UR {self.host}: {reason}; no further motion until recovery (flgctl reset)")

    @property
    def fault(self) -> str | None:
        """Why the arm is faulted, or None."""
        return self._fault

    def latch(self, reason: str) -> None:
        """Latch a fault found elsewhere (e.g. the gripper): the arm will not move until recovery."""
        self._fault = self._fault or reason

    # ------------------------------------------------------------------ connection
    def connect(self) -> None:
        """Open the interfaces; a robot that is not ready leaves a latched fault, not an exception.

        The receive interface and dashboard are opened first: they work whatever
        the robot's state, so a cell can start (and report) while the arm is
        protective-stopped.  The control interface uploads its script and needs
        a running, unlocked arm; it is opened now if possible, else by recover().
        """
        try:
            self.receive = self._factory.receive(self.host)
        except Exception as exc:
            raise CellFault(f"UR {self.host}: cannot open the RTDE receive interface: {exc}") from exc
        try:
            self.dashboard = self._factory.dashboard(self.host)
            self._call(self.dashboard, "connect", DASHBOARD_TIMEOUT_MS)
        except CellFault:
            raise
        except Exception as exc:
            raise CellFault(f"UR {self.host}: cannot open the dashboard client: {exc}") from exc
        reason = self._state_problem()
        if reason:
            self._fault = reason
            return
        self._open_control()

    def _open_control(self) -> None:
        try:
            self.control = self._factory.control(self.host)
            if self._use_io:
                self.io = self._factory.io(self.host)
        except Exception as exc:
            self._latch(f"cannot open the RTDE control interface (remote control enabled on the pendant?): {exc}")
        self._read_installation_tcp()
        self._require(self._call(self.control, "setTcp", list(self.tcp)), "setTcp")

    def _read_installation_tcp(self) -> None:
        """The TCP a freshly uploaded control script starts with (the pendant's installation), read before this
        arm's is set: a path (``move_path``) runs in such a script.  Unknown (None) when it cannot be read: paths
        then run as single moves."""
        self.installation_tcp = None
        try:
            values = [float(v) for v in self._call(self.control, "getTCPOffset")]
        except (CellFault, TypeError, ValueError) as exc:
            log.warning("UR %s: cannot read the installation's TCP (%s); blended paths run as single moves",
                        self.host, exc)
            return
        if len(values) == 6 and all(map(math.isfinite, values)):
            self.installation_tcp = values

    def close(self) -> None:
        """Stop the control script and drop every connection; safe to call twice."""
        for iface, methods in ((self.control, ("stopScript", "disconnect")), (self.io, ("disconnect",)),
                               (self.receive, ("disconnect",)), (self.dashboard, ("disconnect",))):
            for m in methods:
                if iface is not None:
                    try:
                        self._call(iface, m)
                    except CellFault:
                        pass  # closing: the connection may already be gone
        self.control = self.io = self.receive = self.dashboard = None
        close_factory = getattr(self._factory, "close", None)
        if close_factory is not None:
            close_factory()  # ur_rtde's process ends with the arm

    # ------------------------------------------------------------------ state
    def _state_problem(self) -> str | None:
        """What keeps the arm from moving right now (robot state only), or None."""
        rcv = self.receive
        try:
            if rcv is None or not self._call(rcv, "isConnected"):
                return "lost the RTDE receive connection"
            if self._call(rcv, "isEmergencyStopped"):
                return "emergency stop engaged"
            if self._call(rcv, "isProtectiveStopped"):
                if self._protective_since is None:
                    self._protective_since = self._clock()
                return "protective stop"
            mode = int(self._call(rcv, "getSafetyMode"))
            if mode == PROTECTIVE and self._protective_since is None:
                self._protective_since = self._clock()
            if mode not in (NORMAL, REDUCED):
                return f"safety mode {SAFETY_MODES.get(mode, mode)}"
            robot_mode = int(self._call(rcv, "getRobotMode"))
            if robot_mode != ROBOT_RUNNING:
                return (f"robot mode {ROBOT_MODES.get(robot_mode, robot_mode)} (expected RUNNING: power on and "
                        f"release the brakes on the pendant)")
        except CellFault as exc:
            return str(exc)
        return None

    def fault_reason(self) -> str | None:
        """Why motion is impossible now: robot state, connections, control script; or None."""
        problem = self._state_problem()
        if problem:
            return problem
        try:
            if self.control is None or not self._call(self.control, "isConnected"):
                return "lost the RTDE control connection"
            if not self._call(self.control, "isProgramRunning"):
                # a protective or emergency stop ends the script too, and the control interface's stream may
                # show that a few packages before the receive interface's shows the stop: name the cause
                deadline = self._clock() + CAUSE_SETTLE_TIME
                while self._clock() < deadline:
                    self._sleep(self._poll)
                    problem = self._state_problem()
                    if problem:
                        return problem
                return "the ur_rtde control script is not running on the controller"
        except CellFault as exc:
            return str(exc)
        return None

    def check(self) -> None:
        """Raise CellFault if a fault is latched or present now (and latch it)."""
        if self._fault:
            raise CellFault(f"UR {self.host}: in FAULT ({self._fault}); run recovery (flgctl reset) first")
        reason = self.fault_reason()
        if reason:
            self._latch(reason)

    def tcp_pose(self) -> list[float]:
        pose = self._call(self.receive, "getActualTCPPose")
        if pose is None or len(pose) != 6 or not all(map(math.isfinite, pose)):
            self._latch(f"getActualTCPPose returned {pose!r}")
        return [float(v) for v in pose]

    # ------------------------------------------------------------------ motion
    def begin(self) -> None:
        """A plan starts: refuse (MotionStopped) while a stop request is latched.

        Why it does not clear the request: a stop that lands between the caller's
        last check and this call would be erased and the plan would move the arm.
        """
        if self._stop_requested.is_set():
            raise MotionStopped("a stop was requested; nothing more is sent until the stop is cleared")

    @property
    def stop_requested(self) -> bool:
        return self._stop_requested.is_set()

    def stop_motion(self) -> None:
        """Halt the arm now (any thread, a signal handler too): stopL and make the running move return.

        The request stays latched until :meth:`clear_stop`.  The flag is set before
        the lock is taken for stopL, and moveL is only sent under the lock after
        looking at the flag, so a move is either refused or sent before the stopL.
        """
        self._stop_requested.set()
        if self._fault is not None:
            return  # nothing moves while a fault is latched (a recovery may hold the lock for a while): flag only
        self._halt()

    def clear_stop(self) -> None:
        """Forget a stop request: only for an owner that knows no stop is pending (e.g. an operator's start)."""
        self._stop_requested.clear()

    def _halt(self) -> None:
        if self.control is None:
            return
        try:
            self._call(self.control, "stopL", STOP_DECELERATION)
        except CellFault:
            pass  # the arm is already stopped by the controller, or the link is gone

    def move_linear(self, pose: Sequence[float], speed: float, acceleration: float, label: str = "",
                    stop_force: float = 0.0, on_poll: PoseWatch | None = None) -> bool:
        """moveL to ``pose`` [x, y, z, rx, ry, rz] and wait until it is there.

        With ``stop_force`` > 0 (N) the move is guarded: it is halted (stopL) as soon as the
        TCP force differs from its value at the start by more than that, and True is
        returned -- the arm stands somewhere on the line, short of the target.  False: the
        target was reached.  ``on_poll``: called with the TCP pose at every poll while the
        arm moves.  Raises PoseUnreachable (nothing sent), MotionStopped, or CellFault (latched).
        """
        what = f"move '{label}'" if label else "move"
        [target], timeout = self._checked_targets([pose], [speed], [acceleration], what)
        guard = None
        if stop_force > 0.0:
            guard = (self._tcp_force(), float(stop_force))
        self._require(self._send(what, target, float(speed), float(acceleration), True), f"moveL ({what})")
        return self._wait_for_move(target, what, timeout, guard, on_poll=on_poll)

    def _checked_targets(self, poses: Sequence[Sequence[float]], speeds: Sequence[float],
                         accelerations: Sequence[float], what: str) -> tuple[list[list[float]], float]:
        """The targets as floats, each one the controller accepts, and the time limit of the moves through them
        from here; raises PoseUnreachable (nothing sent), MotionStopped or CellFault first."""
        targets = [[float(v) for v in pose] for pose in poses]
        if not targets or any(len(t) != 6 or not all(map(math.isfinite, t)) for t in targets):
            raise PoseUnreachable(f"{what}: target {poses!r} is not poses of six finite numbers")
        if self._stop_requested.is_set():
            raise MotionStopped(f"{what}: stop requested")
        self.check()
        for target in targets:
            if self._call(self.control, "isPoseWithinSafetyLimits", target) is not True:
                self.check()  # a dropped link also answers False
                raise PoseUnreachable(f"{what}: the controller reports {np.round(target, 4).tolist()} outside its "
                                      f"safety limits or reach")
        legs = zip([self.tcp_pose()] + targets[:-1], targets, speeds, accelerations)
        return targets, MOVE_TIMEOUT_MARGIN + 2.0 * sum(move_duration(pose_error(a, b)[0], v, acc)
                                                          for a, b, v, acc in legs)

    def _send(self, what: str, *args: Any) -> Any:
        """ur_rtde's ``moveL(*args)``, unless a stop was requested (see stop_motion: a stop now either refuses
        this move or halts it after it was sent)."""
        with self._lock:
            if self._stop_requested.is_set():
                raise MotionStopped(f"{what}: stop requested")
            return self._call(self.control, "moveL", *args)

    def move_path(self, poses: Sequence[Sequence[float]], speeds: Sequence[float], accelerations: Sequence[float],
                  blends: Sequence[float], label: str = "", on_poll: PoseWatch | None = None) -> None:
        """Blended moveLs through ``poses`` (each [x, y, z, rx, ry, rz] for this arm's TCP) as one motion
        (ur_rtde's ``moveL(path)``): ``blends[k]`` is the radius at ``poses[k]`` (the last one stops).  Waits
        until the last pose is reached.  Raises PoseUnreachable (nothing sent), MotionStopped, or CellFault.

        ur_rtde runs a path by re-uploading its control script with the moves written into it, and a fresh
        script starts with the installation's TCP: the poses are sent for that TCP (read when the control
        interface opened; a script running another TCP halts the path and latches a fault) and this arm's TCP is
        set again once the path has ended.  With that TCP unknown the poses are run as single moves."""
        what = f"path '{label}'" if label else "path"
        installation = self.installation_tcp
        if installation is None:
            for target, v, acc in zip(poses, speeds, accelerations):
                self.move_linear(target, v, acc, label, on_poll=on_poll)
            return
        targets, timeout = self._checked_targets(poses, speeds, accelerations, what)
        path = [for_tcp(t, self.tcp, installation) + [float(v), float(acc), float(r)]
                for t, v, acc, r in zip(targets, speeds, accelerations, list(blends[:-1]) + [0.0])]
        ok = self._send(what, path, True)
        try:
            self._require(ok, f"moveL path ({what})")
            running = self._call(self.control, "getTCPOffset")
            try:
                offset = max(pose_error([float(v) for v in running], installation))
            except (TypeError, ValueError, IndexError):
                offset = math.inf
            if not offset <= 1e-6:
                self._halt()
                self._latch(f"{what}: the path's script runs the TCP {running!r}, not the installation's "
                            f"{np.round(installation, 4).tolist()} read before (changed on the pendant?): halted")
            self._wait_for_move(targets[-1], what, timeout, tcp=installation, on_poll=on_poll)
        finally:
            if self._fault is None and self.control is not None:
                self._require(self._call(self.control, "setTcp", list(self.tcp)), "setTcp after a path")

    def _tcp_force(self) -> np.ndarray:
        """The controller's estimate of the force at the TCP (N, base frame)."""
        try:
            wrench = self._call(self.receive, "getActualTCPForce")
        except CellFault:
            self._halt()  # an unguarded descent must not go on
            raise
        try:
            force = np.asarray(list(wrench), dtype=float)[:3]
        except (TypeError, ValueError):
            force = np.empty(0)
        if force.shape != (3,) or not np.all(np.isfinite(force)):
            self._halt()
            self._latch(f"the controller reported an unusable TCP force {wrench!r}")
        return force

    def _async_running(self) -> bool:
        status = self._call(self.control, "getAsyncOperationProgressEx")
        return bool(status.isAsyncOperationRunning())

    def controller_time(self) -> float:
        """The controller's own clock (RTDE ``timestamp``, s): a move's time limits are counted on it, so that a
        controller that runs slower than the wall clock (an emulator on a busy PC) is judged by its own time.
        Unreadable (a lost link during a move: the move must not go on unwatched): halt and latch."""
        value = self.controller_time_or_none()
        if value is None:
            self._halt()
            self._latch("cannot read the controller's clock (lost link, or an unusable timestamp)")
        return value

    def controller_time_or_none(self) -> float | None:
        """The controller's clock if it can be read now, else None; latches nothing (for accounting only)."""
        try:
            value = float(self._call(self.receive, "getTimestamp"))
        except (CellFault, TypeError, ValueError):
            return None
        return value if math.isfinite(value) else None

    def _wait_for_move(self, target: list[float], what: str, timeout: float,
                       guard: tuple[np.ndarray, float] | None = None, tcp: Sequence[float] | None = None,
                       on_poll: PoseWatch | None = None) -> bool:
        """Poll until the move to ``target`` (a pose of this arm's TCP) has ended; ``tcp``: the TCP the controller
        reports poses for meanwhile, when it is not this arm's (a path's script)."""
        start, controller_start = self._clock(), self.controller_time()
        seen_running = False
        while True:
            if self._stop_requested.is_set():
                self._halt()
                raise MotionStopped(f"{what}: stopped on request")
            reason = self.fault_reason()
            if reason:
                self._halt()
                self._latch(f"{reason} during {what}")
            change = None if guard is None else self._tcp_force() - guard[0]
            if change is not None and np.linalg.norm(change) > guard[1]:
                self._halt()
                log.info("%s stopped on contact: TCP force changed by %s N", what, np.round(change, 1).tolist())
                self._wait_until_still(what)
                return True
            running = self._async_running()
            seen_running = seen_running or running
            here = self.tcp_pose() if tcp is None else for_tcp(self.tcp_pose(), tcp, self.tcp)
            if on_poll is not None:
                on_poll(here)
            dp, dr = pose_error(here, target)
            elapsed = self.controller_time() - controller_start
            if not running:
                if dp <= POSITION_TOLERANCE and dr <= ORIENTATION_TOLERANCE:
                    return False
                if self._stop_requested.is_set():   # stopped on request after the look above: short, not faulty
                    raise MotionStopped(f"{what}: stopped on request")
                if seen_running or elapsed > START_GRACE:
                    self._latch(f"{what} ended {dp * 1000:.1f} mm / {math.degrees(dr):.1f} deg from its target")
            if elapsed > timeout:
                self._halt()
                self._latch(f"{what} did not finish within {timeout:.1f} s")
            wall = self._clock() - start
            if wall > STALLED_CLOCK_FACTOR * timeout:
                self._halt()
                self._latch(f"{what}: the controller's clock advanced {elapsed:.1f} s in {wall:.1f} s; its state "
                            f"stream has stalled or runs at less than 1/{STALLED_CLOCK_FACTOR:g} of real time "
                            f"(network, or an emulator on a PC too busy for it)")
            self._sleep(self._poll)

    def _wait_until_still(self, what: str) -> None:
        """After a guard's stopL: wait for the deceleration to end before the plan goes on."""
        start = self._clock()
        while self._async_running():
            reason = self.fault_reason()
            if reason:
                self._latch(f"{reason} during {what}")
            if self._clock() - start > MOVE_TIMEOUT_MARGIN:
                self._latch(f"{what}: the arm did not stop within {MOVE_TIMEOUT_MARGIN:.0f} s of a contact stop")
            self._sleep(self._poll)

    def set_tool_output(self, index: int, level: bool) -> None:
        """Tool digital output through RTDEIOInterface (the RG2's digital-output wiring)."""
        self.check()
        self._require(self._call(self.io, "setToolDigitalOut", int(index), bool(level)),
                      f"setToolDigitalOut({index}, {level})")
