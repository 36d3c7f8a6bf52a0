"""The production backend against ``flgd emulate``: the daemon's full cycle through ur_rtde, the RG2's XML-RPC and
pyrealsense2 on the emulated cell, and the faults raised on demand reaching it as a real cell's would."""

from __future__ import annotations

import math
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from flgd.config import load_config
from sim_cell.emulator.emulated_cell import EmulatedCell, EmulatorConfigError
from sim_cell.emulator.faults import FaultError, FaultInjector, FaultSocket, inject
from tests.fakes.daemon import REPO, DaemonProcess
from tests.loopback import worker_host

EMULATED = REPO / "cell_config" / "ur5e-emulated.yaml"
HOST = worker_host(3)


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def emulated_config(tmp_path: Path, **sim) -> Path:
    """cell_config/ur5e-emulated.yaml on HOST with free ports, its state in ``tmp_path``, paths made absolute."""
    data = yaml.safe_load(EMULATED.read_text())
    shipped = load_config(EMULATED)
    data["state_dir"] = str(tmp_path / "state")
    data["policy"] = str(shipped.policy)
    data["learning"]["init_trunk"] = str(shipped.learning.init_trunk)
    data["finetune"]["prior_sample"] = str(shipped.finetune.prior_sample)
    data["robot"]["host"] = HOST
    data["gripper"]["xmlrpc_port"] = _free_port(HOST)
    data["camera"]["emulator"] = f"{HOST}:{_free_port(HOST)}"
    data["sim"].update({"objects": 10, **sim})  # enough that the table never empties during a test
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture
def emulator(tmp_path):
    cell = EmulatedCell(load_config(emulated_config(tmp_path)), time_scale=2.0, fault_socket=tmp_path / "f.sock")
    cell.start()
    yield cell
    cell.close()


def _actions(state_dir: Path) -> list[tuple]:
    with sqlite3.connect(state_dir / "flgd.sqlite") as db:
        return db.execute("SELECT step, outcome, primitive, success, failure FROM actions ORDER BY step").fetchall()


@pytest.mark.slow
def test_the_daemon_cycles_through_ur_rtde_and_a_protective_stop_or_a_dropped_link_mid_move_is_latched_then_recovered(
        tmp_path, emulator):
    config = tmp_path / "cell.yaml"
    d = DaemonProcess(tmp_path, config=config, args=["--autostart"]).start()
    try:
        d.wait_ready()
        d.wait_for(lambda st: st["cycles"] >= 1, "a cycle on the emulated cell")
        emulator.faults.arm_for_motion("protective-stop")
        st = d.wait_for(lambda st: st["state"] == "FAULT", "the protective stop latched")
        assert "protective" in st["cause"].lower(), st["cause"]
        moves_at_fault = len(emulator.arm.faults)
        before = st["cycles"]
        d.ok("reset")  # the arm's recovery: wait out the 5 s, unlock on the dashboard, reupload the script
        d.ok("start")
        d.wait_for(lambda st: (st["state"] == "RUNNING" and st["cycles"] >= before + 2)
                   or len(emulator.arm.faults) > moves_at_fault, "two cycles after recovery")
        # no second stop: the recovery left the arm clean
        assert emulator.arm.faults[moves_at_fault:] == [], (emulator.arm.faults, d.log()[-3000:])

        # a dropped RTDE link (ur_rtde loops or crashes on it: flgd/hardware/rtde_process.py): latched in a live
        # daemon, and a reset opens fresh connections without a restart of the service
        emulator.faults.arm_for_motion("drop-rtde")
        st = d.wait_for(lambda st: st["state"] == "FAULT", "the dropped link latched")
        before = st["cycles"]
        d.ok("reset")
        d.ok("start")
        d.wait_for(lambda st: st["state"] == "RUNNING" and st["cycles"] >= before + 2, "two cycles after the reset")
        assert "opening fresh connections" in d.log()
    finally:
        d.ok("stop")
        d.wait_exit()
    rows = _actions(tmp_path / "state")
    assert [r[0] for r in rows] == list(range(len(rows)))  # every cycle recorded, none lost to the fault
    assert any(r[1] == "executed" and r[3] == 1 for r in rows), rows  # real picks through the real protocols
    assert [f["during_motion"] for f in emulator.faults.raised] == [True, True]


def test_a_fault_armed_for_motion_lands_while_the_arm_moves(emulator):
    arm = emulator.arm
    arm.start_program()
    delay = emulator.faults.arm_for_motion("protective-stop")
    assert 0.0 <= delay <= 0.5
    pose = arm.tcp_pose()
    target = list(pose)
    target[2] -= 0.08
    arm.move_linear(target, 0.04, 0.5)  # 2 s of motion, 1 s of wall time at time_scale 2: the stop lands in it
    deadline = time.monotonic() + 10
    while not emulator.faults.raised and time.monotonic() < deadline:
        time.sleep(0.01)
    assert emulator.faults.raised and emulator.faults.raised[0]["during_motion"] is True
    assert not arm.moving and arm.safety_mode == 3  # PROTECTIVE_STOP: the move ended there


