"""The emulated UR5e controller against ur_rtde 1.6.5's own clients and flgd's URArm.

The emulator (sim_cell/emulator: arm, RTDE, dashboard and script ports on a
SimCell) listens on its own loopback host (tests/loopback.py) so that a developer's emulator on 127.0.0.1 is
left alone; ur_rtde's RTDEControlInterface, RTDEReceiveInterface,
RTDEIOInterface and DashboardClient connect to it unmodified.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from flgd.cell import CellFault
from flgd.config import load_config
from flgd.plans import MoveL, plan_grasp
from flgd.safety import check_plan
from flgd.hardware.ur_arm import URArm, pose_error

pytest.importorskip("rtde_control")
import dashboard_client  # noqa: E402
import rtde_control  # noqa: E402
import rtde_io  # noqa: E402
import rtde_receive  # noqa: E402

from sim_cell.emulator.arm import RobotMode, SafetyMode  # noqa: E402
from sim_cell.emulator.control_script import Command  # noqa: E402
from sim_cell.emulator.tcp_service import PortTaken  # noqa: E402
from sim_cell.emulator.ur_controller import EmulatedURController  # noqa: E402
from sim_cell.emulator.world import EmulatorWorld  # noqa: E402
from tests.loopback import worker_host  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HOST = worker_host(2)


def sim_config():
    """The sim cell with an empty table: these tests are about the arm, not about grasping."""
    cfg = load_config(ROOT / "cell_config" / "sim.yaml")
    return dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=0, scene=""),
                               robot=dataclasses.replace(cfg.robot, host=HOST))


class _Harness:
    """The emulator inside its own process, with the few actions the tests need beyond the controller's."""

    def __init__(self) -> None:
        self.world = EmulatorWorld(sim_config(), time_scale=2.0)
        self.ctl = EmulatedURController(self.world, HOST, max_frequency=125)
        self.ctl.start()

    def stop_during_move(self, fraction: float) -> None:
        """A protective stop once a move has covered ``fraction`` of its line."""
        arm, fired = self.ctl.arm, []

        def tick(dt: float) -> None:
            if not fired and arm.moving and arm.line.progress > fraction:
                fired.append(True)
                arm.protective_stop("injected")

        self.world.add_tick(tick)

    def watch_speed_near(self, point: list[float], radius: float) -> None:
        """Record the commanded TCP speed on every tick the TCP is within ``radius`` of ``point``."""
        arm, target = self.ctl.arm, np.asarray(point[:3])
        self.speeds_near: list[float] = []

        def tick(dt: float) -> None:
            if arm.line is not None and not arm.line.arrived:
                if np.linalg.norm(arm.line.pose()[:3, 3] - target) < radius:
                    self.speeds_near.append(float(arm.line.v))

        self.world.add_tick(tick)

    def age_protective_stop(self, seconds: float) -> None:
        self.ctl.arm.protective_stop_at -= seconds

    def start_another(self) -> str:
        try:
            EmulatedURController(self.world, HOST).start()
        except PortTaken as exc:
            return str(exc)
        return "started"

    def close(self) -> None:
        self.ctl.close()
        self.world.close()


def _run_emulator(conn) -> None:
    """Child process: serve the harness's attributes and methods over ``conn`` until "close"."""
    parent = os.getppid()
    harness = _Harness()
    conn.send("ready")
    while True:
        if not conn.poll(0.5):
            if os.getppid() != parent:   # the test process died: never outlive it holding the ports
                harness.close()
                return
            continue
        path, args = conn.recv()
        obj = harness
        try:
            for part in path.split("."):
                obj = getattr(obj, part)
            conn.send(("ok", obj(*args) if callable(obj) else obj))
        except Exception as exc:  # handed to the test, which fails with it
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
        if path == "close":
            return


class Emulator:
    """The test's handle on an emulator process (ur_rtde's C++ calls hold the GIL: a server in the
    test's own process could never answer them)."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("fork")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_run_emulator, args=(child,), daemon=True)
        self._process.start()
        if not self._conn.poll(30.0):
            raise RuntimeError("the emulator process did not start")
        assert self._conn.recv() == "ready"

    def __call__(self, path: str, *args):
        self._conn.send((path, args))
        if not self._conn.poll(30.0):
            raise RuntimeError(f"the emulator did not answer {path}")
        status, value = self._conn.recv()
        if status != "ok":
            raise AssertionError(f"emulator {path}: {value}")
        return value

    def close(self) -> None:
        if self._process.is_alive():
            try:
                self("close")
            except (RuntimeError, OSError, EOFError):
                pass
            self._process.join(5.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(5.0)


@pytest.fixture
def emulator():
    """A fresh emulated controller on 127.0.0.2 in its own process (125 Hz RTDE, physics at twice real time)."""
    emu = Emulator()
    yield emu
    emu.close()


@pytest.fixture
def clients(emulator):
    """ur_rtde's control and receive interfaces on the emulator, disconnected after the test."""
    control = rtde_control.RTDEControlInterface(HOST)
    receive = rtde_receive.RTDEReceiveInterface(HOST)
    yield control, receive
    for iface in (control, receive):
        try:
            iface.disconnect()
        except RuntimeError:
            pass


