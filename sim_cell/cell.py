"""SimCell: the PyBullet robot cell (UR5e + RG2 + D415) behind flgd's cell interface.

Each instance owns one headless physics client, so several cells can live in
one process.  A plan runs like on the real arm: every MoveL becomes a straight
TCP line through closed-form IK and joint position control at the step's
speed and acceleration, gripper commands drive force-limited fingers, and
MeasureWidth reads the finger joints.

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
  * Sleeping: an object still for 0.2 s (|v|^2 + |w|^2 < 2.5e-5) that the gripper
    does not touch is put to sleep, and the solver skips it until an awake body
    touches it (pybullet's islands) or the cell wakes it because an object it
    rested on or against was removed or carried away by a jump.  The costly
    150-iteration squeeze then pays only for the gripper and what touches it.
  * IK: a line's ticks are solved in one batch (``kinematics.inverse_many``).
  Skipped spans still advance ``sim_time`` by their real duration.

Protective stop: a line that presses the gripper down on an object (> 100 N, or
an object squeezed > 6 mm into the table or another object -- pybullet's soft
contacts let a block sink where a real one would stop the arm) stops; the arm
retreats home and the plan fails with a "collision stop" failure.

Guarded moves (``MoveL.stop_on_contact`` > 0, a grasp's descent): the line is
checked every two physics steps and ends where the gripper meets that force (or
squeezes an object ``YIELD_DEPTH`` into its support); the arm holds there and
the rest of the plan is re-planned from the pose it stopped at.

Shift press: a shift presses the closed fingers ``robot.shift_press`` into the
object's top on purpose, so that friction drags it (paper III-A).  Rigid
position control would squeeze the block through the 6 mm rule every time;
instead the press is compliant, like the real fingertips and wrist: once an
object is squeezed more than ``YIELD_DEPTH`` (3 mm), the rest of the plan's
targets rise by the excess, up to ``shift_press`` in total.  A press that the
give cannot absorb (the surface height was read too low) still stops the arm
by the same 6 mm / 100 N rule.  Grasps and pushes get no give.

Bookkeeping: an object measured as held (touching both pads at a MeasureWidth
step) stays in the cell, in the gripper, until the gripper opens on it (at the
place pose of plan_release, or anywhere if the caller skips the place step): then
it is removed and counted in ``stats["grasped_out"]``.  Any other object whose
centre leaves the workspace or falls off the table is removed and counted in
``stats["left_workspace"]`` (one that falls off the table at once, in mid-fall:
there is no floor, and a long fall is no unstable physics); of those, the ones that were
in the gripper when this plan's grasp lift step ended, or were measured as held and
carried into this plan (a place), are also counted in ``stats["dropped"]`` (lifted,
then the grip gave way: the evaluation reports them apart from objects pushed out).  An unstable simulation (NaNs, objects faster than
4 m/s or thrown up, interpenetration > 15 mm at three checks 0.2 s apart or
> 40 mm at once) resets the scene and fails the plan with a failure text
starting with "unstable" and naming the plan step (``stats["unstable_resets"]``).
A single deep check is not enough: a closing finger wedging a prism or half-disk
into the table dips it 15-30 mm for a moment, which the solver resolves (in 20-block
clutter that alone aborted about half of all evaluation runs).
In their own modules: world, stability, scene_maker, randomisation, gripper_contacts, free_space.
What stays here is one plan's execution -- the step loop, the arm's lines, the fingers and the carry --
which share per-plan state (press allowance and give, carry trials, what was lifted) under one lock;
split, each part would reach into the others' state, so the module stays whole at ~600 lines.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pybullet as p

from flgd.cell import Cell, CellFault, ContactStop, ExecutionResult, Frame
from flgd.config import CellConfig
from flgd.geometry import ToolPose, pose_matrix
from flgd.plans import LIFT_LABEL, GripperCommand, MeasureWidth, MoveL
from flgd.safety import CheckedPlan
from sim_cell import camera as simcam
from sim_cell import free_space, kinematics, motion, objects, scene_maker, scenes
from sim_cell.gripper_contacts import GripperContacts
from sim_cell.randomisation import Randomiser
from sim_cell.robot import FINGER_SPEED, GRIPPER_TCP_OFFSET, READY_JOINTS
from sim_cell.scene_maker import PRESET_DIR, preset_scenes
from sim_cell.stability import Unstable as _Unstable
from sim_cell.world import ObjectState, World

__all__ = ["SimCell", "ObjectState", "PRESET_DIR", "preset_scenes"]

CONTROL_SUBSTEPS = 8        # physics steps per IK tick (30 Hz line samples at 240 Hz physics)
CARRY_TRIAL_TICKS = 10      # control ticks (0.33 s) a freshly gripped object is simulated before a jump
GRIPPER_TIMEOUT = 0.8       # s for a finger motion to come to rest
PRESS_DEPTH = 0.006           # m an object may be squeezed into the table/another object
YIELD_DEPTH = 0.003           # m of squeeze at which an intended press starts to give way
PROTECTIVE_STOP_FORCE = 100.0  # N of vertical push on the gripper that stops the arm (UR: 150 N at the TCP)
MAX_SETTLE_AFTER_PLAN = 1.0  # s the world runs on after a plan while something still moves


class SimCell(Cell):
    """PyBullet cell; see the module docstring for what is simulated and what is shortened."""

    name = "sim"

    def __init__(self, config: CellConfig):
        super().__init__(config)
        off = np.asarray(config.robot.tcp_offset, dtype=float)
        if np.max(np.abs(off - np.asarray(GRIPPER_TCP_OFFSET))) > 1e-3:
            raise ValueError(f"{config.source}: robot.tcp_offset: got {list(config.robot.tcp_offset)!r}, "
                             f"expected {list(GRIPPER_TCP_OFFSET)!r} for the simulated RG2 (urdf/rg2.urdf)")
        self._tcp_offset = off
        self._dt = config.sim.time_step
        home = config.robot.home
        home_pose = ToolPose.top_down(*home.position, home.yaw)
        self._home_tcp = pose_matrix(home_pose.position, home_pose.matrix)
        q = kinematics.nearest_solution(kinematics.inverse(motion.tcp_to_flange(self._home_tcp, off)), READY_JOINTS)
        if q is None:
            raise ValueError(f"{config.source}: robot.home: {list(home.position)!r} is out of the UR5e's reach")
        self._home_joints = q
        self._world = World(config, q)
        self._robot = self._world.robot
        self._contacts = GripperContacts(self._world.client, self._robot, self._world.objects, self._world.table)
        seeds = np.random.SeedSequence(config.sim.seed).spawn(2)
        self._noise_rng = np.random.default_rng(seeds[1])
        self._object_count = config.sim.objects
        # What the current objects came from, for logs ("random 20", "packed 9", "scene pile"):
        # a training log must tell a packed scene from a drop.
        self.scene_kind = "none"
        self._randomiser = Randomiser(config, np.random.default_rng(seeds[0]), self._world.client)
        self._press_allowance = 0.0           # m of intended press of the running plan (a shift's press)
        self._press_yield = 0.0               # m the compliant wrist has given way during that press
        # Perception is told the configured camera; the picture is taken from where the camera truly is.
        self._camera = simcam.CameraModel.from_config(config.camera)
        self._true_camera = simcam.CameraModel.from_config(config.camera, config.sim.camera_pose_error)
        self._depth_noise = simcam.DepthNoise.from_config(config.sim)
        self._robot.teleport(q, config.gripper.open_width)
        self._closed = False
        if config.sim.scene:
            self.load_scene(config.sim.scene)
        else:
            self.reset_scene()

    # ================================================================== public API
    def capture(self) -> Frame:
        """Render a D415 frame (raw colour + uint16 depth) of the current scene."""
        return self._capture(labelled=False)[0]

    def capture_labelled(self) -> tuple[Frame, np.ndarray]:
        """A frame as ``capture`` makes it plus which object each pixel shows (ground truth, never for a policy).

        Labels are HxW int32: 0 = no object (table, arm, nothing), else the object's body id.  They come from the
        same render as the frame, so they line up pixel for pixel with its (noisy) depth.
        """
        return self._capture(labelled=True)

    def _capture(self, labelled: bool) -> tuple[Frame, np.ndarray | None]:
        with self._lock:
            self._check_open()
            cfg = self.config.camera
            direction, ambient, diffuse = self._randomiser.light
            if labelled:
                color, depth, seg = simcam.render_labelled(self._client, self._true_camera, direction, ambient=ambient,
                                                           diffuse=diffuse)
                labels = np.where(np.isin(seg, list(self._world.objects)), seg, 0).astype(np.int32)
            else:
                color, depth = simcam.render(self._client, self._true_camera, direction, ambient=ambient,
                                             diffuse=diffuse)
                labels = None
            if self.config.sim.depth_noise:
                depth = simcam.add_depth_noise(depth, self._noise_rng, self._depth_noise,
                                               fx=float(self._true_camera.intrinsics[0, 0]))
            raw = simcam.to_raw_depth(depth, cfg.depth_scale, cfg.depth_range)
            return Frame(color=color, depth=raw, depth_scale=cfg.depth_scale,
                         intrinsics=self._camera.intrinsics.copy(), camera_pose=self._camera.pose.copy(),
                         timestamp=self._sim_time, tool_position=tuple(float(v) for v in self._tcp()[:3, 3])), labels

    def remove_object(self, body: int, settle: float = 0.25) -> bool:
        """Take one object out of the scene (as if picked) and let the rest settle.

        False when the physics went wrong while settling: the scene was then reset to fresh clutter.
        """
        with self._lock:
            self._check_open()
            if body not in self._world.objects:
                raise ValueError(f"remove_object: no object with body id {body} in the scene")
            self._world.stability.wake_near(body)
            p.removeBody(body, physicsClientId=self._client)
            self._world.objects.pop(body)
            self._world.held.discard(body)
            self._world.lifted.discard(body)
            try:
                self._world.settle(settle)
            except _Unstable:
                self.reset_scene()
                return False
            return True

    def execute(self, plan: CheckedPlan) -> ExecutionResult:
        """Run a checked plan; ``duration`` is the simulated time the motions took."""
        planned = plan.verify(self.config)
        steps = planned.steps
        with self._lock:
            self._check_open()
            t0 = self._sim_time
            try:
                lines = self._plan_lines(steps)
            except motion.Unreachable as exc:
                return ExecutionResult(completed=False, failure=f"unreachable: {exc}; the arm did not move",
                                       duration=0.0)
            widths: list[float] = []
            stops: list[ContactStop] = []
            gripper = 0.0   # simulated seconds of the gripper's steps
            # A shift presses the closed fingers ``robot.shift_press`` into the object's top on purpose:
            # that much extra squeeze is the intended press, not a collision.
            self._press_allowance = self.config.robot.shift_press if planned.primitive == "shift" else 0.0
            self._press_yield = 0.0
            self._world.lifted = self._world.held & self._in_gripper()   # carried in (to the place): lost = dropped
            try:
                for i, step in enumerate(steps):
                    if isinstance(step, MoveL):
                        if self._run_line(lines[i], step.stop_on_contact):
                            short = float(np.linalg.norm(self._tcp()[:3, 3] - np.asarray(step.pose.position)))
                            stops.append(ContactStop(step.label, short))
                            # a guarded move met resistance: the rest of the plan starts where it stopped
                            lines.update(self._plan_lines(steps, first=i + 1))
                        if step.label == LIFT_LABEL:   # pinched pairs too (``held``), as a measurement counts them
                            self._world.lifted = self._in_gripper() | self._contacts.held()
                    elif isinstance(step, GripperCommand):
                        started = self._sim_time
                        self._run_gripper(step.width, step.force)
                        gripper += self._sim_time - started
                    elif isinstance(step, MeasureWidth):
                        started = self._sim_time
                        self._fingers_at_rest()
                        widths.append(self.gripper_width())
                        self._note_held()
                        gripper += self._sim_time - started
            except _CollisionStop as exc:
                self._press_allowance = self._press_yield = 0.0
                self._go_home()
                return ExecutionResult(completed=False, widths=widths,
                                       failure=f"collision stop: {exc}; the arm retreated home",
                                       duration=self._sim_time - t0, contact_stops=stops, gripper_time=gripper)
            except motion.Unreachable as exc:  # re-planning from where a guarded move stopped
                self._press_allowance = self._press_yield = 0.0
                self._go_home()
                return ExecutionResult(completed=False, widths=widths,
                                       failure=f"unreachable after a contact stop: {exc}; the arm retreated home",
                                       duration=self._sim_time - t0, contact_stops=stops, gripper_time=gripper)
            except _Unstable as exc:
                self._press_allowance = self._press_yield = 0.0
                self.stats["unstable_resets"] += 1
                self.reset_scene()
                where = f"{planned.primitive} step {i} ({steps[i].label or type(steps[i]).__name__})"
                return ExecutionResult(completed=False, widths=widths,
                                       failure=f"unstable simulation ({exc}) during {where}; scene reset",
                                       duration=self._sim_time - t0, contact_stops=stops, gripper_time=gripper)
            self._press_allowance = self._press_yield = 0.0
            try:
                # the world goes on between actions: a block dropped or nudged comes to rest before the
                # next picture instead of hanging frozen where the last simulated tick left it
                self._settle_until_still(MAX_SETTLE_AFTER_PLAN)
            except _Unstable as exc:
                self.stats["unstable_resets"] += 1
                self.reset_scene()
                return ExecutionResult(completed=False, widths=widths,
                                       failure=f"unstable simulation ({exc}) after {planned.primitive}; scene reset",
                                       duration=self._sim_time - t0, contact_stops=stops, gripper_time=gripper)
            self._remove_outside()
            return ExecutionResult(completed=True, widths=widths, duration=self._sim_time - t0,
                                   contact_stops=stops, gripper_time=gripper)

    def gripper_width(self) -> float:
        """Distance between the finger pads, from the finger joint positions (m)."""
        with self._lock:
            self._check_open()
            return self._robot.width()

    def reset_scene(self) -> None:
        """New clutter: ``sim.objects`` random objects (see set_object_count), or the config's scene file."""
        with self._lock:
            self._check_open()
            if self.config.sim.scene:
                self.load_scene(self.config.sim.scene)
            elif self.config.sim.packed_scenes > 0 and self._randomiser.rng.random() < self.config.sim.packed_scenes:
                self.make_packed()
            else:
                self.make_clutter(self._object_count)

    def recover(self) -> None:
        """Bring the arm home with the gripper open (a held object is carried out)."""
        with self._lock:
            self._check_open()
            self._go_home()

    def workspace_empty_hint(self) -> bool:
        """True when no object is left in the workspace."""
        with self._lock:
            self._check_open()
            self._remove_outside()
            return len(self._world.objects) == 0

    def close(self) -> None:
        with self._lock:
            self._world.close()

    # -- for curricula, tests and benchmarks
    def set_object_count(self, n: int) -> None:
        """Number of random objects for the next ``reset_scene`` (the curriculum's 10 -> 20)."""
        if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= 60:
            raise ValueError(f"object count: got {n!r}, expected an integer 0..60")
        self._object_count = n

    def make_packed(self, groups: int | None = None) -> int:
        """Replace the objects by a packed arrangement (sim_cell.packed): rows of blocks laid flush.
        Returns the count."""
        with self._lock:
            self._check_open()
            self.scene_kind = scene_maker.make_packed(self._world, self._randomiser, groups, self._object_count)
            return len(self._world.objects)

    def make_clutter(self, n: int, spread: float | None = None) -> int:
        """Replace the objects by ``n`` random ones dropped within +-``spread`` m of the workspace
        centre (None = the whole workspace); a small spread piles them up.  Returns the count."""
        with self._lock:
            self._check_open()
            self.scene_kind = scene_maker.make_clutter(self._world, self._randomiser, n, spread)
            return len(self._world.objects)

    def load_scene(self, scene: "str | Path | scenes.Scene", vpg_meshes: str | Path | None = None) -> int:
        """Replace the objects by a scene (a Scene, a scene YAML file, or a VPG test case .txt);
        returns the number of objects placed.  Relative names are looked up in sim_cell/scenes/ too."""
        with self._lock:
            self._check_open()
            scene = scene_maker.read_scene(scene, vpg_meshes)
            try:
                self.scene_kind = scene_maker.place_scene(self._world, scene)
            except scenes.SceneError:
                self.scene_kind = "none"
                raise
            return len(self._world.objects)

    def save_scene(self, path: str | Path) -> None:
        """Write the current objects and poses as a scene file (workspace frame)."""
        with self._lock:
            self._check_open()
            scenes.save_scene(self.current_scene(), path)

    def current_scene(self) -> scenes.Scene:
        """The current objects and poses as a scene (workspace frame)."""
        return scene_maker.current_scene(self._world)

    def object_states(self) -> list[ObjectState]:
        """Ground truth of every object in the scene, in the base frame."""
        with self._lock:
            self._check_open()
            return self._world.object_states()

    def add_object(self, spec: objects.ObjectSpec, settle: float = 0.25) -> int:
        """Put one object (pose in the base frame) into the scene; returns its body id."""
        with self._lock:
            self._check_open()
            body = self._world.add(spec)
            self._world.settle(settle)
            return body

    def simulate(self, seconds: float) -> None:
        """Let the world run for ``seconds`` with the arm holding still."""
        with self._lock:
            self._check_open()
            self._world.step(int(round(seconds / self._dt)))

    @property
    def object_count(self) -> int:
        return len(self._world.objects)

    @property
    def sim_time(self) -> float:
        return self._world.sim_time

    @property
    def stats(self) -> dict[str, int]:
        """Counts of objects ``grasped_out`` and ``left_workspace``, ``unstable_resets`` and ``scenes`` laid out."""
        return self._world.stats

    # ================================================================== internals
    @property
    def _client(self) -> int | None:
        """The pybullet client (None once closed), for raw pybullet calls of tests and oracles."""
        return self._world.client

    @property
    def _sim_time(self) -> float:
        return self._world.sim_time

    def _check_open(self) -> None:
        if self._world.client is None:
            raise CellFault("the simulated cell is closed")

    def _tcp(self) -> np.ndarray:
        return self._robot.tcp_pose(self._tcp_offset)

    def _plan_lines(self, steps, first: int = 0) -> dict[int, motion.Trajectory]:
        """IK for every MoveL of the plan (from step ``first``) before anything moves."""
        return motion.plan_lines(steps, self._robot.joints(), self._tcp(), CONTROL_SUBSTEPS * self._dt,
                                 self._tcp_offset, first)

    # -- motions
    def _in_gripper(self) -> set[int]:
        """What moves with the gripper: whatever is between the pads, and what a width measurement found
        held (a pinched pair) as long as it still touches the pads."""
        return self._contacts.between_pads() | (self._world.held & self._contacts.held())

    def _free_span(self, traj: motion.Trajectory, carried: set[int], from_end: bool) -> int:
        """Number of ticks at the start (or end) of a line that cannot touch anything."""
        half, below = free_space.carry_extent(self._client, self._tcp()[:3, 3], carried)
        boxes = free_space.obstacles(self._client, self._world.objects, carried)
        return free_space.free_span(traj.tcp[:, :3, 3], half, below, boxes, from_end)

    def _jump(self, q: np.ndarray, seconds: float, carried: set[int]) -> None:
        """Put the arm at ``q`` without physics; carried objects move rigidly with the TCP."""
        c = self._client
        before = self._tcp()
        moving = []
        for body in carried & set(self._world.objects):   # (one may have fallen off the table meanwhile)
            self._world.stability.wake_near(body)   # whatever rested on or against it loses that support
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=c)
            t = np.eye(4)
            t[:3, :3] = np.asarray(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
            t[:3, 3] = pos
            moving.append((body, np.linalg.inv(before) @ t))
        self._robot.teleport(q)
        after = self._tcp()
        for body, rel in moving:
            t = after @ rel
            p.resetBasePositionAndOrientation(body, t[:3, 3].tolist(), objects.quaternion_from_matrix(t[:3, :3]),
                                              physicsClientId=c)
            p.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=c)
            self._world.stability.wake(body)
        self._world.sim_time += seconds

    def _run_line(self, traj: motion.Trajectory, stop_force: float = 0.0) -> bool:
        """Follow ``traj``; True when a guarded line (``stop_force`` N > 0) stopped at a contact."""
        joints = traj.joints
        n = len(joints) - 1
        if n <= 0:
            return False
        carried = self._in_gripper()
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
            if i >= last and i > first and self._may_jump(carried, straight_up, i - first):
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
            force, depth = self._contacts.pressing()
            give = self._press_allowance - self._press_yield
            if force > PROTECTIVE_STOP_FORCE or depth > PRESS_DEPTH + give:
                self._robot.command_arm(self._robot.joints())
                raise _CollisionStop(f"the gripper pressed down with {force:.0f} N, squeezing an object "
                                     f"{depth * 1000:.0f} mm into what it rests on")
            if give > 0.0 and depth > YIELD_DEPTH:
                # an intended press (a shift) is compliant: the wrist gives way up to the planned press
                self._press_yield += min(depth - YIELD_DEPTH, give)
        end = self._yielded(traj, n)
        self._robot.command_arm(end)
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
        """Joint target of tick ``i``, raised by the give of a compliant press (see ``_press_yield``)."""
        return motion.raised_joints(traj, i, self._press_yield, self._tcp_offset)

    def _may_jump(self, carried: set[int], straight_up: bool, simulated_ticks: int) -> bool:
        """Whether the rest of a line (already known to be clear of obstacles) may be a jump: the
        gripper touches nothing it does not carry, and what it carries is on a straight lift, has been
        carried for ``CARRY_TRIAL_TICKS`` and is still in the gripper (a carry sideways never jumps)."""
        if carried and (not straight_up or simulated_ticks < CARRY_TRIAL_TICKS
                        or not carried <= self._in_gripper()):
            return False
        return not self._contacts.touching(carried) and not self._world.stability.moving(exclude=carried)

    def _run_gripper(self, width: float, force: float) -> None:
        opening = width > self._robot.finger_target_width() + 1e-4 or width > self._robot.width() + 1e-3
        if opening and self._world.held:
            self._release_held()
        if not self._in_gripper() and not self._contacts.touching(set()) and free_space.clear(
                self._tcp()[None, :3, 3], free_space.GRIPPER_HALF_SIZE, 0.0,
                free_space.obstacles(self._client, self._world.objects, set())):
            # nothing within reach of the fingers: set them without stepping the physics
            travel = abs(width - self._robot.width()) / 2.0
            self._robot.set_fingers(width, force)
            self._world.sim_time += travel / FINGER_SPEED
            return
        self._robot.command_gripper(width, force)
        closing = width < self._robot.width() - 1e-3
        steps = int(GRIPPER_TIMEOUT / self._dt)
        for k in range(0, steps, 4):
            # the costly solver only once a closing pad touches something (free travel needs none)
            self._world.set_solver(squeeze=closing and self._contacts.pads_touch())
            self._world.step(4)
            if k >= 12 and self._robot.finger_speed() < 2e-3:
                break

    def _fingers_at_rest(self) -> None:
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
        for body in list(self._world.held & self._in_gripper()):
            if body in self._world.objects:
                self._world.remove(body, "grasped_out")
        self._world.held.clear()

    def _note_held(self) -> None:
        """What the width measurement found in the gripper is held (see ``GripperContacts.held``)."""
        self._world.held = self._contacts.held()

    def _go_home(self) -> None:
        gr = self.config.gripper
        try:
            self._run_gripper(gr.open_width, gr.force)
            pose = self._tcp()
            up = pose.copy()
            up[2, 3] = max(pose[2, 3], self.config.workspace.z[0] + self.config.robot.lift_height)
            tick = CONTROL_SUBSTEPS * self._dt
            rb = self.config.robot
            first = motion.plan_line(self._robot.joints(), pose, up, rb.speed, rb.acceleration, tick, self._tcp_offset)
            second = motion.plan_line(first.joints[-1], up, self._home_tcp, rb.speed,
                                      rb.acceleration, tick, self._tcp_offset)
            self._run_line(first)
            self._run_line(second)
        except (motion.Unreachable, _Unstable, _CollisionStop):
            self._robot.teleport(self._home_joints, gr.open_width)
        self._world.held.clear()
        self._remove_outside()

    # -- the world, as execute uses it
    def _settle_until_still(self, limit: float) -> None:
        self._world.settle_until_still(limit)

    def _remove_outside(self) -> None:
        """Objects out of the workspace leave the cell, except what the gripper carries (until it opens)."""
        self._world.remove_outside(keep=self._in_gripper())


class _CollisionStop(Exception):
    """The arm stopped on contact, like the UR's protective stop."""
