"""The emulated D415: sim_cell/emulator/camera_feed.py serving SimCell's frames, read by flgd's own D415Camera
(``camera.emulator``) through a librealsense software device -- syncer, depth scale and filters included.

The world's clock is not started here: the scene holds still, so a frame rendered by the cell itself and the
frame that came through librealsense show the same world (depth noise off, so they are the same pixels).
"""

from __future__ import annotations

import dataclasses
import socket
import threading
import time

import numpy as np
import pytest

from flgd.config import ConfigError, config_from_dict, load_config
from flgd.perception import frame_heightmaps

pytest.importorskip("pyrealsense2", reason="pyrealsense2 cannot load here (libusb-1.0 missing?)")

from flgd.hardware.camera import CameraFault  # noqa: E402
from flgd.hardware.d415 import D415Camera  # noqa: E402
from flgd.hardware.frame_feed import FrameFeedClient  # noqa: E402
from flgd.hardware.ur5e_cell import _open_d415  # noqa: E402  (the real cell's camera factory)
from sim_cell.emulator.camera_feed import CameraFeed  # noqa: E402
from sim_cell.emulator.world import EmulatorWorld  # noqa: E402
from sim_cell.objects import ObjectSpec  # noqa: E402
from tests.fakes.realsense import SIM_CONFIG
from tests.loopback import worker_host  # noqa: E402

HOST = worker_host(3)


@pytest.fixture(scope="module")
def world():
    cfg = load_config(SIM_CONFIG)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=6, depth_noise=False))
    with EmulatorWorld(cfg) as w:
        yield w


@pytest.fixture
def feed(world):
    with CameraFeed(world, HOST, 0) as f:
        yield f


def daemon_config(world, address: str, **camera):
    """The daemon's side: the same cell, its camera read from the emulator's feed."""
    cfg = world.config
    return dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, **{"emulator": address,
                                                                              "frame_timeout": 0.5, **camera}))


def assert_same_heightmap(direct, through_rs, cfg) -> None:
    a = frame_heightmaps(direct, cfg.workspace, cfg.camera.depth_range)
    b = frame_heightmaps(through_rs, cfg.workspace, cfg.camera.depth_range)
    assert a.height.max() > 0.02, "the scene must have objects, or the comparison proves nothing"
    np.testing.assert_allclose(b.height, a.height, atol=0.001, rtol=0)
    np.testing.assert_array_equal(b.color, a.color)


def test_the_real_camera_code_on_the_feed_sees_what_the_cell_renders(world, feed):
    cfg = daemon_config(world, feed.address)
    with _open_d415(cfg) as cam:
        got = cam.capture()
    direct = world.cell.capture()
    assert got.depth.dtype == np.uint16 and got.color.dtype == np.uint8
    np.testing.assert_allclose(got.intrinsics, direct.intrinsics)
    assert got.depth_scale == pytest.approx(direct.depth_scale, rel=1e-6)
    assert_same_heightmap(direct, got, cfg)
    assert feed.frames_served >= 30, "the live warm-up frames came from the feed"
    assert feed.renders <= 3, "a still world is rendered once, not for every frame"


def test_frames_follow_the_world(world, feed):
    cfg = daemon_config(world, feed.address)
    with _open_d415(cfg) as cam:
        before = frame_heightmaps(cam.capture(), cfg.workspace, cfg.camera.depth_range)
        body = world.cell.add_object(ObjectSpec(shape="cube", size=(0.05,), position=(-0.30, -0.20, 0.025)))
        try:
            after = frame_heightmaps(cam.capture(), cfg.workspace, cfg.camera.depth_range)
        finally:
            world.cell.remove_object(body, settle=0.0)
    row, col = int((-0.20 - cfg.workspace.y[0]) / 0.002), int((-0.30 - cfg.workspace.x[0]) / 0.002)
    assert before.height[row, col] < 0.01 and after.height[row, col] == pytest.approx(0.05, abs=0.005)


