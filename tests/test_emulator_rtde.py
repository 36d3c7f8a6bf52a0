"""The emulated controller's RTDE stream, read with the protocol's own packets (UR's RTDE guide)."""

from __future__ import annotations

import dataclasses
import socket
import struct
import time
from pathlib import Path

import pytest

from flgd.config import load_config
from sim_cell.emulator.arm import EmulatedArm
from sim_cell.emulator.rtde_server import HEADER, MAX_SILENCE, RTDE_PORT, Registers, RTDEServer
from sim_cell.emulator.tcp_service import read_exact
from sim_cell.emulator.faults import FaultInjector
from sim_cell.emulator.world import EmulatorWorld, slow_clock_warning
from tests.loopback import worker_host

HOST = worker_host(4)
ROOT = Path(__file__).resolve().parents[1]


def _packet(conn: socket.socket) -> tuple[str, bytes]:
    size, kind = HEADER.unpack(read_exact(conn, HEADER.size))
    return chr(kind), read_exact(conn, size - HEADER.size)


def _send(conn: socket.socket, kind: str, payload: bytes) -> None:
    conn.sendall(HEADER.pack(HEADER.size + len(payload), ord(kind)) + payload)


def _stamps_for(conn: socket.socket, seconds: float) -> list[float]:
    """The ``timestamp`` of every data package that arrives within ``seconds``."""
    stamps, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        kind, payload = _packet(conn)
        assert kind == "U"
        stamps.append(struct.unpack(">d", payload[1:9])[0])
    return stamps


@pytest.fixture
def stream():
    """A 500 Hz ``timestamp`` stream from the controller of a world whose clock has not started."""
    cfg = load_config(ROOT / "cell_config" / "sim.yaml")
    world = EmulatorWorld(dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=0, scene="")))
    server = RTDEServer(EmulatedArm(world), Registers(), HOST)
    server.start()
    conn = socket.create_connection((HOST, RTDE_PORT), timeout=5)
    try:
        _send(conn, "V", struct.pack(">H", 2))
        assert _packet(conn) == ("V", b"\x01")
        _send(conn, "O", struct.pack(">d", 500.0) + b"timestamp")
        assert _packet(conn)[0] == "O"
        _send(conn, "S", b"")
        assert _packet(conn) == ("S", b"\x01")
        yield world, conn
    finally:
        conn.close()
        server.close()
        world.close()


def test_a_package_goes_out_only_when_the_world_has_stepped_or_the_stream_would_fall_silent(stream):
    """Packages repeating a state nobody changed cost the emulator's physics its time: with the world's clock
    stopped the stream slows to one package per MAX_SILENCE; once it runs, every step is sent."""
    world, conn = stream
    still = _stamps_for(conn, 0.5)
    assert len(set(still)) == 1
    assert len(still) <= 0.5 / MAX_SILENCE + 2, f"{len(still)} packages of an unchanged state in 0.5 s"
    world.start()   # 240 steps a second
    running = _stamps_for(conn, 0.5)
    assert len(set(running)) > 20 and running == sorted(running)


def test_the_world_reports_how_fast_its_clock_ran_and_a_slow_clock_is_worth_a_warning():
    cfg = load_config(ROOT / "cell_config" / "sim.yaml")
    world = EmulatorWorld(dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=0, scene="")),
                          time_scale=1000.0)   # no PC steps physics 1000 times faster than real time
    injector = FaultInjector()
    injector.watch(world)
    try:
        world.start()
        time.sleep(1.0)
        clock = injector.status()["clock"]
    finally:
        world.close()
    assert clock["time_scale"] == 1000.0 and clock["sim_s"] > 0.1 and 0.9 < clock["wall_s"] < 5.0
    assert clock["real_time_factor"] < 500.0
    # the warning: over most of the window, below half the asked-for speed; never on a clock that keeps up
    assert "runs at 0.40x real time (asked for 1x)" in slow_clock_warning([(0.0, 0.0), (10.0, 4.0)], 1.0)
    assert slow_clock_warning([(0.0, 0.0), (10.0, 6.0)], 1.0) is None
    assert slow_clock_warning([(0.0, 0.0), (3.0, 0.3)], 1.0) is None   # too short a window to judge
