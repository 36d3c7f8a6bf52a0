"""The simulated arm and fingers following a plan's steps, with the shortcuts that keep a plan cheap.

A MoveL becomes a straight TCP line through closed-form IK and joint position control at the step's speed and
acceleration; gripper commands drive force-limited fingers; a width is read once the fingers stop.

Speed -- exactly what is shortened (everything else is stepped at ``sim.time_step``):
  * Free spans of a MoveL.  Every line is solved with IK tick by tick before the
    arm moves (an unreachable free move fails like any other).  The leading and
    trailing ticks whose swept box -- TCP path inflated by the gripper's
    half-size (7.5 cm) and by what it holds, from the TCP (or the held object's
    bottom) up -- keeps ``FREE_MARGIN`` (2 cm) from every other object's bounding
    box are not simulated: the arm is placed at the end of that span, and a held
    object moves rigidly with the TCP.  So the high part of an approach or of a
    descent and the part of a lift after the object has cleared its neighbours are
    jumps; the contact part of descend, lift, push, shift and retreat is simulated.
    A line that starts with the gripper touching an object it does not carry is
    simulated from its start.  What the gripper carries is what is squeezed between
    both pads (side contacts), measured or not.  Whatever it carries is simulated:
    only the tail of a straight lift may be a jump, after ``CARRY_TRIAL_TICKS``
    (0.33 s) of it were simulated with the object still in the gripper; the carry
    home and the carry to the place pose (lateral and wrist accelerations) are
    simulated in full, since a marginal grip can lose the object there.  So the
    widths measured at home and at the place pose tell held from slipped (a grasp
    and its place cost about 0.9 s of CPU against 0.25 s with rigid carries).
  * Free gripper motions: opening/closing while nothing is held and no object is
    within the gripper's reach sets the fingers directly.
  * Solver iterations: 20 normally, 150 while the fingers squeeze something
    (fewer let the pads sink into a held block and falsify the width: with 60,
    25 of 60 light cylinders gripped near their centre read 3-18 mm less than
    their diameter, and a pad sunk > 15 mm counted as unstable physics).
  * IK: a line's ticks are solved in one batch (``kinematics.inverse_many``).
  Skipped spans still advance ``sim_time`` by their real duration.

Protective stop: a line that presses the gripper down on an object (> 100 N, or
an object squeezed > 6 mm into the table or another object -- pybullet's soft
contacts let a block sink where a real one would stop the arm) raises
``CollisionStop``.

Guarded moves (``MoveL.stop_on_contact`` > 0, a grasp's descent): the line is
checked every two physics steps and ends where the gripper meets that force (or
squeezes an object ``YIELD_DEPTH`` into its support); the arm holds there.

Shift press: a shift presses the closed fingers ``robot.shift_press`` into the
object's top on purpose, so that friction drags it (paper III-A).  Rigid
position control would squeeze the block through the 6 mm rule every time;
instead the press is compliant, like the real fingertips and wrist: once an
object is squeezed more than ``YIELD_DEPTH`` (3 mm), the rest of the plan's
targets rise by the excess, up to ``shift_press`` in total.  A press that the
give cannot absorb (the surface height was read too low) still stops the arm
by the same 6 mm / 100 N rule.  Grasps and pushes get no give.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import pybullet as p

from flgd.config import CellConfig
from sim_cell import free_space, motion, objects, path_motion
from sim_cell.gripper_contacts import GripperContacts
from sim_cell.robot import RG2_STROKE_SPEED
from sim_cell.stability import Unstable
from sim_cell.world import World

__all__ = ["ArmDriver", "CollisionStop"]

CONTROL_SUBSTEPS = 8        # physics steps per IK tick (30 Hz line samples at 240 Hz physics)
CARRY_TRIAL_TICKS = 10      # control ticks (0.33 s) a freshly gripped object is simulated before a jump
GRIPPER_TIMEOUT = 0.8       # s for a finger motion to come to rest
PRESS_DEPTH = 0.006           # m an object may be squeezed into the table/another object
YIELD_DEPTH = 0.003           # m of squeeze at which an intended press starts to give way
PROTECTIVE_STOP_FORCE = 100.0  # N of vertical push on the gripper that stops the arm (UR: 150 N at the TCP)


class CollisionStop(Exception):
    """The arm stopped on contact, like the UR's protective stop."""


