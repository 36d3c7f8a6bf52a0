"""The emulated RG2 (sim_cell/emulator/rg2_service.py) driven by flgd's own RG2XmlRpcDriver over XML-RPC.

The service runs on an EmulatorWorld whose clock moves the simulated fingers; nothing in between is a fake.
"""

from __future__ import annotations

import dataclasses
import time
import xmlrpc.client

import numpy as np
import pytest

from flgd.config import load_config
from flgd.geometry import ToolPose, pose_matrix
from flgd.hardware.gripper import GripperFault
from flgd.hardware.rg2 import RG2XmlRpcDriver
from sim_cell import kinematics, motion
from sim_cell.emulator.rg2_service import RG2Service
from sim_cell.emulator.world import EmulatorWorld
from sim_cell.objects import ObjectSpec
from sim_cell.robot import READY_JOINTS
from tests.fakes.realsense import SIM_CONFIG
from tests.loopback import worker_host

HOST = worker_host(2)
BLOCK = 0.040   # m, the edge of the cube put between the fingers
GRIP_XY = (-0.50, 0.0)


@pytest.fixture(scope="module")
def world():
    cfg = load_config(SIM_CONFIG)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=0, scene=""))
    with EmulatorWorld(cfg) as w:
        w.start()
        yield w


@pytest.fixture
def rg2(world):
    with RG2Service(world, HOST, 0) as service:
        yield service


def driver(service: RG2Service) -> RG2XmlRpcDriver:
    return RG2XmlRpcDriver(HOST, service.port, timeout=3.0)


def _tcp_down_to(world, z: float) -> None:
    """Put the fingertips at (GRIP_XY, z), pointing down (the arm is not what this file tests)."""
    cell = world.cell
    off = np.asarray(cell.config.robot.tcp_offset)
    pose = ToolPose.top_down(*GRIP_XY, z, 0.0)
    q = kinematics.nearest_solution(kinematics.inverse(motion.tcp_to_flange(pose_matrix(pose.position, pose.matrix),
                                                                            off)), READY_JOINTS)
    with world.lock:
        robot = cell._robot
        robot.teleport(q)
        robot.command_arm(q)


def test_open_and_close_on_nothing_take_the_rg2s_time(world, rg2):
    d = driver(rg2)
    _tcp_down_to(world, 0.20)   # high above the table: nothing between the fingers
    d.move(0.100, 20.0)
    assert d.width() == pytest.approx(0.100, abs=0.002)
    started = time.monotonic()
    d.move(0.0, 20.0)
    took = time.monotonic() - started
    assert d.width() == pytest.approx(0.0, abs=0.002)
    # the RG2 takes about 1 s for 110 mm; the upper bound only allows for a busy machine's slower physics clock
    assert 0.6 < took < 5.0, f"100 mm closed in {took:.2f} s"
    assert {"rg_grip", "rg_get_busy", "rg_get_safety_failed", "rg_get_width"} <= set(rg2.calls)
    d.close()


def test_closing_on_a_block_stops_at_its_width(world, rg2):
    d = driver(rg2)
    _tcp_down_to(world, 0.20)
    d.move(0.085, 40.0)
    cube = world.cell.add_object(ObjectSpec(shape="cube", size=(BLOCK,), position=(*GRIP_XY, BLOCK / 2)))
    try:
        _tcp_down_to(world, BLOCK / 2)
        d.move(0.0, 40.0)
        assert d.width() == pytest.approx(BLOCK, abs=0.003)
        assert not rg2.busy
        d.move(0.085, 40.0)
        assert d.width() == pytest.approx(0.085, abs=0.002)
    finally:
        world.cell.remove_object(cube, settle=0.0)
        _tcp_down_to(world, 0.20)
        d.close()


def test_a_release_goes_on_once_the_fingers_opened_its_gap_and_the_next_move_waits_for_them(world, rg2):
    """gripper.release_gap: the arm may leave once the pads are off the object; the fingers finish opening
    meanwhile, and the next gripper command starts only once they have stopped."""
    d = driver(rg2)
    _tcp_down_to(world, 0.20)
    d.move(0.0, 40.0)
    d.move(0.085, 40.0, proceed_after=0.010)
    assert rg2.busy, "returned while the fingers were still opening"
    opened = d.width()
    assert 0.008 < opened < 0.060, f"returned at {opened * 1000:.1f} mm, not once 10 mm were open"
    grips = rg2.calls.count("rg_grip")
    d.move(0.085, 40.0)   # the grasp's open: waits for the release to end, then finds the fingers open already
    assert not rg2.busy and d.width() == pytest.approx(0.085, abs=0.002)
    assert rg2.calls.count("rg_grip") == grips, "an open gripper is not sent the same open again"
    rg2.trip_safety()   # a tool that trips while open: the next open is not sent, and is still a fault
    try:
        with pytest.raises(GripperFault, match="safety switch tripped"):
            d.move(0.085, 40.0)
    finally:
        rg2.reset_safety()
    d.move(0.030, 40.0)
    assert d.width() == pytest.approx(0.030, abs=0.002)
    d.close()


def test_a_tripped_safety_switch_is_a_gripper_fault_until_reset(world, rg2):
    d = driver(rg2)
    _tcp_down_to(world, 0.20)
    d.move(0.080, 20.0)
    rg2.trip_safety()
    with pytest.raises(GripperFault, match=r"safety switch tripped"):
        d.move(0.020, 20.0)
    assert d.width() == pytest.approx(0.080, abs=0.002), "a tripped tool does not move"
    rg2.reset_safety()
    d.move(0.020, 20.0)
    assert d.width() == pytest.approx(0.020, abs=0.002)
    d.close()


def test_stop_halts_the_fingers_mid_travel(world, rg2):
    d = driver(rg2)
    _tcp_down_to(world, 0.20)
    d.move(0.100, 20.0)
    proxy = xmlrpc.client.ServerProxy(f"http://{HOST}:{rg2.port}/")
    proxy.rg_grip(0, 0.0, 20.0)
    time.sleep(0.3)
    d.stop()
    assert not proxy.rg_get_busy(0)
    halted = d.width()
    assert 0.01 < halted < 0.097, "stopped on the way, not before it began nor at its end"
    time.sleep(0.3)
    assert d.width() == pytest.approx(halted, abs=0.002)
    d.close()


def test_bad_calls_are_faults_and_a_taken_port_is_named(world, rg2):
    proxy = xmlrpc.client.ServerProxy(f"http://{HOST}:{rg2.port}/")
    for call in (lambda: proxy.rg_grip(0, "wide", 20.0), lambda: proxy.rg_grip(0, 50.0, 400.0),
                 lambda: proxy.rg_get_width(3)):
        with pytest.raises(xmlrpc.client.Fault):
            call()
    assert proxy.rg_get_safety_failed(0) is False   # the service is still there
    with pytest.raises(OSError, match=rf"{HOST}:{rg2.port}"):
        RG2Service(world, HOST, rg2.port).start()


def test_nothing_listening_is_a_gripper_fault(world):
    with RG2Service(world, HOST, 0) as service:
        port = service.port
    with pytest.raises(GripperFault, match="connection refused"):
        RG2XmlRpcDriver(HOST, port, timeout=1.0).width()
