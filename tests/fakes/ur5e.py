"""A fake UR5e controller behind fakes of ur_rtde's classes (RTDEControl, RTDEReceive, RTDEIO, the dashboard):
the arm's state, its replies and its refusals as ur_rtde reports them, on a fake clock."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from pathlib import Path

import numpy as np

from flgd.cell import CellFault
from flgd.config import CellConfig, load_config
from flgd.plans import plan_grasp, plan_push
from flgd.safety import CheckedPlan, check_plan
from flgd.hardware.rg2 import RG2XmlRpcDriver
from flgd.hardware.ur5e_cell import UR5eCell
from flgd.hardware.ur_arm import PROTECTIVE_STOP_UNLOCK_DELAY
from tests.fakes.d415 import FakeD415Factory
from tests.fakes.rg2 import LoopbackRG2

ROOT = Path(__file__).resolve().parents[2]

# --------------------------------------------------------------------------- the fake controller

_REAL_FORCE = object()  # FakeURController.force_reply: answer from the force model

class FakeURController:
    """One simulated UR controller shared by the fake interfaces; time advances only through ``sleep``.

    ``rate`` is the controller's seconds per wall-clock second: 1 for a real controller, below 1 for an emulator
    that falls behind real time, 0 for a controller whose state stream has frozen.
    """

    def __init__(self, tcp=(0.40, 0.0, 0.30), speed_scale: float = 1.0):
        self.now = 1000.0
        self.rate = 1.0
        self.controller_now = 50.0   # RTDE ``timestamp``: seconds since the controller booted
        self.log: list[tuple] = []
        self.tcp = np.array([*tcp, math.pi, 0.0, 0.0])
        self.safety_mode = 1
        self.robot_mode = 7
        self.estop = False
        self.protective = False
        self.protective_at: float | None = None
        self.popup = False
        self.program_running = True
        self.interfaces: list = []        # every fake interface opened, each with its own link
        self.network_up = True
        self.installation_tcp = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]   # the pendant's: what a fresh script starts with
        self.tcp_offset = list(self.installation_tcp)
        self.tool_out = {0: False, 1: False}
        self.fail_next: dict[str, int] = {}
        self.unreachable = lambda pose: math.dist(pose[:3], (0, 0, 0)) > 0.85  # UR5e reach
        self.hooks: list = []              # (move index, fraction of the way, action)
        self.moves = 0
        self.moving = threading.Event()
        self._target = None
        self._speed = 0.0
        self._start = None
        self.real_sleep = 0.0
        # TCP force model: a rigid top surface at ``surface_z`` (None = free space) pushes back with
        # ``surface_stiffness`` N/m; ``force_offset`` is the sensor's bias; ``force_reply`` replaces the answer
        self.surface_z: float | None = None
        self.surface_stiffness = 20000.0
        self.force_offset = np.array([3.0, -2.0, 9.0])
        self.force_reply = _REAL_FORCE
        self.stop_positions: list[np.ndarray] = []  # TCP position at each stopL

    # -- recording / scripted failures
    def record(self, iface: str, method: str, *args) -> None:
        self.log.append((self.now, iface, method, args))

    def failing(self, method: str) -> bool:
        if self.fail_next.get(method, 0) > 0:
            self.fail_next[method] -= 1
            return True
        return False

    def names(self, since: int = 0) -> list[str]:
        return [m for _, _, m, _ in self.log[since:]]

    def calls(self, method: str, since: int = 0) -> list[tuple]:
        return [a for _, _, m, a in self.log[since:] if m == method]

    # -- events a test can trigger
    def protective_stop(self) -> None:
        self.protective, self.protective_at, self.safety_mode = True, self.now, 3
        self.popup, self.program_running = True, False
        self._halt()

    def emergency_stop(self) -> None:
        self.estop, self.safety_mode, self.program_running = True, 7, False
        self.popup = True
        self._halt()

    def release_emergency_stop(self) -> None:
        """Releasing the button leaves the arm powered off, as on a real UR."""
        self.estop, self.safety_mode, self.robot_mode = False, 1, 3

    def power_on(self) -> None:
        self.robot_mode = 7

    def lose_network(self) -> None:
        self.network_up = False
        for iface in self.interfaces:
            iface.connected = False
        self.program_running = False  # the script exits when its RTDE client is gone
        self._halt()

    def kill_script(self) -> None:
        self.program_running = False
        self._halt()

    def at(self, move_index: int, fraction: float, action) -> None:
        self.hooks.append((move_index, fraction, action))

    # -- time and motion
    def sleep(self, dt: float) -> None:
        if self.real_sleep:
            time.sleep(self.real_sleep)
        self.now += dt
        self.controller_now += dt * self.rate
        target = self._target  # another thread may stopL meanwhile
        if target is None:
            return
        pos, goal = self.tcp[:3], target[:3]
        total = np.linalg.norm(goal - self._start[:3])
        step = self._speed * dt * self.rate
        left = goal - pos
        if np.linalg.norm(left) <= step:
            self.tcp = target.copy()
            self._target = None
            self.moving.clear()
        else:
            self.tcp[:3] = pos + left / np.linalg.norm(left) * step
        done = 1.0 if total == 0 else 1.0 - np.linalg.norm(goal - self.tcp[:3]) / total
        for hook in list(self.hooks):
            if hook[0] == self.moves and done >= hook[1]:
                self.hooks.remove(hook)
                hook[2]()

    def _halt(self) -> None:
        self._target = None
        self.moving.clear()

    def clock(self) -> float:
        return self.now

    def start_move(self, pose, speed) -> None:
        self.moves += 1
        self._start = self.tcp.copy()
        self._target = np.asarray(pose, float)
        self._speed = speed
        self.moving.set()

    def ready_for_motion(self, iface) -> bool:
        return iface.connected and self.program_running and self.safety_mode in (1, 2) and not self.estop


class _FakeAsyncStatus:
    def __init__(self, running: bool):
        self._running = running

    def isAsyncOperationRunning(self) -> bool:
        return self._running


class _FakeInterface:
    name = "?"

    def __init__(self, ctl: FakeURController, host: str):
        self.ctl, self.host = ctl, host
        self.connected = ctl.network_up
        ctl.interfaces.append(self)

    def _rec(self, method: str, *args) -> None:
        self.ctl.record(self.name, method, *args)

    def isConnected(self) -> bool:
        self._rec("isConnected")
        return self.connected

    def disconnect(self) -> None:
        self._rec("disconnect")
        self.connected = False

    def reconnect(self) -> bool:
        self._rec("reconnect")
        if not self.ctl.network_up:
            return False
        self.connected = True
        return True


class FakeRTDEControl(_FakeInterface):
    """ur_rtde's RTDEControlInterface: False when the script is not running or the link is down."""

    name = "control"

    def __init__(self, ctl, host):
        super().__init__(ctl, host)
        self._rec("RTDEControlInterface", host)
        if not ctl.network_up:
            raise RuntimeError("One of the RTDE input registers are already in use!")  # any construction error
        if ctl.estop or ctl.safety_mode not in (1, 2):
            raise RuntimeError("ur_rtde: Failed to start control script, before timeout of 5 seconds")
        ctl.program_running = True

    def reconnect(self) -> bool:
        ok = super().reconnect()
        if ok and self.ctl.safety_mode in (1, 2):
            self.ctl.program_running = True  # reconnect uploads the control script again
        return ok

    def setTcp(self, tcp) -> bool:
        self._rec("setTcp", list(tcp))
        if self.ctl.failing("setTcp") or not self.ctl.ready_for_motion(self):
            return False
        self.ctl.tcp_offset = list(tcp)
        return True

    def isPoseWithinSafetyLimits(self, pose) -> bool:
        self._rec("isPoseWithinSafetyLimits", list(pose))
        if not self.connected or self.ctl.failing("isPoseWithinSafetyLimits"):
            return False
        return not self.ctl.unreachable(pose)

    def moveL(self, pose, speed=0.25, acceleration=1.2, asynchronous=False) -> bool:
        """A single moveL, or ur_rtde's ``moveL(path, asynchronous)``: rows of [pose, speed, acceleration, blend]
        (the fake runs a path straight to its last pose at its first speed, with the script's TCP)."""
        if pose and isinstance(pose[0], (list, tuple)):
            path, asynchronous = [list(row) for row in pose], bool(speed)
            self._rec("moveL", path, asynchronous)
            self.ctl.program_running = False            # ur_rtde re-uploads its script with the path in it
            self.ctl.tcp_offset = list(self.ctl.installation_tcp)
            self.ctl.program_running = True
            if self.ctl.failing("moveL") or not self.ctl.ready_for_motion(self):
                return False
            self.ctl.start_move(path[-1][:6], path[0][6])
            return True
        self._rec("moveL", list(pose), speed, acceleration, asynchronous)
        if self.ctl.failing("moveL") or not self.ctl.ready_for_motion(self):
            return False
        self.ctl.start_move(pose, speed)
        return True

    def getTCPOffset(self) -> list[float]:
        self._rec("getTCPOffset")
        return list(self.ctl.tcp_offset)

    def stopL(self, a=10.0, asynchronous=False) -> None:
        self._rec("stopL", a)
        self.ctl.stop_positions.append(self.ctl.tcp[:3].copy())
        self.ctl._halt()

    def getAsyncOperationProgressEx(self) -> _FakeAsyncStatus:
        self._rec("getAsyncOperationProgressEx")
        return _FakeAsyncStatus(self.ctl._target is not None)

    def isProgramRunning(self) -> bool:
        self._rec("isProgramRunning")
        return self.connected and self.ctl.program_running

    def reuploadScript(self) -> bool:
        self._rec("reuploadScript")
        if self.ctl.failing("reuploadScript") or not self.connected or \
                self.ctl.safety_mode not in (1, 2):
            return False
        self.ctl.program_running = True
        return True

    def stopScript(self) -> None:
        self._rec("stopScript")
        self.ctl.program_running = False