class ArmDriver:
    """The arm and fingers of one simulated cell; one plan at a time (the cell holds its lock around a plan)."""

    def __init__(self, config: CellConfig, world: World, tcp_offset: np.ndarray, home_tcp: np.ndarray,
                 home_joints: np.ndarray):
        self.config = config
        self._world = world
        self._robot = world.robot
        self._contacts = GripperContacts(world.client, world.robot, world.objects, world.table)
        self._tcp_offset = tcp_offset
        self._dt = config.sim.time_step
        self._home_tcp = home_tcp
        self._home_joints = home_joints
        self._press_allowance = 0.0           # m of intended press of the running plan (a shift's press)
        self._press_yield = 0.0               # m the compliant wrist has given way during that press
        self._fingers_until: tuple[float, float] | None = None   # (sim_time of a move that went on early, its end)
        self._watch: Callable[[], bool] | None = None   # run_line's watch while it has not yet fired

    @property
    def contacts(self) -> GripperContacts:
        return self._contacts

    @property
    def _client(self) -> int | None:
        return self._world.client

    def begin_plan(self, press: float) -> None:
        """A plan starts; ``press`` m of squeeze is intended (a shift's press into the object's top), not a
        collision: the wrist gives way that much (the targets rise by the give)."""
        self._press_allowance, self._press_yield = press, 0.0

    def end_plan(self) -> None:
        self._press_allowance = self._press_yield = 0.0

    def tcp(self) -> np.ndarray:
        return self._robot.tcp_pose(self._tcp_offset)

    def plan_lines(self, steps, first: int = 0) -> dict[int, motion.Trajectory]:
        """IK for every MoveL of the plan (from step ``first``) before anything moves."""
        return path_motion.plan_lines(steps, self._robot.joints(), self.tcp(), CONTROL_SUBSTEPS * self._dt,
                                 self._tcp_offset, first)

    def in_gripper(self) -> set[int]:
        """What moves with the gripper: whatever is between the pads, and what a width measurement found
        held (a pinched pair) as long as it still touches the pads."""
        return self._contacts.between_pads() | (self._world.held & self._contacts.held())

    def _free_span(self, traj: motion.Trajectory, carried: set[int], from_end: bool) -> int:
        """Number of ticks at the start (or end) of a line that cannot touch anything."""
        half, below = free_space.carry_extent(self._client, self.tcp()[:3, 3], carried)
        boxes = free_space.obstacles(self._client, self._world.objects, carried)
        return free_space.free_span(traj.tcp[:, :3, 3], half, below, boxes, from_end)

    def _jump(self, q: np.ndarray, seconds: float, carried: set[int]) -> None:
        """Put the arm at ``q`` without physics; carried objects move rigidly with the TCP."""
        c = self._client
        before = self.tcp()
        moving = []
        for body in carried & set(self._world.objects):   # (one may have fallen off the table meanwhile)
            self._world.stability.wake_near(body)   # whatever rested on or against it loses that support
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=c)
            t = np.eye(4)
            t[:3, :3] = np.asarray(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
            t[:3, 3] = pos
            moving.append((body, np.linalg.inv(before) @ t))
        self._robot.teleport(q)
        after = self.tcp()
        for body, rel in moving:
            t = after @ rel
            p.resetBasePositionAndOrientation(body, t[:3, 3].tolist(), objects.quaternion_from_matrix(t[:3, :3]),
                                              physicsClientId=c)
            p.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=c)
            self._world.stability.wake(body)
        self._world.sim_time += seconds

    def run_line(self, traj: motion.Trajectory, stop_force: float = 0.0, settle: bool = True,
                 watch: Callable[[], bool] | None = None) -> bool:
        """Follow ``traj``; True when a guarded line (``stop_force`` N > 0) stopped at a contact.  ``settle=False``:
        the motion goes on into the next trajectory (a blended path), so the servos' last error is not waited out.
        ``watch``: called after every tick (and after a jump) until it returns True (a picture taken on the way)."""
        joints = traj.joints
        n = len(joints) - 1
        if n <= 0:
            if watch is not None:
                watch()
            return False
        self._watch = watch
        try:
            stopped = self._follow(traj, stop_force, settle)
            self._watched()   # not yet taken (or the line was a jump): the end of the line is the last chance
            return stopped
        finally:
            self._watch = None

    def _watched(self) -> None:
        if self._watch is not None and self._watch():
            self._watch = None

    def _follow(self, traj: motion.Trajectory, stop_force: float, settle: bool) -> bool:
        joints = traj.joints
        n = len(joints) - 1
        carried = self.in_gripper()
        # whatever the gripper carries is simulated, so that a weak grip can slip (only a lift may jump, below)
        first = 0
        if not carried and not self._contacts.touching(carried) and not self._world.stability.moving():
            free_head = self._free_span(traj, carried, from_end=False)
            if free_head >= len(joints):
                self._jump(joints[-1], traj.duration, carried)
                return False
            first = max(free_head - 1, 0)
            if first > 0:
                self._jump(joints[first], first * traj.tick, carried)
        last = n - max(self._free_span(traj, carried, from_end=True) - 1, 0)
        straight_up = bool(np.allclose(traj.tcp[0, :3, :3], traj.tcp[-1, :3, :3], atol=1e-6)
                           and np.linalg.norm(traj.tcp[-1, :2, 3] - traj.tcp[0, :2, 3]) < 1e-3
                           and traj.tcp[-1, 2, 3] > traj.tcp[0, 2, 3])
        self._world.set_solver()
        target = self._yielded(traj, first)
        for i in range(first, n):
            if i >= last and i > first and self.may_jump(carried, straight_up, i - first):
                self._jump(joints[-1], (n - i) * traj.tick, carried)
                return False
            nxt = self._yielded(traj, i + 1)
            vel = (nxt - target) / traj.tick
            for sub in range(CONTROL_SUBSTEPS):
                a = (sub + 1) / CONTROL_SUBSTEPS
                self._robot.command_arm(target * (1 - a) + nxt * a, vel)
                self._world.step(1)
                if stop_force > 0.0 and sub % 2 == 1 and self._met_resistance(stop_force):
                    self._hold_still()
                    return True
            target = nxt
            self._watched()
            force, depth = self._contacts.pressing()
            give = self._press_allowance - self._press_yield
            if force > PROTECTIVE_STOP_FORCE or depth > PRESS_DEPTH + give:
                self._robot.command_arm(self._robot.joints())
                raise CollisionStop(f"the gripper pressed down with {force:.0f} N, squeezing an object "
                                     f"{depth * 1000:.0f} mm into what it rests on")
            if give > 0.0 and depth > YIELD_DEPTH:
                # an intended press (a shift) is compliant: the wrist gives way up to the planned press
                self._press_yield += min(depth - YIELD_DEPTH, give)
        end = self._yielded(traj, n)
        self._robot.command_arm(end)
        if not settle:
            return False
        # let the servos close the last tracking error
        for _ in range(10):
            if np.max(np.abs(self._robot.joints() - end)) < 2e-4:
                break
            self._world.step(2)
        return False

    def _met_resistance(self, stop_force: float) -> bool:
        """A guarded move's contact test: the gripper pushed up by ``stop_force`` N, or an object it
        touches squeezed ``YIELD_DEPTH`` into its support (pybullet's soft contacts give before the
        force builds up)."""
        force, depth = self._contacts.pressing()
        return force > stop_force or depth > YIELD_DEPTH

    def _hold_still(self) -> None:
        """Stop the arm where it is, as a controller's stopL does, and let it settle."""
        self._robot.command_arm(self._robot.joints())
        self._world.step(8)

    def _yielded(self, traj: motion.Trajectory, i: int) -> np.ndarray:
        """Joint target of tick ``i``, raised by the give of a compliant press (see ``begin_plan``)."""
        return motion.raised_joints(traj, i, self._press_yield, self._tcp_offset)

    def may_jump(self, carried: set[int], straight_up: bool, simulated_ticks: int) -> bool:
        """Whether the rest of a line (already known to be clear of obstacles) may be a jump: the
        gripper touches nothing it does not carry, and what it carries is on a straight lift, has been
        carried for ``CARRY_TRIAL_TICKS`` and is still in the gripper (a carry sideways never jumps)."""
        if carried and (not straight_up or simulated_ticks < CARRY_TRIAL_TICKS
                        or not carried <= self.in_gripper()):
            return False
        return not self._contacts.touching(carried) and not self._world.stability.moving(exclude=carried)

    def run_gripper(self, width: float, force: float, proceed_after: float = 0.0) -> None:
        """The fingers to ``width``, on the RG2's time; with ``proceed_after`` (m) a move with nothing in reach
        charges only that much travel and the rest to the next gripper command (the arm moves meanwhile)."""
        if self._fingers_until is not None:   # a move that went on early: its end first (a reset clock owes none)
            began, end = self._fingers_until
            if began <= self._world.sim_time < end:
                self._world.sim_time = end
            self._fingers_until = None
        opening = width > self._robot.finger_target_width() + 1e-4 or width > self._robot.width() + 1e-3
        if opening and self._world.held:
            self._release_held()
        if not self.in_gripper() and not self._contacts.touching(set()) and free_space.clear(
                self.tcp()[None, :3, 3], free_space.GRIPPER_HALF_SIZE, 0.0,
                free_space.obstacles(self._client, self._world.objects, set())):
            # nothing within reach of the fingers: set them without stepping the physics
            travel = abs(width - self._robot.width())
            self._robot.set_fingers(width, force)
            began = self._world.sim_time
            if 0.0 < proceed_after < travel:
                self._fingers_until = (began, began + travel / RG2_STROKE_SPEED)
                travel = proceed_after
            self._world.sim_time += travel / RG2_STROKE_SPEED
            return
        started, start_width = self._world.sim_time, self._robot.width()
        self._robot.command_gripper(width, force)
        closing = width < self._robot.width() - 1e-3
        steps = int(GRIPPER_TIMEOUT / self._dt)
        for k in range(0, steps, 4):
            # the costly solver only once a closing pad touches something (free travel needs none)
            self._world.set_solver(squeeze=closing and self._contacts.pads_touch())
            self._world.step(4)
            if k >= 12 and self._robot.finger_speed() < 2e-3:
                break
        # the simulated fingers travel faster than an RG2's: the move takes the RG2's time on the cell's clock
        rg2_time = abs(self._robot.width() - start_width) / RG2_STROKE_SPEED
        self._world.sim_time += max(0.0, rg2_time - (self._world.sim_time - started))

    def fingers_at_rest(self) -> None:
        """Step until the fingers have stopped (as the real cell reads a settled width), at most 1 s.

        Why: a block slipping out as the arm arrives home is still between the
        pads for a moment; the fingers go on closing after it.
        """
        still = 0
        for _ in range(int(1.0 / self._dt) // 4):
            still = still + 1 if self._robot.finger_speed() < 2e-3 else 0
            if still >= 2:
                return
            self._world.step(4)

    def _release_held(self) -> None:
        """Opening the gripper on a held object still in it hands it out of the cell (carried out); one that
        slipped out on the way stays in the scene, where it fell."""
        for body in list(self._world.held & self.in_gripper()):
            if body in self._world.objects:
                self._world.remove(body, "grasped_out")
        self._world.held.clear()

    def note_held(self) -> None:
        """What the width measurement found in the gripper is held (see ``GripperContacts.held``)."""
        self._world.held = self._contacts.held()

    def go_home(self) -> None:
        gr = self.config.gripper
        try:
            self.run_gripper(gr.open_width, gr.force)
            pose = self.tcp()
            up = pose.copy()
            up[2, 3] = max(pose[2, 3], self.config.workspace.z[0] + self.config.robot.lift_height)
            tick = CONTROL_SUBSTEPS * self._dt
            rb = self.config.robot
            first = motion.plan_line(self._robot.joints(), pose, up, rb.speed, rb.acceleration, tick, self._tcp_offset)
            second = motion.plan_line(first.joints[-1], up, self._home_tcp, rb.speed,
                                      rb.acceleration, tick, self._tcp_offset)
            self.run_line(first)
            self.run_line(second)
        except (motion.Unreachable, Unstable, CollisionStop):
            self._robot.teleport(self._home_joints, gr.open_width)
        self._world.held.clear()
        self.remove_outside()

    def remove_outside(self) -> None:
        """Objects out of the workspace leave the cell, except what the gripper carries (until it opens)."""
        self._world.remove_outside(keep=self.in_gripper())
