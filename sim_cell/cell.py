"""SimCell: the PyBullet robot cell (UR5e + RG2 + D415) behind flgd's cell interface.

Each instance owns one headless physics client, so several cells can live in
one process.  A plan runs like on the real arm (``sim_cell.arm_driver``: straight
TCP lines through IK and joint position control, force-limited fingers, the
shortcuts that keep a plan cheap, the protective stop, guarded moves and the
compliant shift press); this module is the cell around it: the camera, the
scenes, and one plan's step loop with its outcome.

Protective stop: the arm retreats home and the plan fails with a "collision
stop" failure.  A guarded move (a grasp's descent) that met resistance holds
there and the rest of the plan is re-planned from the pose it stopped at.

Sleeping: an object still for 0.2 s (|v|^2 + |w|^2 < 2.5e-5) that the gripper
does not touch is put to sleep, and the solver skips it until an awake body
touches it (pybullet's islands) or the cell wakes it because an object it
rested on or against was removed or carried away by a jump.  The costly
150-iteration squeeze then pays only for the gripper and what touches it.

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
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import pybullet as p

from flgd.camera_view import VIEW_MARGIN, in_view_on_the_way
from flgd.cell import Cell, CellFault, ContactStop, ExecutionResult, Frame, FrameOnTheWay
from flgd.config import CellConfig
from flgd.geometry import ToolPose, pose_matrix
from flgd.plans import LIFT_LABEL, GripperCommand, MeasureWidth, MoveL, abort_steps
from flgd.safety import CheckedPlan
from sim_cell import camera as simcam
from sim_cell import kinematics, motion, objects, scene_maker, scenes
from sim_cell.arm_driver import ArmDriver, CollisionStop
from sim_cell.randomisation import Randomiser
from sim_cell.robot import GRIPPER_TCP_OFFSET, READY_JOINTS
from sim_cell.scene_maker import PRESET_DIR, preset_scenes
from sim_cell.stability import Unstable as _Unstable
from sim_cell.world import ObjectState, World

__all__ = ["SimCell", "ObjectState", "PRESET_DIR", "preset_scenes"]

MAX_SETTLE_AFTER_PLAN = 1.0  # s the world runs on after a plan while something still moves
ARM_CHECK_INTERVAL = 0.05   # s of simulated time between renders looked at for the arm on the way home


class SimCell(Cell):
    """PyBullet cell; see the module docstring for what is simulated and what is shortened."""

    name = "sim"

    def __init__(self, config: CellConfig):
        super().__init__(config)
        self._frame_on_the_way: FrameOnTheWay | None = None   # execute_and_capture's, for the plan it runs
        off = np.asarray(config.robot.tcp_offset, dtype=float)
        if np.max(np.abs(off - np.asarray(GRIPPER_TCP_OFFSET))) > 1e-3:
            raise ValueError(f"{config.source}: robot.tcp_offset: got {list(config.robot.tcp_offset)!r}, "
                             f"expected {list(GRIPPER_TCP_OFFSET)!r} for the simulated RG2 (urdf/rg2.urdf)")
        self._dt = config.sim.time_step
        home = config.robot.home
        home_pose = ToolPose.top_down(*home.position, home.yaw)
        home_tcp = pose_matrix(home_pose.position, home_pose.matrix)
        q = kinematics.nearest_solution(kinematics.inverse(motion.tcp_to_flange(home_tcp, off)), READY_JOINTS)
        if q is None:
            raise ValueError(f"{config.source}: robot.home: {list(home.position)!r} is out of the UR5e's reach")
        self._world = World(config, q)
        self._robot = self._world.robot
        self._arm = ArmDriver(config, self._world, off, home_tcp, q)
        seeds = np.random.SeedSequence(config.sim.seed).spawn(2)
        self._noise_rng = np.random.default_rng(seeds[1])
        self._object_count = config.sim.objects
        # What the current objects came from, for logs ("random 20", "packed 9", "scene pile"):
        # a training log must tell a packed scene from a drop.
        self.scene_kind = "none"
        self._randomiser = Randomiser(config, np.random.default_rng(seeds[0]), self._world.client)
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
            color, depth, seg = self._render(segmented=labelled)
            labels = None if seg is None else np.where(np.isin(seg, list(self._world.objects)), seg, 0).astype(np.int32)
            return self._frame(color, depth), labels

    def _render(self, segmented: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        direction, ambient, diffuse = self._randomiser.light
        if segmented:
            return simcam.render_labelled(self._client, self._true_camera, direction, ambient=ambient, diffuse=diffuse)
        color, depth = simcam.render(self._client, self._true_camera, direction, ambient=ambient, diffuse=diffuse)
        return color, depth, None

    def _frame(self, color: np.ndarray, depth: np.ndarray) -> Frame:
        """A D415 frame of a render (true depth in metres): the simulated noise, raw units, the tool's position."""
        cfg = self.config.camera
        if self.config.sim.depth_noise:
            depth = simcam.add_depth_noise(depth, self._noise_rng, self._depth_noise,
                                           fx=float(self._true_camera.intrinsics[0, 0]))
        raw = simcam.to_raw_depth(depth, cfg.depth_scale, cfg.depth_range)
        return Frame(color=color, depth=raw, depth_scale=cfg.depth_scale,
                     intrinsics=self._camera.intrinsics.copy(), camera_pose=self._camera.pose.copy(),
                     timestamp=self._sim_time, tool_position=tuple(float(v) for v in self._tcp()[:3, 3]))

    def _arm_over_workspace(self, depth: np.ndarray, seg: np.ndarray) -> bool:
        """Whether a render shows part of the arm, or of what it holds, where the heightmaps look: a pixel of it
        whose surface point lies over the workspace (the heightmaps would show it as an object) or whose ray meets
        the table inside it (it hides the table there).  The tool model of ``flgd.camera_view`` (a cylinder, tested
        by its rays) leaves out a long held object's overhang and the wrist beside the gripper."""
        carried = list(self._arm.in_gripper() | self._world.held)
        rows, cols = np.nonzero(((seg == self._world.robot.body) | np.isin(seg, carried)) & (depth > 0))
        if rows.size == 0:
            return False
        cam, ws = self._true_camera, self.config.workspace
        rays = cam.pose[:3, :3] @ (np.linalg.inv(cam.intrinsics) @ np.stack([cols + 0.5, rows + 0.5,
                                                                              np.ones(rows.size)]))
        origin = cam.pose[:3, 3]
        points = origin[:2, None] + depth[rows, cols] * rays[:2]   # the optical z is the render's depth
        down = rays[2] < 0.0
        hits = origin[:2, None] + (ws.table_z - origin[2]) / np.where(down, rays[2], -1.0) * rays[:2]

        def over(xy: np.ndarray) -> np.ndarray:
            return ((ws.x[0] - VIEW_MARGIN <= xy[0]) & (xy[0] <= ws.x[1] + VIEW_MARGIN)
                    & (ws.y[0] - VIEW_MARGIN <= xy[1]) & (xy[1] <= ws.y[1] + VIEW_MARGIN))
        return bool(np.any(over(points)) or np.any(down & over(hits)))

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
        on_frame, self._frame_on_the_way = self._frame_on_the_way, None
        return self._run(plan, on_frame)

    def execute_and_capture(self, plan: CheckedPlan, on_frame: FrameOnTheWay) -> ExecutionResult:
        """Run a checked plan; on its last move, the first tick with the tool out of the camera's view renders a
        frame for ``on_frame`` (with the simulated seconds since the plan started) and the motion goes on.  The plan
        runs through ``execute``, so a subclass that wraps it wraps this plan too."""
        self._frame_on_the_way = on_frame
        try:
            return self.execute(plan)
        finally:
            self._frame_on_the_way = None

    def _watch_view(self, on_frame: FrameOnTheWay, t0: float) -> Callable[[], bool]:
        """A check for each tick of the last move: True once the frame has been taken and handed over.  Once the
        tool is out of view, a render every ``ARM_CHECK_INTERVAL`` is looked at and handed over only if no part of
        the arm shows over the workspace."""
        next_render = -np.inf

        def watch() -> bool:
            nonlocal next_render
            if self._sim_time < next_render or in_view_on_the_way(tuple(float(v) for v in self._tcp()[:3, 3]),
                                                                   self.config):
                return False
            color, depth, seg = self._render(segmented=True)
            assert seg is not None
            if self._arm_over_workspace(depth, seg):
                next_render = self._sim_time + ARM_CHECK_INTERVAL
                return False
            on_frame(self._frame(color, depth), self._sim_time - t0)
            return True
        return watch

    def _run(self, plan: CheckedPlan, on_frame: FrameOnTheWay | None) -> ExecutionResult:
        planned = plan.verify(self.config)
        steps = planned.steps
        with self._lock:
            self._check_open()
            t0 = self._sim_time
            moves = [k for k, s in enumerate(steps) if isinstance(s, MoveL)]
            watch = None if on_frame is None or not moves else self._watch_view(on_frame, t0)
            try:
                lines = self._arm.plan_lines(steps)
            except motion.Unreachable as exc:
                return ExecutionResult(completed=False, failure=f"unreachable: {exc}; the arm did not move",
                                       duration=0.0)
            widths: list[float] = []
            stops: list[ContactStop] = []
            gripper = 0.0   # simulated seconds of the gripper's steps
            # A shift presses the closed fingers ``robot.shift_press`` into the object's top on purpose:
            # that much extra squeeze is the intended press, not a collision.
            self._arm.begin_plan(self.config.robot.shift_press if planned.primitive == "shift" else 0.0)
            self._world.lifted = self._world.held & self._arm.in_gripper()   # carried in (to the place): lost = dropped
            try:
                i = -1
                while i + 1 < len(steps):
                    i += 1
                    step = steps[i]
                    if isinstance(step, MoveL):
                        blends_on = step.blend > 0.0 and i + 1 < len(steps) and isinstance(steps[i + 1], MoveL)
                        watching = watch if watch is not None and i == moves[-1] else None
                        if self._arm.run_line(lines[i], step.stop_on_contact, settle=not blends_on, watch=watching):
                            short = float(np.linalg.norm(self._tcp()[:3, 3] - np.asarray(step.pose.position)))
                            stops.append(ContactStop(step.label, short))
                            if step.abort_on_contact:   # the rest of the plan: back up and home
                                steps = steps[:i + 1] + abort_steps(steps, i)
                            # a guarded move met resistance: the rest of the plan starts where it stopped
                            lines.update(self._arm.plan_lines(steps, first=i + 1))
                        if step.label == LIFT_LABEL:   # pinched pairs too (``held``), as a measurement counts them
                            self._world.lifted = self._arm.in_gripper() | self._arm.contacts.held()
                    elif isinstance(step, GripperCommand):
                        started = self._sim_time
                        self._arm.run_gripper(step.width, step.force, step.proceed_after)
                        gripper += self._sim_time - started
                    elif isinstance(step, MeasureWidth):
                        started = self._sim_time
                        self._arm.fingers_at_rest()
                        widths.append(self.gripper_width())
                        self._arm.note_held()
                        gripper += self._sim_time - started
            except CollisionStop as exc:
                self._arm.end_plan()
                self._arm.go_home()
                return ExecutionResult(completed=False, widths=widths,
                                       failure=f"collision stop: {exc}; the arm retreated home",
                                       duration=self._sim_time - t0, contact_stops=stops, gripper_time=gripper)
            except motion.Unreachable as exc:  # re-planning from where a guarded move stopped
                self._arm.end_plan()
                self._arm.go_home()
                return ExecutionResult(completed=False, widths=widths,
                                       failure=f"unreachable after a contact stop: {exc}; the arm retreated home",
                                       duration=self._sim_time - t0, contact_stops=stops, gripper_time=gripper)
            except _Unstable as exc:
                self._arm.end_plan()
                self.stats["unstable_resets"] += 1
                self.reset_scene()
                where = f"{planned.primitive} step {i} ({steps[i].label or type(steps[i]).__name__})"
                return ExecutionResult(completed=False, widths=widths,
                                       failure=f"unstable simulation ({exc}) during {where}; scene reset",
                                       duration=self._sim_time - t0, contact_stops=stops, gripper_time=gripper)
            self._arm.end_plan()
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
            self._arm.remove_outside()
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
            self._arm.go_home()

    def workspace_empty_hint(self) -> bool:
        """True when no object is left in the workspace."""
        with self._lock:
            self._check_open()
            self._arm.remove_outside()
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
        return self._arm.tcp()

    # -- the world, as execute uses it
    def _settle_until_still(self, limit: float) -> None:
        self._world.settle_until_still(limit)