def wait_until(condition, timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def wait_for_move(control) -> None:
    assert wait_until(lambda: not control.getAsyncOperationProgressEx().isAsyncOperationRunning(), 10.0)


# --------------------------------------------------------------------------- RTDE receive and dashboard

def test_receive_reports_the_simulated_tcp_pose_and_the_modes(emulator):
    receive = rtde_receive.RTDEReceiveInterface(HOST)
    try:
        assert receive.isConnected()
        pose = receive.getActualTCPPose()
        assert max(pose_error(pose, emulator("ctl.arm.tcp_pose"))) < 1e-3   # a rotation vector near pi may flip
        np.testing.assert_allclose(pose[:3], sim_config().robot.home.position, atol=1e-3)
        assert receive.getRobotMode() == RobotMode.RUNNING
        assert receive.getSafetyMode() == SafetyMode.NORMAL
        assert not receive.isProtectiveStopped() and not receive.isEmergencyStopped()
        emulator("ctl.arm.protective_stop", "test")
        assert wait_until(receive.isProtectiveStopped)
        assert receive.getSafetyMode() == SafetyMode.PROTECTIVE_STOP
    finally:
        receive.disconnect()


def test_dashboard_commands_act_on_the_arm(emulator):
    db = dashboard_client.DashboardClient(HOST)
    db.connect(2000)
    try:
        assert db.isConnected()
        assert db.polyscopeVersion().startswith("5.11")
        assert "RUNNING" in db.robotmode()
        db.powerOff()
        assert emulator("ctl.arm.robot_mode") == RobotMode.POWER_OFF
        db.powerOn()
        assert emulator("ctl.arm.robot_mode") == RobotMode.IDLE
        db.brakeRelease()
        assert emulator("ctl.arm.robot_mode") == RobotMode.RUNNING
        emulator("ctl.arm.protective_stop", "test")
        assert "PROTECTIVE_STOP" in db.safetystatus()
        with pytest.raises(RuntimeError, match="Cannot unlock protective stop until 5s"):
            db.unlockProtectiveStop()   # within 5 s of the stop: the controller refuses
        assert emulator("ctl.arm.safety_mode") == SafetyMode.PROTECTIVE_STOP
        emulator("age_protective_stop", 5.0)
        db.unlockProtectiveStop()
        db.closeSafetyPopup()
        assert emulator("ctl.arm.safety_mode") == SafetyMode.NORMAL and "NORMAL" in db.safetystatus()
        db.play()
        assert emulator("ctl.arm.program_running")
        db.stop()
        assert not emulator("ctl.arm.program_running")
    finally:
        db.disconnect()


def test_a_taken_port_is_named_in_the_error(emulator):
    assert f"{HOST}:29999" in emulator("start_another")


# --------------------------------------------------------------------------- RTDE control: moves

def test_the_control_script_runs_after_connect_and_stops_on_stopScript(emulator, clients):
    control, receive = clients
    assert control.isConnected() and control.isProgramRunning()
    assert emulator("ctl.scripts.programs") == ["rtde_control"]
    control.stopScript()
    assert not control.isProgramRunning()
    assert control.reuploadScript()
    assert wait_until(control.isProgramRunning)


def test_a_moveL_moves_the_simulated_tcp_to_the_target_within_1_mm(emulator, clients):
    control, receive = clients
    assert control.setTcp(emulator("ctl.arm.installation_tcp"))
    start = receive.getActualTCPPose()
    target = list(start)
    target[0] += 0.08
    target[2] -= 0.05
    assert control.isPoseWithinSafetyLimits(target)
    assert control.moveL(target, 0.25, 1.2, True)
    assert wait_until(lambda: control.getAsyncOperationProgressEx().isAsyncOperationRunning(), 1.0)
    wait_for_move(control)
    dp, dr = pose_error(receive.getActualTCPPose(), target)
    assert dp < 0.001 and dr < 0.002
    assert pose_error(emulator("ctl.arm.tcp_pose"), target)[0] < 0.001


def test_an_unreachable_pose_is_refused_before_anything_moves(emulator, clients):
    control, receive = clients
    assert not control.isPoseWithinSafetyLimits([1.5, 0.0, 0.3, 3.14159, 0.0, 0.0])
    assert control.isPoseWithinSafetyLimits(receive.getActualTCPPose())


def start_a_long_move(control, receive) -> tuple[list[float], list[float]]:
    """A slow 25 cm moveL, 0.3 s under way; (start, target)."""
    start = receive.getActualTCPPose()
    target = list(start)
    target[1] -= 0.25
    assert control.moveL(target, 0.1, 0.5, True)
    time.sleep(0.3)
    return start, target


def test_stopL_ends_a_move_short_of_its_target(emulator, clients):
    control, receive = clients
    start, target = start_a_long_move(control, receive)
    control.stopL(2.0)
    wait_for_move(control)
    stopped = receive.getActualTCPPose()
    assert 0.005 < pose_error(stopped, start)[0] < 0.2
    time.sleep(0.2)
    assert pose_error(receive.getActualTCPPose(), stopped)[0] < 0.001, "the arm stands still after stopL"


def test_a_protective_stop_during_a_move_stops_it_and_is_reported(emulator, clients):
    control, receive = clients
    start, target = start_a_long_move(control, receive)
    emulator("ctl.arm.protective_stop", "test")
    assert wait_until(receive.isProtectiveStopped)
    assert wait_until(lambda: not control.isProgramRunning())
    here = receive.getActualTCPPose()
    time.sleep(0.3)
    assert pose_error(receive.getActualTCPPose(), here)[0] < 0.001, "the move ended at the stop"
    assert pose_error(here, target)[0] > 0.05
    assert control.moveL(start, 0.1, 0.5, True) is False, "a stopped controller refuses a move"


def test_tool_digital_output_through_RTDEIOInterface(emulator):
    io = rtde_io.RTDEIOInterface(HOST)
    try:
        assert io.setToolDigitalOut(1, True)
        assert wait_until(lambda: emulator("ctl.arm.tool_digital_outputs") == 0b10)
        assert io.setToolDigitalOut(1, False)
        assert wait_until(lambda: emulator("ctl.arm.tool_digital_outputs") == 0)
    finally:
        io.disconnect()


# --------------------------------------------------------------------------- flgd's URArm

@pytest.fixture
def ur_arm(emulator):
    cfg = sim_config()
    arm = URArm(HOST, cfg.robot.tcp_offset, use_io=True)
    arm.connect()
    yield arm
    arm.close()


@pytest.mark.slow
def test_urarm_connects_and_executes_a_checked_plans_moves(emulator, ur_arm):
    cfg = sim_config()
    assert ur_arm.fault is None and ur_arm.fault_reason() is None
    ws = cfg.workspace
    x, y = (ws.x[0] + ws.x[1]) / 2, (ws.y[0] + ws.y[1]) / 2
    checked = check_plan(plan_grasp(x, y, ws.z[0] + 0.02, 0.3, cfg), cfg)
    moves = [s for s in checked.plan.steps if isinstance(s, MoveL)]
    assert len(moves) >= 3
    for step in moves:
        assert ur_arm.move_linear(step.pose.as_ur_pose(), step.speed, step.acceleration, step.label) is False
        assert pose_error(emulator("ctl.arm.tcp_pose"), step.pose.as_ur_pose())[0] < 0.002
    ur_arm.set_tool_output(0, True)
    assert wait_until(lambda: emulator("ctl.arm.tool_digital_outputs") & 1)


def _corner_path(ur_arm) -> tuple[list[list[float]], list[float]]:
    """Two 8 cm lines with a right-angle corner, from where the arm stands; (poses, blends)."""
    here = ur_arm.tcp_pose()
    corner = list(here)
    corner[2] += 0.08
    end = list(corner)
    end[1] -= 0.08
    return [corner, end], [0.02, 0.0]


def test_urarm_runs_a_blended_path_through_its_corner_without_stopping(emulator, ur_arm):
    """ur_rtde's moveL(path) re-uploads its script with the moves in it; the emulator reads them and runs one
    motion that keeps moving at the corner, and the arm's TCP is set again afterwards."""
    poses, blends = _corner_path(ur_arm)
    emulator("watch_speed_near", poses[0], 0.012)   # the corner passes 7 mm inside its pose
    programs = emulator("ctl.scripts.programs").count("rtde_control")
    ur_arm.move_path(poses, [0.2, 0.2], [1.0, 1.0], blends, "corner")
    assert pose_error(emulator("ctl.arm.tcp_pose"), poses[-1])[0] < 0.002
    assert Command.MOVE_PATH in emulator("ctl.script.commands")
    assert emulator("ctl.scripts.programs").count("rtde_control") == programs + 1
    near = emulator("speeds_near")
    assert near and min(near) > 0.05, "the tool passed the corner without stopping"
    assert emulator("ctl.arm.tcp") == list(sim_config().robot.tcp_offset) + [0.0, 0.0, 0.0]
    # a single move after the path goes where it is sent (the arm's TCP again)
    back = ur_arm.tcp_pose()
    back[1] += 0.04
    assert ur_arm.move_linear(back, 0.2, 1.0, "after") is False
    assert pose_error(emulator("ctl.arm.tcp_pose"), back)[0] < 0.002


def test_a_protective_stop_during_a_blended_path_latches_and_nothing_moves_after_it(emulator, ur_arm):
    poses, blends = _corner_path(ur_arm)
    emulator("stop_during_move", 0.4)
    with pytest.raises(CellFault, match="protective stop|control script is not running"):
        ur_arm.move_path(poses, [0.1, 0.1], [0.5, 0.5], blends, "corner")
    assert ur_arm.fault
    here = emulator("ctl.arm.tcp_pose")
    assert pose_error(here, poses[-1])[0] > 0.03, "stopped short of the path's end"
    with pytest.raises(CellFault):
        ur_arm.move_path(poses, [0.1, 0.1], [0.5, 0.5], blends, "again")
    with pytest.raises(CellFault):
        ur_arm.move_linear(poses[-1], 0.1, 0.5, "again")
    time.sleep(0.2)
    assert pose_error(emulator("ctl.arm.tcp_pose"), here)[0] < 0.001, "nothing moved after the latch"


@pytest.mark.slow
def test_urarm_recovers_from_a_protective_stop_during_a_move_in_the_documented_order(emulator, ur_arm):
    here = ur_arm.tcp_pose()
    target = list(here)
    target[1] -= 0.25
    emulator("stop_during_move", 0.3)
    # the stop and the program's end reach the receive and the control connection in either order
    with pytest.raises(CellFault, match="protective stop|control script is not running"):
        ur_arm.move_linear(target, 0.1, 0.5, "probe")
    assert ur_arm.fault and not emulator("ctl.arm.program_running")
    t0 = time.monotonic()
    ur_arm.recover()
    assert time.monotonic() - t0 > 4.0, "the unlock waited for the controller's 5 s"
    assert ur_arm.fault is None and emulator("ctl.arm.safety_mode") == SafetyMode.NORMAL
    assert emulator("ctl.arm.program_running") and emulator("ctl.scripts.programs").count("rtde_control") == 2
    assert ur_arm.move_linear(here, 0.25, 1.2, "back") is False


@pytest.mark.slow
def test_an_emergency_stop_refuses_recovery_until_released_and_powered(emulator, ur_arm):
    emulator("ctl.arm.emergency_stop")
    assert wait_until(lambda: ur_arm.fault_reason() == "emergency stop engaged")
    with pytest.raises(CellFault, match="emergency stop engaged"):
        ur_arm.recover()
    emulator("ctl.arm.release_emergency_stop")
    assert wait_until(lambda: not ur_arm.receive.isEmergencyStopped())
    with pytest.raises(CellFault, match="robot mode POWER_OFF"):
        ur_arm.recover()
    emulator("ctl.arm.power_on")
    emulator("ctl.arm.brake_release")
    assert wait_until(lambda: ur_arm.receive.getRobotMode() == RobotMode.RUNNING)
    ur_arm.recover()
    assert ur_arm.fault is None and emulator("ctl.arm.program_running")


@pytest.mark.slow
def test_a_stopped_program_is_reported_and_the_script_reuploaded(emulator, ur_arm):
    emulator("ctl.arm.stop_program")
    assert wait_until(lambda: ur_arm.fault_reason() is not None)
    assert "control script is not running" in ur_arm.fault_reason()
    ur_arm.recover()
    assert ur_arm.fault is None and emulator("ctl.arm.program_running")


def test_a_dropped_link_is_reported_and_the_receive_interface_reconnects(emulator):
    """The receive interface on its own; URArm's recovery after a drop (fresh interfaces in a fresh ur_rtde
    process) is exercised through the daemon in tests/test_emulator_cell.py."""
    receive = rtde_receive.RTDEReceiveInterface(HOST)
    try:
        assert receive.isConnected()
        emulator("ctl.drop_connections")
        assert wait_until(lambda: not receive.isConnected())
        assert receive.reconnect()
        assert max(pose_error(receive.getActualTCPPose(), emulator("ctl.arm.tcp_pose"))) < 1e-3
    finally:
        receive.disconnect()


def test_the_emulator_refuses_connections_once_closed(emulator):
    emulator("close")
    with pytest.raises(OSError):
        socket.create_connection((HOST, 29999), timeout=1.0)


def test_ur_rtde_dying_in_its_process_is_a_named_fault_and_the_next_interfaces_start_a_new_one(emulator):
    """What a segmentation fault inside ur_rtde does to the daemon: nothing but a fault naming the signal."""
    import signal

    from flgd.hardware.rtde_process import IsolatedRTDEFactory, RTDEProcessLost

    factory = IsolatedRTDEFactory()
    try:
        receive = factory.receive(HOST)
        assert receive.isConnected() and receive.process_alive
        first = factory._child.process
        os.kill(first.pid, signal.SIGSEGV)
        with pytest.raises(RTDEProcessLost, match="SIGSEGV"):
            receive.getActualTCPPose()
        assert not receive.process_alive
        again = factory.receive(HOST)  # what URArm's recovery does: fresh interfaces, in a fresh process
        assert factory._child.process.pid != first.pid
        assert max(pose_error(again.getActualTCPPose(), emulator("ctl.arm.tcp_pose"))) < 1e-3
    finally:
        factory.close()


def _in_a_subprocess(body: str, timeout: float = 120.0) -> dict:
    """Run ``body`` (it sets ``result``, a JSON-able dict) in a fresh interpreter of its own session.

    Why: these guarantees are about calls that would otherwise never return; run here, a broken guarantee is a
    failed test at ``timeout`` (the whole session killed, the stopped ur_rtde process too), never a hung suite.
    """
    import json
    import signal
    import subprocess
    import sys
    import textwrap

    code = ("import json, os, signal, time\nfrom flgd.hardware import rtde_process\n"
            f"HOST = {HOST!r}\n" + textwrap.dedent(body) + "\nprint(json.dumps(result))\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[1], start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"did not return within {timeout:g} s (the guarantee is broken: a call hangs):\n{err[-2000:]}")
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def test_ur_rtde_hanging_in_its_process_is_stopped_at_the_call_deadline(emulator):
    """ur_rtde looping in its own thread (seen after a dropped link) holds its process, never the daemon."""
    result = _in_a_subprocess("""
        rtde_process.CALL_TIMEOUT = 1.0
        factory = rtde_process.IsolatedRTDEFactory()
        try:
            receive = factory.receive(HOST)
            child = factory._child.process
            os.kill(child.pid, signal.SIGSTOP)  # it answers nothing from now on
            try:
                receive.isConnected()
                error = None
            except rtde_process.RTDEProcessLost as exc:
                error = str(exc)
            result = {"error": error, "child_alive": child.is_alive()}
        finally:
            factory.close()
    """)
    assert result["error"] is not None and "receive.isConnected did not return within 1 s" in result["error"]
    assert not result["child_alive"]  # killed, not left behind


def test_a_signal_handlers_call_during_a_call_on_the_same_thread_is_refused_not_deadlocked(emulator):
    """SIGTERM during a move runs URArm.stop_motion on the thread that waits for ur_rtde's reply; its stopL must
    not wait for the pipe that thread holds (the move's loop sees the stop request and halts on its own)."""
    result = _in_a_subprocess("""
        rtde_process.CALL_TIMEOUT = 2.0
        factory = rtde_process.IsolatedRTDEFactory()
        seen = []

        def handler(signum, frame):
            try:
                receive.getActualTCPPose()
            except BaseException as exc:
                seen.append(type(exc).__name__)

        signal.signal(signal.SIGALRM, handler)
        try:
            receive = factory.receive(HOST)
            os.kill(factory._child.process.pid, signal.SIGSTOP)  # the next call waits its full deadline
            signal.setitimer(signal.ITIMER_REAL, 0.3)
            try:
                receive.isConnected()
                outer = None
            except rtde_process.RTDEProcessLost as exc:
                outer = type(exc).__name__
            result = {"outer": outer, "seen": seen}
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            factory.close()
    """)
    assert result["outer"] == "RTDEProcessLost"
    assert result["seen"] == ["RTDECallInProgress"], result