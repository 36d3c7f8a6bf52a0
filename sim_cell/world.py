"""The physics world of one simulated cell: the pybullet client, the table, the arm's body and the objects.

The world keeps the objects' bookkeeping (sim_cell.cell's module docstring, "Bookkeeping"): which objects
are in the scene and which the gripper is known to hold, the counts of what left it (``stats``), and the
simulated time.  Stepping runs the stability checks of sim_cell.stability every eighth physics step (a
deep check every 48th); settling lets the objects come to rest.  Scene making and plan execution act on
the world through these operations, so that an object is added, removed and counted in one place.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pybullet as p

from flgd.cell import CellFault
from flgd.config import CellConfig
from sim_cell import objects, scenes
from sim_cell.robot import SimRobot
from sim_cell.stability import FALLEN_DEPTH, SLEEP_MOTION, Stability, Unstable

SOLVER_ITERATIONS = 20      # enough for resting piles, pushes and free fingers
GRIP_SOLVER_ITERATIONS = 150  # while fingers squeeze an object; fewer let pads sink into it (sim_cell.cell)
TABLE_MARGIN = 0.15         # m of table beyond the workspace on each side
BIN_HALF_SIZE = 0.10        # m: the bin under robot.place, 20 cm square, open at the top


@dataclass(frozen=True)
class ObjectState:
    """One object as the simulator knows it (for oracles, tests and curricula, never for the policy)."""

    body: int
    label: str
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    points: np.ndarray   # corner points in the base frame
    top: float           # highest point, m in the base frame


class World:
    """One headless pybullet client with the table, the arm (``robot``) and the objects of a cell.

    ``home_joints``: where a cleared scene puts the arm, with the fingers at ``gripper.open_width``.
    """

    def __init__(self, config: CellConfig, home_joints: np.ndarray):
        self.dt = config.sim.time_step
        self.client: int | None = p.connect(p.DIRECT)
        if self.client < 0:
            raise CellFault("pybullet: cannot open a physics client")
        self.ws = config.workspace
        self.objects: dict[int, objects.SpawnedObject] = {}
        self.held: set[int] = set()           # objects measured as held: carried out when the gripper opens
        # objects in the gripper when this plan's grasp finished lifting: one of them lost from here was dropped
        self.lifted: set[int] = set()
        # dropped: of left_workspace, those lost after the gripper had lifted them (a grip that gave way)
        self.stats = {"grasped_out": 0, "left_workspace": 0, "dropped": 0, "unstable_resets": 0, "scenes": 0}
        self.sim_time = 0.0
        self._steps = 0
        self._iterations = SOLVER_ITERATIONS
        self._mass_scale = config.sim.object_mass_scale
        self._home_joints = home_joints
        self._open_width = config.gripper.open_width
        self._place = tuple(config.robot.place.position[:2])
        ws, c = self.ws, self.client
        p.resetSimulation(physicsClientId=c)
        p.setGravity(0, 0, -9.81, physicsClientId=c)
        p.setPhysicsEngineParameter(fixedTimeStep=self.dt, numSolverIterations=SOLVER_ITERATIONS, deterministicOverlappingPairs=1,
                                    physicsClientId=c)
        half = [(ws.x[1] - ws.x[0]) / 2 + TABLE_MARGIN, (ws.y[1] - ws.y[0]) / 2 + TABLE_MARGIN, 0.05]
        centre = scenes.workspace_origin(ws)
        self.table = p.createMultiBody(
            0, p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=c),
            p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=[0.45, 0.45, 0.45, 1], physicsClientId=c),
            [centre[0], centre[1], ws.z[0] - half[2]], physicsClientId=c)
        p.changeDynamics(self.table, -1, lateralFriction=0.6, physicsClientId=c)
        self.robot = SimRobot(c)
        self.stability = Stability(c, self.objects, self.robot.body, ws.z[0])

    def close(self) -> None:
        if self.client is not None:
            try:
                p.disconnect(physicsClientId=self.client)
            except p.error:
                pass
            self.client = None

    # -- stepping
    def step(self, n: int, before_step: Callable[[int], None] | None = None) -> None:
        """``n`` physics steps; a stability check every eighth (raises ``Unstable``)."""
        c = self.client
        for k in range(n):
            if before_step is not None:
                before_step(k)
            p.stepSimulation(physicsClientId=c)
            self.sim_time += self.dt
            self._steps += 1
            if self._steps % 8 == 0:
                self.check_stable(deep=(self._steps % 48 == 0))

    def check_stable(self, deep: bool) -> None:
        self.stability.check(deep, self.held, self.remove_lost)

    def settle(self, seconds: float) -> None:
        """Let the world run for ``seconds``; an unstable one is counted in ``stats`` (and raised)."""
        try:
            self.step(int(round(seconds / self.dt)))
        except Unstable:
            self.stats["unstable_resets"] += 1
            raise

    def settle_until_still(self, limit: float) -> None:
        """Step in 0.1 s chunks until no object moves, for at most ``limit`` s."""
        chunk = int(round(0.1 / self.dt))
        waited = 0.0
        while waited < limit and self.stability.moving():
            self.step(chunk)
            waited += 0.1

    def set_solver(self, squeeze: bool | None = None) -> None:
        """More solver iterations only while the fingers press on something (costly otherwise)."""
        if squeeze is None:
            squeeze = self.robot.finger_target_width() < self.robot.width() - 2e-3
        iterations = GRIP_SOLVER_ITERATIONS if squeeze else SOLVER_ITERATIONS
        if iterations != self._iterations:
            p.setPhysicsEngineParameter(numSolverIterations=iterations, physicsClientId=self.client)
            self._iterations = iterations

    # -- objects
    def add(self, spec: objects.ObjectSpec) -> int:
        """Spawn ``spec`` (pose in the base frame); returns its body id."""
        obj = objects.spawn(self.client, spec)
        scale = self._mass_scale
        if scale != 1.0:
            for link in range(-1, p.getNumJoints(obj.body, physicsClientId=self.client)):
                mass = p.getDynamicsInfo(obj.body, link, physicsClientId=self.client)[0]
                p.changeDynamics(obj.body, link, mass=mass * scale, physicsClientId=self.client)
        p.changeDynamics(obj.body, -1, activationState=p.ACTIVATION_STATE_ENABLE_SLEEPING,
                         sleepThreshold=SLEEP_MOTION, physicsClientId=self.client)
        self.objects[obj.body] = obj
        return obj.body

    def remove(self, body: int, reason: str) -> None:
        """Take ``body`` out and count it in ``stats[reason]``; what rested on it is woken."""
        self.stability.wake_near(body)
        p.removeBody(body, physicsClientId=self.client)
        self.objects.pop(body, None)
        self.stability.forget(body)
        self.held.discard(body)
        self.lifted.discard(body)
        self.stats[reason] += 1

    def remove_lost(self, body: int) -> None:
        """An object out of the cell other than in the gripper: it left the workspace, and was dropped when the
        gripper had lifted it in this plan or held it (a grip that gave way).  Carried out is counted where the
        gripper opens on it (the cell's release), or where one still held at the last width reading fell into
        the bin under the place (``over_bin``): the reading judged it picked, and it lies where picks go."""
        if body in self.held and self.over_bin(body):
            self.remove(body, "grasped_out")
            return
        if body in self.lifted or body in self.held:
            self.stats["dropped"] += 1
        self.remove(body, "left_workspace")

    def over_bin(self, body: int) -> bool:
        """Whether ``body``'s centre lies over the bin under ``robot.place``: within ``BIN_HALF_SIZE`` of it and
        outside the workspace (a place over the workspace has no bin)."""
        (x, y, _z), _ = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
        ws = self.ws
        return (abs(x - self._place[0]) <= BIN_HALF_SIZE and abs(y - self._place[1]) <= BIN_HALF_SIZE
                and not (ws.x[0] <= x <= ws.x[1] and ws.y[0] <= y <= ws.y[1]))

    def remove_outside(self, keep: set[int] | frozenset[int] = frozenset()) -> None:
        """Remove every object whose centre left the workspace or fell off the table, except ``keep`` (what
        the gripper carries: it leaves the cell when the gripper opens on it)."""
        ws = self.ws
        for body in list(self.objects):
            if body in keep:
                continue
            pos, _ = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
            inside = ws.x[0] <= pos[0] <= ws.x[1] and ws.y[0] <= pos[1] <= ws.y[1] and pos[2] > ws.z[0] - FALLEN_DEPTH
            if not inside:
                self.remove_lost(body)

    def clear(self) -> None:
        """No objects (uncounted), the arm home with open fingers, the normal solver."""
        for body in list(self.objects):
            p.removeBody(body, physicsClientId=self.client)
        self.objects.clear()
        self.stability.reset()
        self.held.clear()
        self.lifted.clear()
        if self.client is not None:
            self.set_solver(squeeze=False)   # a scene reset mid-squeeze must not drop the next pile at 150
            self.robot.teleport(self._home_joints, self._open_width)

    def object_states(self) -> list[ObjectState]:
        """Ground truth of every object in the scene, in the base frame."""
        out = []
        for obj in self.objects.values():
            pos, orn = p.getBasePositionAndOrientation(obj.body, physicsClientId=self.client)
            pts = obj.world_points(self.client)
            out.append(ObjectState(body=obj.body, label=obj.spec.label, position=tuple(pos),
                                   orientation=tuple(orn), points=pts, top=float(pts[:, 2].max())))
        return out