class FakeRTDEReceive(_FakeInterface):
    """ur_rtde's RTDEReceiveInterface: after a lost link it keeps answering with stale data, like the real one."""

    name = "receive"

    def __init__(self, ctl, host):
        super().__init__(ctl, host)
        self._rec("RTDEReceiveInterface", host)
        if not ctl.network_up:
            raise RuntimeError("Timeout connecting to UR controller")
        self._stale = None

    def _fresh(self):
        if self.connected:
            self._stale = (self.ctl.safety_mode, self.ctl.robot_mode, self.ctl.protective, self.ctl.estop,
                           self.ctl.tcp.copy(), self.ctl.controller_now)
        return self._stale

    def getSafetyMode(self) -> int:
        self._rec("getSafetyMode")
        return self._fresh()[0]

    def getRobotMode(self) -> int:
        self._rec("getRobotMode")
        return self._fresh()[1]

    def isProtectiveStopped(self) -> bool:
        self._rec("isProtectiveStopped")
        return self._fresh()[2]

    def isEmergencyStopped(self) -> bool:
        self._rec("isEmergencyStopped")
        return self._fresh()[3]

    def getActualTCPPose(self) -> list[float]:
        self._rec("getActualTCPPose")
        return self._fresh()[4].tolist()

    def getTimestamp(self) -> float:
        self._rec("getTimestamp")
        if self.ctl.failing("getTimestamp"):
            raise RuntimeError("RTDE receive: read failed")
        return self._fresh()[5]

    def getActualTCPForce(self) -> list[float]:
        self._rec("getActualTCPForce")
        ctl = self.ctl
        if ctl.force_reply is not _REAL_FORCE:
            return ctl.force_reply
        tcp = self._fresh()[4]
        force = ctl.force_offset.copy()
        if ctl.surface_z is not None and tcp[2] < ctl.surface_z:
            force[2] += ctl.surface_stiffness * (ctl.surface_z - tcp[2])
        return [*force.tolist(), 0.0, 0.0, 0.0]


