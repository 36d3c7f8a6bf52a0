"""The UR5e cell against a fake at the ur_rtde class boundary.

``FakeURController`` models one UR controller in simulated time: linear
motion at the commanded speed, protective and emergency stops, lost
connections, a control script that dies, and False returns.  The four fake
interfaces (``FakeRTDEControl``, ``FakeRTDEReceive``, ``FakeRTDEIO``,
``FakeDashboard``) have the method names, arguments and failure behaviour of
ur_rtde 1.6's classes, and record every call, so the tests can check what
reached the "robot" and in which order.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from flgd.cell import CellFault, make_cell
from flgd.config import CellConfig, load_config
from flgd.geometry import ToolPose
from flgd.clutter import grasp_reward
from flgd.plans import GripperCommand, MeasureWidth, MoveL, Plan, plan_grasp, plan_home, plan_push
from flgd.safety import CheckedPlan, PlanRefused, check_plan
from flgd.hardware.rg2 import RG2XmlRpcDriver
from flgd.hardware.ur5e_cell import UR5eCell
from flgd.hardware.ur_arm import PROTECTIVE_STOP_UNLOCK_DELAY
from tests.test_hardware_rg2 import LoopbackRG2

ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- the fake controller

_REAL_FORCE = object()  # FakeURController.force_reply: answer from the force model

class FakeURController:
    """One simulated UR controller shared by the fake interfaces; time advances only through ``sleep``."""

    def __init__(self, tcp=(0.40, 0.0, 0.30), speed_scale: float = 1.0):
        self.now = 1000.0
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
        self.tcp_offset = None
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
        target = self._target  # another thread may stopL meanwhile
        if target is None:
            return
        pos, goal = self.tcp[:3], target[:3]
        total = np.linalg.norm(goal - self._start[:3])
        step = self._speed * dt
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
        self._rec("moveL", list(pose), speed, acceleration, asynchronous)
        if self.ctl.failing("moveL") or not self.ctl.ready_for_motion(self):
            return False
        self.ctl.start_move(pose, speed)
        return True

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
                           self.ctl.tcp.copy())
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


# --------------------------------------------------------------------------- fixtures

def real_config(**gripper) -> CellConfig:
    """The real-cell example config, on loopback, with its policy read from this checkout (the example
    names the installed copy under /opt/flgd)."""
    cfg = load_config(ROOT / "cell_config" / "ur5e-d415.yaml")
    return dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, host="127.0.0.1"),
                               gripper=dataclasses.replace(cfg.gripper, **gripper),
                               policy=str(ROOT / "policies" / Path(cfg.policy).name))


class _NoCamera:
    """The camera is tested in test_hardware_d415; these tests are about the arm."""

    def capture(self):
        raise CellFault("no camera in this test")

    def close(self) -> None:
        pass


@pytest.fixture
def rg2():
    server = LoopbackRG2(move_time=0.01)
    yield server
    server.close()


@pytest.fixture
def ctl():
    return FakeURController()


def make_ur5e(ctl: FakeURController, rg2: LoopbackRG2, cfg: CellConfig | None = None, **kw) -> UR5eCell:
    cfg = cfg or real_config(xmlrpc_port=rg2.port)
    gripper = kw.pop("gripper", None) or RG2XmlRpcDriver("127.0.0.1", rg2.port, timeout=2.0, poll_interval=0.002)
    return UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), gripper=gripper, camera_factory=lambda c: _NoCamera(),
                    clock=ctl.clock, sleep=ctl.sleep, **kw)


def grasp(cfg: CellConfig) -> CheckedPlan:
    return check_plan(plan_grasp(0.50, 0.05, 0.04, 0.3, cfg), cfg)


def push(cfg: CellConfig) -> CheckedPlan:
    return check_plan(plan_push(0.45, -0.05, 1.2, cfg), cfg)


MOTION = {"moveL", "stopL", "setToolDigitalOut", "reuploadScript", "unlockProtectiveStop"}


# --------------------------------------------------------------------------- tests

def test_grasp_plan_runs_as_checked_async_moves_and_measures_the_width(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    rg2.object_width_mm = 31.0
    checked = grasp(cfg)
    result = cell.execute(checked)
    assert result.completed, result.failure
    assert result.widths == [pytest.approx(0.031)]
    assert ctl.tcp_offset == [0.0, 0.0, 0.225, 0.0, 0.0, 0.0], "the TCP is the fingertip centre"
    moves = [s for s in checked.plan.steps if isinstance(s, MoveL)]
    sent = ctl.calls("moveL")
    assert len(sent) == len(moves)
    names = ctl.names()
    for step, (pose, speed, acc, asynchronous) in zip(moves, sent):
        np.testing.assert_allclose(pose, step.pose.as_ur_pose(), atol=1e-12)
        assert (speed, acc, asynchronous) == (step.speed, step.acceleration, True)
    # The controller's own limits are consulted before every single move, for that very pose.
    i_moves = [i for i, n in enumerate(names) if n == "moveL"]
    for i in i_moves:
        j = max(k for k in range(i) if names[k] == "isPoseWithinSafetyLimits")
        assert "moveL" not in names[j + 1:i]
        np.testing.assert_allclose(ctl.log[j][3][0], ctl.log[i][3][0])
    grips = [c for c in rg2.calls if c[0] == "rg_grip"]
    assert [g[2] for g in grips] == [pytest.approx(85.0), pytest.approx(0.0)]
    np.testing.assert_allclose(ctl.tcp[:3], cfg.robot.home.position, atol=1e-9)


def test_the_width_is_read_once_the_fingers_stop_so_a_block_slipping_out_at_home_is_a_failure(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    rg2.object_width_mm = 31.0
    rg2.slip_mm = [31.0, 22.0, 9.0, 0.0]  # the block slides out as the arm arrives home
    t0 = ctl.clock()
    result = cell.execute(grasp(cell.config))
    assert result.completed, result.failure
    assert result.widths == [0.0]
    assert grasp_reward(result.widths[0], cell.config.gripper) == 0.0
    # a steady width is read twice and that is all: one settle interval
    rg2.slip_mm = []
    rg2.object_width_mm = 31.0
    reads = rg2.names().count("rg_get_width")
    result = cell.execute(grasp(cell.config))
    assert result.widths == [pytest.approx(0.031)]
    assert rg2.names().count("rg_get_width") - reads == 2
    assert ctl.clock() > t0


def test_a_plan_outside_the_envelope_never_reaches_the_robot(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    n = len(ctl.log)
    outside = ToolPose.top_down(0.50, 0.0, cfg.workspace.table_z - 0.05, 0.0)   # below the table
    too_fast = ToolPose.top_down(0.50, 0.0, 0.20, 0.0)
    for plan in (Plan("push", (MoveL(outside, 0.1, 0.5),)),
                 Plan("push", (MoveL(too_fast, cfg.safety.max_speed * 3, 0.5),)),
                 Plan("grasp", (GripperCommand(0.085, 400.0), MeasureWidth()))):
        with pytest.raises(PlanRefused):
            check_plan(plan, cfg)
        with pytest.raises(PlanRefused):   # a hand-made "checked" plan is re-verified by the cell
            cell.execute(CheckedPlan(plan, id(cfg)))
    assert ctl.log[n:] == [], "nothing at all was sent for a refused plan"
    assert not any(c[0] == "rg_grip" for c in rg2.calls)


def test_a_pose_the_controller_refuses_is_not_sent_and_is_not_a_fault(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    checked = push(cell.config)
    bad = checked.plan.poses[1].as_ur_pose()  # the descent
    ctl.unreachable = lambda pose: np.allclose(pose, bad)
    result = cell.execute(checked)
    assert not result.completed and "step 2 (descend)" in result.failure and "safety limits" in result.failure
    assert len(ctl.calls("moveL")) == 1, "only the approach went out; nothing after the refused pose"
    assert not any(np.allclose(p[0], bad) for p in ctl.calls("moveL"))
    ctl.unreachable = lambda pose: False
    assert cell.execute(push(cell.config)).completed


def test_a_false_return_latches_a_fault_that_stops_all_motion(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.fail_next["moveL"] = 1
    with pytest.raises(CellFault, match=r"moveL .* returned False"):
        cell.execute(grasp(cell.config))
    n = len(ctl.log)
    grips = len(rg2.calls)
    for plan in (grasp(cell.config), push(cell.config), check_plan(plan_home(cell.config), cell.config)):
        with pytest.raises(CellFault, match="in FAULT .*recovery"):
            cell.execute(plan)
    assert not MOTION & set(ctl.names(n)), "no motion command after a fault"
    assert len(rg2.calls) == grips, "nor a gripper command"


def test_protective_stop_mid_move_then_recovery_in_documented_order(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.at(2, 0.5, ctl.protective_stop)         # halfway through the descent
    with pytest.raises(CellFault, match="protective stop during move 'descend'"):
        cell.execute(grasp(cell.config))
    stopped_at = ctl.protective_at
    n = len(ctl.log)
    with pytest.raises(CellFault):
        cell.execute(push(cell.config))
    assert not MOTION & set(ctl.names(n))

    n = len(ctl.log)
    cell.recover()
    seq = [m for m in ctl.names(n) if m in {"isEmergencyStopped", "unlockProtectiveStop", "closeSafetyPopup",
                                             "getSafetyMode", "reuploadScript", "setTcp", "moveL", "rg_grip"}]
    first = {m: seq.index(m) for m in ("isEmergencyStopped", "unlockProtectiveStop", "closeSafetyPopup",
                                       "reuploadScript", "setTcp", "moveL")}
    assert first["isEmergencyStopped"] < first["unlockProtectiveStop"] < first["closeSafetyPopup"] \
        < first["reuploadScript"] < first["setTcp"] < first["moveL"]
    # NORMAL safety mode is confirmed after closing the popup and before the script comes back.
    assert "getSafetyMode" in seq[first["closeSafetyPopup"]:first["reuploadScript"]]
    unlock_time = next(t for t, _, m, _ in ctl.log[n:] if m == "unlockProtectiveStop")
    assert unlock_time - stopped_at >= PROTECTIVE_STOP_UNLOCK_DELAY
    assert len(ctl.calls("unlockProtectiveStop")) == 1, "unlocked once, after waiting, not retried early"
    assert not ctl.popup and ctl.program_running
    home = ctl.calls("moveL", n)
    assert len(home) == 1
    np.testing.assert_allclose(home[0][0][:3], cell.config.robot.home.position)
    assert cell.execute(grasp(cell.config)).completed


def test_emergency_stop_refuses_recovery_until_released_and_powered(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.at(1, 0.3, ctl.emergency_stop)
    with pytest.raises(CellFault, match="emergency stop engaged during move 'approach'"):
        cell.execute(push(cell.config))
    n = len(ctl.log)
    with pytest.raises(CellFault, match="emergency stop engaged.*recovery refused"):
        cell.recover()
    assert not MOTION & set(ctl.names(n)) and "closeSafetyPopup" not in ctl.names(n)
    ctl.release_emergency_stop()
    with pytest.raises(CellFault, match="robot mode POWER_OFF"):
        cell.recover()
    assert "moveL" not in ctl.names(n)
    ctl.power_on()
    cell.recover()
    assert cell.execute(push(cell.config)).completed


def test_lost_connection_is_a_fault_and_recovery_reconnects(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.at(3, 0.4, ctl.lose_network)
    with pytest.raises(CellFault, match="lost the RTDE receive connection during move 'push'"):
        cell.execute(push(cell.config))
    n = len(ctl.log)
    with pytest.raises(CellFault, match="cannot reconnect the RTDE receive interface"):
        cell.recover()
    assert not MOTION & set(ctl.names(n))
    ctl.network_up = True
    n = len(ctl.log)
    cell.recover()
    names = ctl.names(n)
    assert names.count("reconnect") >= 2, "receive and control were reconnected"
    assert names.index("reconnect") < names.index("moveL")
    assert cell.execute(push(cell.config)).completed


def test_a_dead_control_script_is_a_fault_and_is_reuploaded(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.at(1, 1.0, ctl.kill_script)  # the script dies right as the first move ends
    with pytest.raises(CellFault, match="control script is not running"):
        cell.execute(grasp(cell.config))
    n = len(ctl.log)
    ctl.fail_next["reuploadScript"] = 1
    with pytest.raises(CellFault, match="reuploadScript returned False"):
        cell.recover()
    assert "moveL" not in ctl.names(n)
    cell.recover()
    assert ctl.program_running and cell.execute(grasp(cell.config)).completed


def test_stop_motion_from_another_thread_halts_the_move_promptly(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.real_sleep = 0.0005                      # let the other thread run while the fake arm moves
    ctl.tcp[:3] = (0.40, 0.30, 0.30)             # far from the grasp so the first move takes a while
    result = {}
    worker = threading.Thread(target=lambda: result.setdefault("r", cell.execute(grasp(cell.config))))
    worker.start()
    assert ctl.moving.wait(10), "the arm started moving"
    cell.stop_motion()                           # what the daemon's SIGTERM handler calls
    worker.join(10)
    assert not worker.is_alive()
    r = result["r"]
    assert not r.completed and "stopped on request" in r.failure
    names = ctl.names()
    assert "stopL" in names and names.count("moveL") == 1, "stopL sent; no move after it"
    assert names.index("stopL") > names.index("moveL")
    # The stop is latched: the next plan sends nothing until the owner clears it on purpose.
    n = len(ctl.log)
    again = cell.execute(push(cell.config))
    assert not again.completed and "stopped on request" in again.failure
    assert "moveL" not in ctl.names(n) and cell.fault is None, "a stop is not a fault, and nothing moved"
    cell.clear_stop()
    assert cell.execute(push(cell.config)).completed, "after a deliberate clear the next plan runs"


def test_starting_while_protective_stopped_reports_and_recovers(ctl, rg2):
    ctl.protective_stop()
    cell = make_ur5e(ctl, rg2)
    assert "protective stop" in cell.fault
    assert "RTDEControlInterface" not in ctl.names(), "the control script is not uploaded into a stopped arm"
    with pytest.raises(CellFault, match="protective stop"):
        cell.execute(push(cell.config))
    cell.recover()
    names = ctl.names()
    assert names.index("unlockProtectiveStop") < names.index("RTDEControlInterface") < names.index("moveL")
    assert cell.fault is None


def test_gripper_failure_latches_the_fault_too(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    rg2.fault = "tool not connected"
    with pytest.raises(CellFault, match="step 0 \\(open\\).*tool not connected"):
        cell.execute(grasp(cell.config))
    rg2.fault = None
    n = len(ctl.log)
    with pytest.raises(CellFault, match="in FAULT"):
        cell.execute(push(cell.config))
    assert "moveL" not in ctl.names(n)


def test_tool_digital_output_gripper(ctl, rg2):
    cfg = real_config(driver="tool_digital_output", digital_output=1)
    with pytest.raises(CellFault, match="cannot measure the finger width"):
        UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), camera_factory=lambda c: _NoCamera(),
                 clock=ctl.clock, sleep=ctl.sleep)
    cell = UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), camera_factory=lambda c: _NoCamera(),
                    clock=ctl.clock, sleep=ctl.sleep, require_width=False)
    assert cell.execute(push(cfg)).completed
    assert ctl.calls("setToolDigitalOut") == [(1, True)]
    ctl.fail_next["setToolDigitalOut"] = 1
    with pytest.raises(CellFault, match=r"setToolDigitalOut\(1, True\) returned False"):
        cell.execute(push(cfg))
    with pytest.raises(CellFault):
        cell.gripper_width()


def test_registered_as_the_ur5e_backend_and_refuses_an_empty_host():
    cfg = load_config(ROOT / "cell_config" / "ur5e-d415.yaml")
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, host=""))
    with pytest.raises(CellFault, match="robot.host is empty"):
        make_cell(cfg)


def _descend_step(checked: CheckedPlan) -> MoveL:
    return next(s for s in checked.plan.steps if isinstance(s, MoveL) and s.label == "descend")


def test_guarded_descent_stops_at_contact_and_the_grasp_goes_on_from_there(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    assert cfg.robot.descent_contact_force > 0, "the shipped real-cell config guards grasp descents"
    checked = grasp(cfg)
    descend = _descend_step(checked)
    assert descend.stop_on_contact == cfg.robot.descent_contact_force
    # a neighbour's top 2 cm above the planned fingertip height: the descent must stop on it
    surface = descend.pose.position[2] + 0.02
    ctl.surface_z = surface
    since = len(ctl.log)
    result = cell.execute(checked)
    assert result.completed, result.failure
    names = ctl.names(since)
    moves = [i for i, n in enumerate(names) if n == "moveL"]
    stops = [i for i, n in enumerate(names) if n == "stopL"]
    assert len(stops) == 1 and moves[1] < stops[0] < moves[2], "one stopL, during the descent"
    # stopped just past first contact (within the force threshold's squeeze + one poll of travel)
    (at_stop,) = ctl.stop_positions
    assert surface - 0.003 < at_stop[2] <= surface
    np.testing.assert_allclose(at_stop[:2], descend.pose.position[:2], atol=1e-9)
    # reported: which move stopped, and how far short of its pose (the arm's own TCP reading)
    (stop,) = result.contact_stops
    assert stop.label == "descend"
    assert stop.short_by == pytest.approx(at_stop[2] - descend.pose.position[2], abs=1e-6)
    # the fingers closed there and the plan went on: lift to its absolute pose, home
    grips = [c for c in rg2.calls if c[0] == "rg_grip"]
    assert [g[2] for g in grips] == [pytest.approx(85.0), pytest.approx(0.0)]
    lift = ctl.calls("moveL", since)[2][0]
    step_lift = next(s for s in checked.plan.steps if isinstance(s, MoveL) and s.label == "lift")
    np.testing.assert_allclose(lift, step_lift.pose.as_ur_pose())
    np.testing.assert_allclose(ctl.tcp[:3], cfg.robot.home.position, atol=1e-9)


def test_guard_measures_the_change_of_force_not_the_sensor_bias(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    ctl.force_offset = np.array([0.0, -5.0, 3.0 * cfg.robot.descent_contact_force])  # a big, constant bias
    checked = grasp(cfg)
    surface = _descend_step(checked).pose.position[2] + 0.01
    ctl.surface_z = surface
    result = cell.execute(checked)
    assert result.completed, result.failure
    (at_stop,) = ctl.stop_positions  # no stop from the bias alone, one at the contact
    assert surface - 0.003 < at_stop[2] <= surface


def test_free_descent_reaches_the_planned_depth(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    checked = grasp(cell.config)
    reached = []
    ctl.at(2, 1.0, lambda: reached.append(ctl.tcp[2]))
    result = cell.execute(checked)
    assert result.completed, result.failure
    assert ctl.calls("stopL") == [] and result.contact_stops == []
    assert reached == [pytest.approx(_descend_step(checked).pose.position[2])]


@pytest.mark.parametrize("reply", [None, [float("nan")] * 6, [1.0, 2.0], "garbage"])
def test_an_unusable_force_reading_stops_the_arm_and_latches(ctl, rg2, reply):
    cell = make_ur5e(ctl, rg2)
    checked = grasp(cell.config)
    ctl.at(2, 0.3, lambda: setattr(ctl, "force_reply", reply))  # mid-descent
    with pytest.raises(CellFault, match="TCP force"):
        cell.execute(checked)
    assert cell.fault is not None
    assert ctl.calls("stopL"), "the descent was halted before the fault was raised"
    assert ctl._target is None
    since = len(ctl.log)
    with pytest.raises(CellFault):
        cell.execute(checked)
    assert "moveL" not in ctl.names(since), "no motion until recovery"


def test_reset_reopens_a_camera_whose_stream_died(ctl, rg2):
    """flgctl reset clears a camera fault: the cell's recovery closes the camera and opens it anew.

    The camera is librealsense's own software_device (tests.test_hardware_d415), driven through the real
    D415Camera; its depth sensor stopping is a stream that died under the camera.
    """
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 cannot load here (libusb-1.0 missing?)")
    from flgd.hardware.d415 import CameraFault, D415Camera
    from tests.test_hardware_d415 import SERIAL, registered_camera, synthetic_frame, sim_config

    frame = synthetic_frame(sim_config(), width=64, height=48)
    dev = registered_camera(frame)
    cfg = real_config(xmlrpc_port=rg2.port)
    cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, serial=SERIAL, frame_timeout=1.0))
    opened = []

    def open_camera(c):
        opened.append(D415Camera.from_device(c, dev.device, warmup_frames=2))
        return opened[-1]

    gripper = RG2XmlRpcDriver("127.0.0.1", rg2.port, timeout=2.0, poll_interval=0.002)
    with dev.streaming(frame.depth, frame.color):
        cell = UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), gripper=gripper, camera_factory=open_camera,
                        clock=ctl.clock, sleep=ctl.sleep)
        assert cell.capture().depth.shape == (48, 64)
        dev.depth_sensor.stop()  # the stream dies; only a new start brings it back
        with pytest.raises(CameraFault, match=r"^RealSense .*: no depth\+colour frame within 1\.0 s"):
            cell.capture()
    # still gone when the operator resets: a clear error, and the arm is not touched
    n = len(ctl.log)
    with pytest.raises(CellFault, match=r"recovery: the camera did not come back: .*no depth\+colour frame.*"
                                        r"USB cable.*then flgctl reset again"):
        cell.recover()
    assert "moveL" not in ctl.names(n)
    with pytest.raises(CellFault, match="camera is not open"):
        cell.capture()
    # back: the next reset reopens it (the failed attempt left the device free) and homes the arm
    with dev.streaming(frame.depth, frame.color):
        cell.recover()
        assert cell.capture().depth.shape == (48, 64)
    assert len(opened) == 2, "the first camera, and the one reopened by the successful reset"
    assert len(ctl.calls("moveL", n)) == 1
    cell.close()
