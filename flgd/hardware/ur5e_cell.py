"""The real cell: a UR5e arm, an RG2 gripper and a RealSense D415 behind ``flgd.cell.Cell``.

It runs the same checked plans as the simulated cell.  Each plan is
re-verified against this cell's config before anything moves; MoveL steps
become ``moveL`` at the step's speed and acceleration (capped by the safety
envelope), a blended run of them one ``moveL(path)`` (``URArm.move_path``);
the measured gripper width is recorded at MeasureWidth steps.

Faults (protective/emergency stop, lost connection, dead control script,
gripper errors, the arm standing outside the safety envelope) raise
:class:`flgd.cell.CellFault` and are latched: every later ``execute`` refuses
until ``recover()`` has reopened the camera, run the arm's recovery sequence
(see ``flgd.hardware.ur_arm``) and brought the arm home through a checked
``plan_home``.  A stop request is latched as well (``stop_motion`` ..
``clear_stop``): while it is set nothing moves and ``recover`` refuses.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from typing import Callable

from flgd.camera_view import in_view_on_the_way
from flgd.cell import (STOPPED_ON_REQUEST, Cell, CellFault, ContactStop, ExecutionResult, Frame, FrameOnTheWay,
                       StopPending)
from flgd.config import CellConfig
from flgd.geometry import ToolPose, rotvec_to_matrix
from flgd.plans import GripperCommand, MeasureWidth, MoveL, Plan, abort_steps, blended_runs, plan_home
from flgd.safety import CheckedPlan, PlanRefused, check_plan
from flgd.hardware.camera import Camera
from flgd.hardware.gripper import GripperDriver, GripperFault
from flgd.hardware.rg2 import make_gripper_driver
from flgd.hardware.ur_arm import MotionStopped, PoseUnreachable, RTDEFactory, URArm, pose_error

__all__ = ["UR5eCell"]

log = logging.getLogger(__name__)


# A MeasureWidth step reads until two readings WIDTH_SETTLE_INTERVAL apart differ by at most WIDTH_STEADY: fingers
# slower than 5 mm/s, an eighth of the RG2's slowest gripping speed (38 mm/s), have stopped.  A pick is judged
# again at the place (``flgd.plans.PLACE_CHECK_LABEL``), so a slip that starts after this reading still counts;
# with home at the place (``flgd.plans.place_is_home``) an object that slips after it falls where it is placed.
WIDTH_SETTLE_INTERVAL = 0.04  # s between width readings at a MeasureWidth step
WIDTH_STEADY = 0.0002        # m: two readings this close mean the fingers have stopped
WIDTH_SETTLE_TIMEOUT = 1.0   # s: after this the last reading counts
FLOOR_MEASUREMENT_TOLERANCE = 0.0005  # m below the table clearance floor an arm stopped on it may read
CAPTURE_ON_THE_WAY_WAIT = 5.0   # s a plan's end waits for a capture started on its last move (a D415 takes < 0.2 s)
# s the tool must have been out of view before a capture on the way starts: a streaming D415 (30 Hz) may deliver a
# frame whose exposure began up to about two frame periods and the USB transfer before the request
CLEAR_BEFORE_CAPTURE = 0.1


def _open_d415(config: CellConfig) -> Camera:
    from flgd.hardware.d415 import D415Camera

    return D415Camera.open(config)


class UR5eCell(Cell):
    """UR5e + RG2 + D415.  Constructor parameters after ``config`` exist for tests and tools."""

    name = "ur5e"

    def __init__(self, config: CellConfig, *, arm: URArm | None = None, gripper: GripperDriver | None = None,
                 camera_factory: Callable[[CellConfig], Camera] = _open_d415,
                 rtde_factory: RTDEFactory | None = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, require_width: bool = True):
        super().__init__(config)
        self._clock = clock
        self._sleep = sleep
        self.arm = arm
        self.gripper = gripper
        self.camera: Camera | None = None
        self._camera_factory = camera_factory
        try:
            if self.arm is None:
                self.arm = URArm(config.robot.host, config.robot.tcp_offset, factory=rtde_factory,
                                 use_io=config.gripper.driver == "tool_digital_output", clock=clock, sleep=sleep)
                self.arm.connect()
            if self.gripper is None:
                self.gripper = make_gripper_driver(config, self.arm.set_tool_output, clock=clock, sleep=sleep)
            if require_width and not self.gripper.measures_width:
                raise CellFault(f"gripper.driver {config.gripper.driver!r} in {config.source} cannot measure the "
                                f"finger width, which decides grasp success; use 'rg2_xmlrpc'")
            self.camera = camera_factory(config)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ sensing
    def capture(self) -> Frame:
        if self.camera is None:
            raise CellFault("the camera is not open (its last reopen failed): reconnect the D415, then flgctl reset")
        frame = self.camera.capture()
        # read after the frame arrived: no motion is sent while a picture is taken, so the arm stood there
        return dataclasses.replace(frame, tool_position=tuple(self.arm.tcp_pose()[:3]))

    def gripper_width(self) -> float:
        with self._lock:
            return self.gripper.width()

    # ------------------------------------------------------------------ acting
    def execute(self, plan: CheckedPlan) -> ExecutionResult:
        return self._run(plan, None)

    def execute_and_capture(self, plan: CheckedPlan, on_frame: FrameOnTheWay) -> ExecutionResult:
        """Run ``plan``; during its last move, once the tool has been out of the camera's view for
        ``CLEAR_BEFORE_CAPTURE``, a capture starts beside the motion (the camera and the arm are separate devices).
        The frame is handed over if the tool is still out of view after it (``_LookOnTheWay``);
        ``execute_and_capture`` returns once that capture has ended too (or ``CAPTURE_ON_THE_WAY_WAIT`` after the
        plan)."""
        return self._run(plan, on_frame)

    def _run(self, plan: CheckedPlan, on_frame: FrameOnTheWay | None) -> ExecutionResult:
        look = None if on_frame is None else _LookOnTheWay(self, on_frame)
        try:
            return self._run_steps(plan, look)
        finally:
            if look is not None:
                look.join()

    def _run_steps(self, plan: CheckedPlan, look: "_LookOnTheWay | None") -> ExecutionResult:
        with self._lock:
            steps = plan.verify(self.config).steps  # PlanRefused: nothing has moved
            self.arm.check()
            start = self.arm.controller_time()   # durations on the controller's clock (ExecutionResult)
            try:
                self.arm.begin()  # a latched stop request: nothing is sent
            except MotionStopped:
                return ExecutionResult(False, [], f"before step 0: {STOPPED_ON_REQUEST}", self._elapsed(start))
            self._check_start_pose()
            sf, gr = self.config.safety, self.config.gripper
            widths: list[float] = []
            stops: list[ContactStop] = []
            gripper = 0.0   # controller seconds of the gripper's steps
            runs = {a: b for a, b in blended_runs(steps) if b > a}   # blended moves: one path each
            last_move = max((k for k, s in enumerate(steps) if isinstance(s, MoveL)), default=-1)
            if look is not None:
                look.start_clock = start
            i = -1
            while i + 1 < len(steps):
                i += 1
                step = steps[i]
                where = f"step {i} ({step.label or type(step).__name__})"
                try:
                    if self.arm.stop_requested:
                        raise MotionStopped("stop requested")
                    if i in runs:
                        moves = [s for s in steps[i:runs[i] + 1] if isinstance(s, MoveL)]
                        self.arm.move_path([m.pose.as_ur_pose() for m in moves],
                                           [min(m.speed, sf.max_speed) for m in moves],
                                           [min(m.acceleration, sf.max_acceleration) for m in moves],
                                           [m.blend for m in moves],
                                           " to ".join(dict.fromkeys(m.label or "move" for m in moves)),
                                           on_poll=look.poll if look is not None and runs[i] == last_move else None)
                        i = runs[i]
                    elif isinstance(step, MoveL):
                        # a guarded move may end short of its pose; the next (absolute) pose goes on from there
                        target = step.pose.as_ur_pose()
                        if self.arm.move_linear(target, min(step.speed, sf.max_speed),
                                                min(step.acceleration, sf.max_acceleration), step.label,
                                                stop_force=step.stop_on_contact,
                                                on_poll=look.poll if look is not None and i == last_move else None):
                            stops.append(ContactStop(step.label, pose_error(self.arm.tcp_pose(), target)[0]))
                            if step.abort_on_contact:   # the rest of the plan: back up and home, move by move
                                steps = steps[:i + 1] + abort_steps(steps, i)
                                runs = {a: b for a, b in runs.items() if b <= i}
                    elif isinstance(step, GripperCommand):
                        self.arm.check()
                        started = self._elapsed(start)
                        self.gripper.move(step.width, min(step.force, gr.force), step.proceed_after)
                        gripper += self._elapsed(start) - started
                    elif isinstance(step, MeasureWidth):
                        started = self._elapsed(start)
                        widths.append(self._settled_width())
                        gripper += self._elapsed(start) - started
                    else:  # verify() refuses unknown steps; this guards a future step type
                        raise CellFault(f"{where}: the ur5e cell cannot run {type(step).__name__}")
                except PoseUnreachable as exc:
                    return ExecutionResult(False, widths, f"{where}: {exc}", self._elapsed(start), stops, gripper)
                except MotionStopped:
                    return ExecutionResult(False, widths, f"{where}: {STOPPED_ON_REQUEST}", self._elapsed(start),
                                           stops, gripper)
                except GripperFault as exc:
                    self.arm.latch(f"gripper: {exc}")
                    raise CellFault(f"{where}: {exc}") from exc
            return ExecutionResult(True, widths, "", self._elapsed(start), stops, gripper)

    def _elapsed(self, start: float) -> float:
        """Seconds on the controller's clock since ``start``; 0 when it cannot be read (a plan cut short by a
        lost link ends in a fault, whose cycle time nobody plans with)."""
        now = self.arm.controller_time_or_none()
        return 0.0 if now is None else now - start

    def _check_start_pose(self) -> None:
        """Refuse the plan (a latched fault) unless the arm stands inside the safety envelope now.

        Why: the first moveL of a plan is a straight line from wherever the arm
        actually is -- after a start, a reset, a recovery or a jog on the pendant
        that is no pose any plan was checked for.  The actual pose gets the same
        check as a plan's poses (``check_plan``: box, table floor, tilt).  The box
        and the half-space above the table floor are convex, so a straight segment
        between two points inside them stays inside: with the start checked here and
        every target checked by ``check_plan``, no segment of the plan leaves the box.
        """
        actual = self.arm.tcp_pose()
        sf = self.config.safety
        floor = self.config.workspace.table_z + sf.min_table_clearance
        # a grasp descends to the floor itself: the arm stopped there (a fault in the close) reads a hair below
        # it, and must still be allowed back up (the rest of the box is checked as it stands)
        z = floor if floor - FLOOR_MEASUREMENT_TOLERANCE <= actual[2] < floor else actual[2]
        rotation = rotvec_to_matrix(actual[3:6])
        here = ToolPose((actual[0], actual[1], z), tuple(tuple(float(v) for v in row) for row in rotation))
        probe = MoveL(here, sf.max_speed, sf.max_acceleration, "actual TCP pose")
        try:
            check_plan(Plan("start pose", (probe,)), self.config)
        except PlanRefused as exc:
            where = ", ".join(f"{v:.4f}" for v in actual[:3])
            reason = (f"the arm stands at [{where}] m, outside the safety envelope ({exc.reason}; envelope "
                      f"x {list(sf.envelope_x)}, y {list(sf.envelope_y)}, z {list(sf.envelope_z)} m, table floor "
                      f"{floor:.4f} m, tilt <= {sf.max_tilt} rad in {self.config.source}); nothing was sent: "
                      f"jog the arm inside the envelope on the pendant, then flgctl reset (or, in flgd "
                      f"calibrate, run it again)")
            self.arm.latch(reason)
            raise CellFault(f"UR {self.arm.host}: {reason}") from None

    def _settled_width(self) -> float:
        """The finger width once it has stopped changing (at most ``WIDTH_SETTLE_TIMEOUT`` s).

        Why: a block slipping out of the fingers as the arm arrives home is still
        between them at the first reading; the fingers go on closing after it, so
        a width read once would call an empty grasp held.
        """
        last = self.gripper.width()
        deadline = self._clock() + WIDTH_SETTLE_TIMEOUT
        while True:
            self._sleep(WIDTH_SETTLE_INTERVAL)
            now = self.gripper.width()
            if abs(now - last) <= WIDTH_STEADY or self._clock() >= deadline:
                return now
            last = now

    def stop_motion(self) -> None:
        """Halt arm and fingers now; safe from a signal handler or another thread (no cell lock taken)."""
        if self.arm is not None:
            self.arm.stop_motion()
        if self.gripper is not None:
            self.gripper.stop()

    # ------------------------------------------------------------------ life cycle
    @property
    def fault(self) -> str | None:
        return self.arm.fault if self.arm is not None else "not connected"

    def clear_stop(self) -> None:
        """Forget a latched stop request (the controller, when no stop is pending)."""
        if self.arm is not None:
            self.arm.clear_stop()

    def can_reset_scene(self) -> bool:
        """A real table is refilled by a person, never by the cell."""
        return False

    def recover(self) -> None:
        """Reopen the camera, run the arm's recovery sequence, then home through a checked plan.

        Raises CellFault when that is not possible, and StopPending (before anything
        moves, the fault left latched) when a stop is requested before or during it.
        """
        with self._lock:
            self._refuse_if_stopped("the arm was not moved")
            self._reopen_camera()
            self.arm.recover()
            self._refuse_if_stopped("the arm was not moved")
            result = self.execute(check_plan(plan_home(self.config), self.config))
            if not result.completed:
                if STOPPED_ON_REQUEST in result.failure:
                    self._refuse_if_stopped("the arm was halted on its way home")
                self.arm.latch(f"could not reach home after recovery: {result.failure}")
                raise CellFault(f"recovery: could not reach home: {result.failure}")

    def _refuse_if_stopped(self, what_happened: str) -> None:
        if self.arm is not None and self.arm.stop_requested:
            raise StopPending(f"recovery stopped: a stop was requested; {what_happened}")

    def _reopen_camera(self) -> None:
        """Close the camera and open it anew: a camera fault (unplugged, stalled stream) is cleared only so."""
        old, self.camera = self.camera, None
        if old is not None:
            try:
                old.close()
            except Exception:  # the old stream may be half gone; what matters is the new one
                pass
        try:
            self.camera = self._camera_factory(self.config)
        except Exception as exc:
            raise CellFault(f"recovery: the camera did not come back: {exc}. Check the D415's USB cable (a USB 3 "
                            f"port) and that `rs-enumerate-devices -s` lists it, then flgctl reset again") from exc

    def close(self) -> None:
        if getattr(self, "_closed", False):
            return
        self._closed = True
        for part in (self.camera, self.gripper, self.arm):
            if part is not None:
                try:
                    part.close()
                except CellFault:
                    pass  # closing anyway


class _LookOnTheWay:
    """One picture taken beside a plan's last move.

    The capture starts once every poll of the last ``CLEAR_BEFORE_CAPTURE`` seconds (on the controller's clock) found
    the tool out of view: a camera that streams (the D415) may deliver a frame whose exposure began before the request,
    and that frame must not show the tool either.  The frame is handed over only if a pose read after it arrived (the
    next poll of the move, or the arm's pose once the plan has ended) has the tool out of view too; ``tool_position``
    is where the tool was when the capture started.  A capture that fails (a camera fault) hands nothing over: the
    cycle then captures at home and meets the fault there."""

    def __init__(self, cell: UR5eCell, on_frame: FrameOnTheWay):
        self._cell, self._on_frame = cell, on_frame
        self.start_clock: float | None = None   # the plan's start on the controller's clock
        self._clear_since: float | None = None   # controller time of the first poll of the clear run
        self._started_at: tuple[float, float, float] | None = None
        self._thread: threading.Thread | None = None
        self._taken: tuple[Frame, float] | None = None   # (frame, seconds since the plan started), not yet checked
        self._seen = False   # a poll has found the frame taken: the next one checks it
        self._taken_lock = threading.Lock()

    def poll(self, pose: list[float]) -> None:
        """Each poll of the last move, with the TCP pose for this arm's TCP; never raises (the move must go on)."""
        try:
            self._poll(pose)
        except Exception as exc:
            log.warning("picture on the way home: %s", exc)
            self._started_at = self._started_at or (math.nan, math.nan, math.nan)   # give up for this plan

    def _poll(self, pose: list[float]) -> None:
        arm = self._cell.arm
        if arm is None:
            return
        if self._thread is not None:
            self._check_taken(pose)
            return
        if self._started_at is not None:
            return
        now = arm.controller_time_or_none()   # (never latches: a failed read here only delays the picture)
        if now is None or in_view_on_the_way(pose[:3], self._cell.config):
            self._clear_since = None
            return
        if self._clear_since is None:
            self._clear_since = now
        if now - self._clear_since < CLEAR_BEFORE_CAPTURE:
            return
        self._started_at = (float(pose[0]), float(pose[1]), float(pose[2]))
        thread = threading.Thread(target=self._capture, name="flgd-capture-on-the-way", daemon=True)
        thread.start()
        self._thread = thread

    def _capture(self) -> None:
        cell = self._cell
        try:
            if cell.camera is None or cell.arm is None:
                return
            frame = cell.camera.capture()
            at = cell.arm.controller_time_or_none()
        except Exception as exc:   # the camera's or the link's fault: no frame now; the capture at home reports it
            log.warning("capture on the way home failed: %s", exc)
            return
        if self.start_clock is not None and at is not None:
            with self._taken_lock:
                self._taken = (frame, at - self.start_clock)

    def _check_taken(self, pose: list[float], read_after: bool = False) -> None:
        """Hand the frame over if the tool at ``pose`` is out of view.  A poll that first finds the frame there may
        have read its pose before the frame arrived: the next poll's pose is the one checked (``read_after``: the
        pose was read after the capture ended, at the plan's end)."""
        with self._taken_lock:
            taken = self._taken
            if taken is not None and not (read_after or self._seen):
                self._seen = True
                return
            self._taken = None
        if taken is None:
            return
        why = in_view_on_the_way(pose[:3], self._cell.config)
        if why:
            log.warning("picture on the way home dropped: after it was taken, %s", why)
            return
        assert self._started_at is not None
        self._on_frame(dataclasses.replace(taken[0], tool_position=self._started_at), taken[1])

    def join(self) -> None:
        """Once the plan has ended: wait for a capture still running (at most ``CAPTURE_ON_THE_WAY_WAIT``) and hand
        over a frame that no poll has checked yet, against the arm's pose now."""
        if self._thread is None:
            return
        self._thread.join(CAPTURE_ON_THE_WAY_WAIT)
        if self._thread.is_alive():
            log.warning("a capture on the way home still runs %.0f s after the plan ended", CAPTURE_ON_THE_WAY_WAIT)
            return
        arm = self._cell.arm
        try:
            if arm is not None and arm.fault is None:
                self._check_taken(arm.tcp_pose(), read_after=True)
        except CellFault as exc:
            log.warning("picture on the way home: %s", exc)