def test_the_fault_socket_raises_reports_and_refuses_by_name(emulator, tmp_path):
    sock = tmp_path / "f.sock"
    assert inject(sock, "gripper-trip")["ok"] and emulator.gripper.busy is False
    assert inject(sock, "camera-stop")["ok"]
    status = inject(sock, "status")
    assert [r["kind"] for r in status["raised"]] == ["gripper-trip", "camera-stop"]
    reply = inject(sock, "melt-down")
    assert reply["ok"] is False and "unknown fault 'melt-down'" in reply["error"]
    reply = inject(sock, "camera-resume --during-motion")
    assert reply["ok"] is False and "cannot wait for a motion" in reply["error"]


def test_a_second_emulator_on_the_same_fault_socket_is_refused(emulator, tmp_path):
    with pytest.raises(OSError, match="another flgd emulate"):
        FaultSocket(FaultInjector(), tmp_path / "f.sock").start()


def test_a_fault_for_a_device_the_emulator_lacks_is_an_error():
    with pytest.raises(FaultError, match="no RG2"):
        FaultInjector().raise_now("gripper-trip")


def test_a_config_the_emulator_cannot_play_names_the_key(tmp_path):
    cfg = load_config(emulated_config(tmp_path))
    import dataclasses

    with pytest.raises(EmulatorConfigError, match="camera.emulator is empty"):
        EmulatedCell(dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, emulator="")))
    with pytest.raises(EmulatorConfigError, match="backend is 'sim'"):
        EmulatedCell(dataclasses.replace(cfg, backend="sim"))


@pytest.mark.slow
def test_a_swap_to_the_sim_backend_and_back_mid_run(tmp_path, emulator):
    d = DaemonProcess(tmp_path, config=tmp_path / "cell.yaml", args=["--autostart"]).start()
    try:
        d.wait_ready()
        d.wait_for(lambda st: st["cycles"] >= 1, "a cycle on the emulated cell")
        assert d.ok("backend", name="sim")["previous"] == "ur5e"
        d.ok("start")
        on_sim = d.wait_for(lambda st: st["state"] == "RUNNING", "running on sim")["cycles"]
        d.wait_for(lambda st: st["cycles"] >= on_sim + 2, "two cycles on sim")
        assert d.ok("backend", name="ur5e")["previous"] == "sim"
        d.ok("start")
        back = d.wait_for(lambda st: st["state"] == "RUNNING", "running on the emulated cell")["cycles"]
        d.wait_for(lambda st: st["cycles"] >= back + 1, "a cycle back on the emulated cell")
    finally:
        d.ok("stop")
        d.wait_exit()
    with sqlite3.connect(tmp_path / "state" / "flgd.sqlite") as db:
        backends = [b for (b,) in db.execute("SELECT backend FROM actions ORDER BY step")]
    assert backends[0] == "ur5e" and "sim" in backends and backends[-1] == "ur5e", backends


@pytest.mark.slow
def test_flgd_calibrate_on_the_emulated_cell_finds_the_camera_where_it_truly_is(tmp_path):
    """A camera 1.2 cm and 1° away from its configured pose; ``flgd calibrate`` through ur_rtde and pyrealsense2
    sees the marker on the emulated gripper and writes the true pose into the config."""
    from flgd.geometry import rpy_to_matrix
    from sim_cell.camera import CameraModel

    error = {"position": [0.009, -0.006, 0.005], "rpy": [0.012, -0.01, 0.008]}
    path = emulated_config(tmp_path, objects=0, camera_pose_error=error)  # calibration wants an empty table
    before = load_config(path)
    truth = CameraModel.from_config(before.camera, before.sim.camera_pose_error).pose
    offset = (-0.08, 0.0, -0.02)
    cell = EmulatedCell(before, time_scale=3.0, marker="aruco", marker_offset=offset)
    cell.start()
    try:
        # its own process, as on a cell: ur_rtde's calls hold this interpreter's lock while they wait for replies
        run = subprocess.run([sys.executable, "-m", "flgd.cli", "calibrate", "--config", str(path), "--marker",
                              "aruco", "--marker-offset", *map(str, offset), "--margin", "0.1", "--settle", "0.3"],
                             capture_output=True, text=True, timeout=300, cwd=REPO)
    finally:
        cell.close()
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    assert "wrote camera.pose" in run.stdout
    after = load_config(path)
    position = np.asarray(after.camera.pose.position)
    turn = rpy_to_matrix(*after.camera.pose.rpy).T @ truth[:3, :3]
    angle = math.degrees(math.acos(min(1.0, (np.trace(turn) - 1.0) / 2.0)))
    assert np.linalg.norm(position - truth[:3, 3]) < 0.003, (position, truth[:3, 3])
    assert angle < 0.3
    assert np.linalg.norm(np.asarray(before.camera.pose.position) - truth[:3, 3]) > 0.01  # it had something to find
    assert after.sim.camera_pose_error == before.sim.camera_pose_error  # only the camera's pose lines changed

