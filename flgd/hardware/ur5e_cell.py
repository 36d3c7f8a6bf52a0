"""The real cell: a UR5e arm, an RG2 gripper and a RealSense D415 behind ``flgd.cell.Cell``.

It runs the same checked plans as the simulated cell.  Each plan is
re-verified against this cell's config before anything moves; MoveL steps
become ``moveL`` at the step's speed and acceleration (capped by the safety
envelope); the measured gripper width is recorded at MeasureWidth steps.

Faults (protective/emergency stop, lost connection, dead control script,
gripper errors) raise :class:`flgd.cell.CellFault` and are latched: every
later ``execute`` refuses until ``recover()`` has run the arm's recovery
sequence (see ``flgd.hardware.ur_arm``) and brought the arm home through a
checked ``plan_home``.
"""

from __future__ import annotations

import time
from typing import Any, Callable

from flgd.cell import STOPPED_ON_REQUEST, Cell, CellFault, ContactStop, ExecutionResult, Frame
from flgd.config import CellConfig
from flgd.plans import GripperCommand, MeasureWidth, MoveL, plan_home
from flgd.safety import CheckedPlan, check_plan
from flgd.hardware.rg2 import GripperDriver, GripperFault, make_gripper_driver
from flgd.hardware.ur_arm import MotionStopped, PoseUnreachable, RTDEFactory, URArm, pose_error

__all__ = ["UR5eCell"]


WIDTH_SETTLE_INTERVAL = 0.1  # s between width readings at a MeasureWidth step
WIDTH_STEADY = 0.0005        # m: two readings this close mean the fingers have stopped
WIDTH_SETTLE_TIMEOUT = 1.0   # s: after this the last reading counts


def _open_d415(config: CellConfig) -> Any:
    from flgd.hardware.d415 import D415Camera

    return D415Camera.open(config)


class UR5eCell(Cell):
    """UR5e + RG2 + D415.  Constructor parameters after ``config`` exist for tests and tools."""

    name = "ur5e"

    def __init__(self, config: CellConfig, *, arm: URArm | None = None, gripper: GripperDriver | None = None,
                 camera_factory: Callable[[CellConfig], Any] = _open_d415,
                 rtde_factory: RTDEFactory | None = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, require_width: bool = True):
        super().__init__(config)
        self._clock = clock
        self._sleep = sleep
        self.arm = arm
        self.gripper = gripper
        self.camera: Any = None
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
        return self.camera.capture()

    def gripper_width(self) -> float:
        with self._lock:
            return self.gripper.width()

    # ------------------------------------------------------------------ acting
    def execute(self, plan: CheckedPlan) -> ExecutionResult:
        start = self._clock()
        with self._lock:
            steps = plan.verify(self.config).steps  # PlanRefused: nothing has moved
            self.arm.check()
            self.arm.begin()
            sf, gr = self.config.safety, self.config.gripper
            widths: list[float] = []
            stops: list[ContactStop] = []
            for i, step in enumerate(steps):
                where = f"step {i} ({step.label or type(step).__name__})"
                try:
                    if self.arm.stop_requested:
                        raise MotionStopped("stop requested")
                    if isinstance(step, MoveL):
                        # a guarded move may end short of its pose; the next (absolute) pose goes on from there
                        target = step.pose.as_ur_pose()
                        if self.arm.move_linear(target, min(step.speed, sf.max_speed),
                                                min(step.acceleration, sf.max_acceleration), step.label,
                                                stop_force=step.stop_on_contact):
                            stops.append(ContactStop(step.label, pose_error(self.arm.tcp_pose(), target)[0]))
                    elif isinstance(step, GripperCommand):
                        self.arm.check()
                        self.gripper.move(step.width, min(step.force, gr.force))
                    elif isinstance(step, MeasureWidth):
                        widths.append(self._settled_width())
                    else:  # verify() refuses unknown steps; this guards a future step type
                        raise CellFault(f"{where}: the ur5e cell cannot run {type(step).__name__}")
                except PoseUnreachable as exc:
                    return ExecutionResult(False, widths, f"{where}: {exc}", self._clock() - start, stops)
                except MotionStopped:
                    return ExecutionResult(False, widths, f"{where}: {STOPPED_ON_REQUEST}", self._clock() - start,
                                           stops)
                except GripperFault as exc:
                    self.arm.latch(f"gripper: {exc}")
                    raise CellFault(f"{where}: {exc}") from exc
            return ExecutionResult(True, widths, "", self._clock() - start, stops)

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

    def recover(self) -> None:
        """The arm's recovery sequence, then home through a checked plan (raises CellFault on failure)."""
        with self._lock:
            self.arm.recover()
            result = self.execute(check_plan(plan_home(self.config), self.config))
            if not result.completed:
                self.arm.latch(f"could not reach home after recovery: {result.failure}")
                raise CellFault(f"recovery: could not reach home: {result.failure}")

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