class FakeRTDEIO(_FakeInterface):
    name = "io"

    def __init__(self, ctl, host):
        super().__init__(ctl, host)
        self._rec("RTDEIOInterface", host)

    def setToolDigitalOut(self, output_id: int, level: bool) -> bool:
        self._rec("setToolDigitalOut", output_id, level)
        if self.ctl.failing("setToolDigitalOut") or not self.connected:
            return False
        self.ctl.tool_out[output_id] = level
        return True


class FakeDashboard:
    """ur_rtde's DashboardClient: unlockProtectiveStop raises unless the controller replies 'releasing'."""

    name = "dashboard"

    def __init__(self, ctl, host):
        self.ctl, self.connected = ctl, False
        ctl.record("dashboard", "DashboardClient", host)

    def connect(self, timeout_ms=2000) -> None:
        self.ctl.record("dashboard", "connect", timeout_ms)
        if not self.ctl.network_up:
            raise RuntimeError("Timeout connecting to UR dashboard server.")
        self.connected = True

    def isConnected(self) -> bool:
        self.ctl.record("dashboard", "isConnected")
        return self.connected and self.ctl.network_up

    def disconnect(self) -> None:
        self.ctl.record("dashboard", "disconnect")
        self.connected = False

    def unlockProtectiveStop(self) -> None:
        self.ctl.record("dashboard", "unlockProtectiveStop")
        c = self.ctl
        if c.protective_at is not None and c.now - c.protective_at < PROTECTIVE_STOP_UNLOCK_DELAY:
            raise RuntimeError("Unlock protective stop failure: Cannot unlock protective stop until 5s after "
                               "occurrence. Always inspect cause of protective stop before unlocking")
        if c.estop:
            raise RuntimeError("Unlock protective stop failure: Protective stop cannot be released")
        c.protective, c.protective_at = False, None
        if c.safety_mode == 3:
            c.safety_mode = 1

    def closeSafetyPopup(self) -> None:
        self.ctl.record("dashboard", "closeSafetyPopup")
        self.ctl.popup = False

    def safetymode(self) -> str:
        self.ctl.record("dashboard", "safetymode")
        return {1: "Safetymode: NORMAL", 3: "Safetymode: PROTECTIVE_STOP"}.get(self.ctl.safety_mode, "Safetymode: ?")


