"""The D415 backend read through pyrealsense2 itself: a software_device, and a .db3 recording of one.

Frames are rendered by the simulated cell (``sim_cell.cell.SimCell``); the
alignment test, which needs the depth seen from a second imager, uses the
analytic box renderer of ``tests.fakes.scene``; the camera is ``tests.fakes.realsense``.  The heightmap that comes
out of librealsense must match the one made from the same frame directly.
"""

from __future__ import annotations

import gc

import numpy as np
import pytest

from flgd.cell import Frame
from flgd.config import CellConfig
from flgd.perception import frame_heightmaps

rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 cannot load here (libusb-1.0 missing?)")

from flgd.hardware.camera import CameraFault  # noqa: E402
from flgd.hardware.d415 import D415Camera  # noqa: E402
from tests.fakes.realsense import (BOXES, SERIAL, SoftwareD415, registered_camera,  # noqa: E402
                                   scene_frame, sim_config, synthetic_frame)


def assert_heightmaps_match(direct: Frame, through_rs: Frame, cfg: CellConfig) -> None:
    a = frame_heightmaps(direct, cfg.workspace, cfg.camera.depth_range)
    b = frame_heightmaps(through_rs, cfg.workspace, cfg.camera.depth_range)
    assert a.height.max() > 0.02, "the scene must have objects, or the comparison proves nothing"
    np.testing.assert_allclose(b.height, a.height, atol=0.001, rtol=0)
    np.testing.assert_array_equal(b.color, a.color)


# --------------------------------------------------------------------------- tests

def test_software_device_frames_give_the_same_heightmap():
    # Config intrinsics and depth scale deliberately differ from the device's: the camera must ignore them.
    cfg = sim_config(serial=SERIAL, depth_scale=0.00025)
    frame = scene_frame(sim_config())
    dev = registered_camera(frame)
    with D415Camera.from_device(cfg, dev.device) as cam, dev.streaming(frame.depth, frame.color):
        got = cam.capture()
    assert got.depth.dtype == np.uint16 and got.color.dtype == np.uint8
    np.testing.assert_allclose(got.intrinsics, frame.intrinsics)
    assert got.depth_scale == pytest.approx(frame.depth_scale, rel=1e-6)
    np.testing.assert_allclose(got.camera_pose, frame.camera_pose, atol=1e-12)
    assert_heightmaps_match(frame, got, cfg)


def test_recording_to_db3_and_playback_through_a_pipeline_give_the_same_heightmap(tmp_path):
    cfg = sim_config(serial=SERIAL, frame_timeout=0.5)
    frame = scene_frame(sim_config())
    dev = registered_camera(frame)
    path = tmp_path / "cell.db3"
    recorder = rs.recorder(str(path), dev.device)
    cam = D415Camera.from_device(cfg, recorder)
    with dev.streaming(frame.depth, frame.color):
        recorded = cam.capture()
    cam.close()
    del cam, recorder
    gc.collect()  # librealsense finalises the file when the recorder is destroyed
    assert path.is_file()

    with D415Camera.from_recording(cfg, str(path)) as playback:
        played = playback.capture()
        assert_heightmaps_match(frame, played, cfg)
        assert_heightmaps_match(frame, recorded, cfg)
        # The recording has a handful of frames; once they are used up a capture is a clear fault.
        with pytest.raises(CameraFault, match=r"no depth\+colour frame within 0\.5 s"):
            for _ in range(200):
                playback.capture()