@pytest.mark.slow
def test_a_stopped_feed_is_a_camera_fault_and_a_reopen_recovers_it(world, feed):
    cfg = daemon_config(world, feed.address)
    cam = _open_d415(cfg)
    try:
        cam.capture()
        feed.stop_frames()
        with pytest.raises(CameraFault, match=r"no depth\+colour frame within 0\.5 s \(camera.frame_timeout\)"):
            cam.capture()
    finally:
        cam.close()
    with pytest.raises(CameraFault, match=r"no depth\+colour frame within 0\.5 s"):
        _open_d415(cfg)   # a reset while the camera is still silent fails as on a real cell
    feed.resume_frames()
    with _open_d415(cfg) as cam:   # the reset's reopen, once the frames are back
        assert_same_heightmap(world.cell.capture(), cam.capture(), cfg)


def test_a_feed_that_is_not_there_is_a_camera_fault(world):
    with CameraFeed(world, HOST, 0) as gone:
        address = gone.address
    with pytest.raises(CameraFault, match=rf"emulated RealSense at {address} .*cannot open the feed.*flgd emulate"):
        _open_d415(daemon_config(world, address))


def test_a_feed_that_closes_is_a_disconnected_camera(world):
    feed = CameraFeed(world, HOST, 0).start()
    cam = D415Camera.open(daemon_config(world, feed.address), warmup_frames=0)
    try:
        cam.capture()
        feed.close()
        with pytest.raises(CameraFault, match=r"was disconnected"):
            cam.capture()
    finally:
        cam.close()


def test_a_malformed_request_closes_that_connection_only(world, feed):
    with socket.create_connection((HOST, feed.port), timeout=2.0) as bad:
        bad.makefile("rb").readline()          # the hello
        bad.sendall(b"give me everything\n")
        assert bad.recv(1) == b"", "the feed hangs up on a client that breaks the format"
    client = FrameFeedClient(HOST, feed.port, timeout=2.0)
    try:
        client.request()
        frame = client.receive()
        assert frame.depth.shape == (client.hello.height, client.hello.width)
    finally:
        client.close()
    with pytest.raises(OSError, match=rf"{HOST}:{feed.port}"):
        CameraFeed(world, HOST, feed.port).start()


def test_camera_emulator_must_be_host_and_port():
    assert config_from_dict({"camera": {"emulator": "127.0.0.2:50415"}}).camera.emulator == "127.0.0.2:50415"
    assert load_config(SIM_CONFIG).camera.emulator == "", "empty by default: the real camera"
    for bad in ("50415", "localhost", "127.0.0.1:0", "127.0.0.1:port"):
        with pytest.raises(ConfigError, match=r"camera\.emulator: got .*expected HOST:PORT"):
            config_from_dict({"camera": {"emulator": bad}})


def test_a_capture_never_takes_a_frame_asked_for_before_it_began(world, feed, monkeypatch):
    """A frame rendered before the world changed and delivered late (a loaded PC) must not answer a capture
    that began after the change: here every answer lags its render by 0.3 s."""
    rendered = threading.Event()
    render = feed._current_frame

    def late_render():
        frame = render()
        rendered.set()
        time.sleep(0.3)
        return frame

    monkeypatch.setattr(feed, "_current_frame", late_render)
    cfg = daemon_config(world, feed.address, frame_timeout=3.0)
    row, col = int((-0.20 - cfg.workspace.y[0]) / 0.002), int((-0.30 - cfg.workspace.x[0]) / 0.002)
    cam = D415Camera.open(cfg, warmup_frames=0)
    try:
        cam.capture()
        rendered.clear()
        rendered.wait(2.0)   # a frame of the world without the cube is on its way
        body = world.cell.add_object(ObjectSpec(shape="cube", size=(0.05,), position=(-0.30, -0.20, 0.025)))
        try:
            after = frame_heightmaps(cam.capture(), cfg.workspace, cfg.camera.depth_range)
        finally:
            world.cell.remove_object(body, settle=0.0)
    finally:
        cam.close()
    assert after.height[row, col] == pytest.approx(0.05, abs=0.005)


def test_between_captures_the_camera_asks_the_feed_for_nothing(world, feed):
    """A render holds the emulator's physics; frames are asked for only while a capture waits, so an arm moving
    between two captures is never slowed by renders nobody looks at."""
    cfg = daemon_config(world, feed.address)
    with _open_d415(cfg) as cam:
        cam.capture()
        time.sleep(0.2)   # a request already on its way may still be answered
        served = feed.frames_served
        time.sleep(0.5)   # 15 frames of a 30 fps stream
        assert feed.frames_served == served
        cam.capture()
        assert feed.frames_served > served