class FakeRTDEFactory:
    def __init__(self, ctl: FakeURController):
        self.ctl = ctl

    def control(self, host):
        return FakeRTDEControl(self.ctl, host)

    def receive(self, host):
        return FakeRTDEReceive(self.ctl, host)

    def io(self, host):
        return FakeRTDEIO(self.ctl, host)

    def dashboard(self, host):
        return FakeDashboard(self.ctl, host)


# --------------------------------------------------------------------------- helpers

def real_config(**gripper) -> CellConfig:
    """The real-cell example config, on loopback, with its policy read from this checkout (the example
    names the installed copy under /opt/flgd).  Every move single and slow near the grasp over the whole approach
    height (no blend, no contact zone): these tests count the moves a plan sends; blended paths and the contact
    zone have their own tests, which set them."""
    cfg = load_config(ROOT / "cell_config" / "ur5e-d415.yaml")
    return dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, host="127.0.0.1", blend_radius=0.0,
                                                              contact_clearance=0.0, raise_speed=0.0),
                               gripper=dataclasses.replace(cfg.gripper, **gripper),
                               policy=str(ROOT / "policies" / Path(cfg.policy).name))


class NoCamera:
    """The camera is tested in test_hardware_d415; these tests are about the arm."""

    def capture(self):
        raise CellFault("no camera in this test")

    def close(self) -> None:
        pass


def make_ur5e(ctl: FakeURController, rg2: LoopbackRG2, cfg: CellConfig | None = None, **kw) -> UR5eCell:
    cfg = cfg or real_config(xmlrpc_port=rg2.port)
    gripper = kw.pop("gripper", None) or RG2XmlRpcDriver("127.0.0.1", rg2.port, timeout=2.0, poll_interval=0.002)
    return UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), gripper=gripper, camera_factory=lambda c: NoCamera(),
                    clock=ctl.clock, sleep=ctl.sleep, **kw)


def grasp(cfg: CellConfig) -> CheckedPlan:
    return check_plan(plan_grasp(0.50, 0.05, 0.04, 0.3, cfg), cfg)


def push(cfg: CellConfig) -> CheckedPlan:
    return check_plan(plan_push(0.45, -0.05, 1.2, cfg), cfg)


MOTION = {"moveL", "stopL", "setToolDigitalOut", "reuploadScript", "unlockProtectiveStop"}
def make_cell(ctl: FakeURController, rg2, cfg: CellConfig, cameras: FakeD415Factory) -> UR5eCell:
    # sleep looks ctl.sleep up at each call, so a test can wrap it after the cell exists
    return UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), camera_factory=cameras,
                    gripper=RG2XmlRpcDriver("127.0.0.1", rg2.port, timeout=2.0, poll_interval=0.002),
                    clock=ctl.clock, sleep=lambda dt: ctl.sleep(dt))