def test_depth_from_a_separate_imager_is_aligned_to_colour():
    """A D415's depth comes from its left imager, ~15 mm from the colour camera, with other intrinsics."""
    cfg = sim_config()
    color_frame = synthetic_frame(cfg)
    depth_in_color = np.eye(4)
    depth_in_color[:3, 3] = (-0.015, 0.0, 0.0)          # depth imager pose in the colour camera frame
    depth_k = np.array([[590.0, 0, 318.0], [0, 590.0, 242.0], [0, 0, 1.0]])
    depth_frame = synthetic_frame(cfg, camera_pose=color_frame.camera_pose @ depth_in_color, intrinsics=depth_k)
    dev = SoftwareD415(depth_k, color_frame.intrinsics, depth_scale=cfg.camera.depth_scale,
                       depth_to_color=depth_in_color)
    with D415Camera.from_device(cfg, dev.device) as cam, dev.streaming(depth_frame.depth, color_frame.color):
        got = cam.capture()
    assert not np.array_equal(got.depth, depth_frame.depth), "depth must have been re-projected"
    # unfilled: the occlusion seams stay 0 in both instead of being filled from neighbours that differ
    a = frame_heightmaps(color_frame, cfg.workspace, cfg.camera.depth_range, fill="none").height
    b = frame_heightmaps(got, cfg.workspace, cfg.camera.depth_range, fill="none").height
    close = np.abs(a - b) <= 0.001
    # Re-projection leaves a few cells at object edges (occlusion seams) different; nothing else.
    assert close.mean() > 0.995, f"only {close.mean():.4f} of the heightmap matches within 1 mm"
    for box in BOXES:
        r, c = int((box.y - cfg.workspace.y[0]) / 0.002), int((box.x - cfg.workspace.x[0]) / 0.002)
        assert b[r - 2:r + 3, c - 2:c + 3] == pytest.approx(box.height, abs=0.001)


def test_librealsense_filters_fill_holes_and_keep_the_surface():
    cfg = sim_config(spatial_filter=True, temporal_filter=True, hole_filling=True)
    frame = synthetic_frame(cfg)
    rng = np.random.default_rng(3)
    holed = frame.depth.copy()
    holed[rng.random(holed.shape) < 0.05] = 0           # 5 % of readings missing, like a real D415
    dev = registered_camera(frame)
    with D415Camera.from_device(cfg, dev.device) as cam, dev.streaming(holed, frame.color):
        got = cam.capture()
    assert np.count_nonzero(got.depth == 0) < 0.1 * np.count_nonzero(holed == 0)
    a = frame_heightmaps(frame, cfg.workspace, cfg.camera.depth_range).height
    b = frame_heightmaps(got, cfg.workspace, cfg.camera.depth_range).height
    assert np.median(np.abs(a - b)) < 0.001


def test_no_frames_is_a_camera_fault_naming_the_timeout():
    cfg = sim_config(frame_timeout=0.3)
    frame = synthetic_frame(cfg, width=64, height=48)
    dev = registered_camera(frame)
    with D415Camera.from_device(cfg, dev.device) as cam:
        with pytest.raises(CameraFault, match=r"no depth\+colour frame within 0\.3 s \(camera\.frame_timeout\)"):
            cam.capture()
        with dev.streaming(frame.depth, frame.color):
            assert cam.capture().depth.shape == (48, 64)  # frames flowing again: capture works
        dev.depth_sensor.stop()                           # the depth stream dies under the camera
        with dev.streaming(frame.depth, frame.color), pytest.raises(CameraFault, match="no depth"):
            cam.capture()


def test_a_failed_warm_up_releases_the_device_so_the_next_open_works():
    """A camera that sends nothing right after it is opened (warm-up) must not stay open: the next open
    (flgctl reset) would find the device busy however healthy the camera is by then."""
    cfg = sim_config(frame_timeout=1.0)  # a restarted software_device may take a few frames to sync
    frame = synthetic_frame(cfg, width=64, height=48)
    dev = registered_camera(frame)
    with pytest.raises(CameraFault, match=r"no depth\+colour frame within 1\.0 s"):
        D415Camera.from_device(cfg, dev.device, warmup_frames=2)
    with dev.streaming(frame.depth, frame.color):
        with D415Camera.from_device(cfg, dev.device, warmup_frames=2) as cam:
            assert cam.capture().depth.shape == (48, 64)


def test_serial_mismatch_and_missing_camera_are_refused():
    frame = synthetic_frame(sim_config(), width=64, height=48)
    dev = registered_camera(frame)
    with pytest.raises(CameraFault, match=f"has serial {SERIAL}, but camera.serial .* is 999"):
        D415Camera.from_device(sim_config(serial="999"), dev.device)
    # No RealSense on this machine: opening the configured one is a clear fault, not a crash.
    if len(rs.context().query_devices()) == 0:
        with pytest.raises(CameraFault, match="RealSense 123 .* is not connected; connected: none"):
            D415Camera.open(sim_config(serial="123"))
        with pytest.raises(CameraFault, match="camera.serial is empty .* 0 RealSense cameras"):
            D415Camera.open(sim_config(serial=""))
