"""The D415 backend read through pyrealsense2 itself: a software_device, and a .db3 recording of one.

Frames are rendered by the simulated cell (``sim_cell.cell.SimCell``); the
alignment test, which needs the depth seen from a second imager, uses the
analytic box renderer of ``tests.fakes.scene``.  The heightmap that comes
out of librealsense must match the one made from the same frame directly.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import threading
from pathlib import Path

import numpy as np
import pytest

from flgd.cell import Frame
from flgd.config import CellConfig, load_config
from flgd.geometry import pose_matrix, rpy_to_matrix
from flgd.perception import frame_heightmaps
from tests.fakes.scene import Box, render

rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 cannot load here (libusb-1.0 missing?)")

from flgd.hardware.d415 import CameraFault, D415Camera  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIM_CONFIG = ROOT / "cell_config" / "sim.yaml"
SERIAL = "821212345678"
BOXES = [Box(-0.55, -0.03, 0.05, 0.07, 0.04, 0.3, (200, 40, 40)),
         Box(-0.40, 0.10, 0.03, 0.06, 0.08, -0.6, (40, 200, 40)),
         Box(-0.47, 0.15, 0.04, 0.04, 0.025, 1.1, (40, 40, 200))]


def sim_config(**camera_changes) -> CellConfig:
    cfg = load_config(SIM_CONFIG)
    return dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, **camera_changes))


def scene_frame(cfg: CellConfig) -> Frame:
    """A frame of clutter rendered by the simulated cell (D415-like noise and holes included)."""
    from sim_cell.cell import SimCell

    with SimCell(cfg) as cell:
        return cell.capture()


def synthetic_frame(cfg: CellConfig, camera_pose: np.ndarray | None = None, intrinsics: np.ndarray | None = None,
                    width: int = 640, height: int = 480) -> Frame:
    it = cfg.camera.intrinsics
    k = intrinsics if intrinsics is not None else np.array([[it.fx, 0, it.cx], [0, it.fy, it.cy], [0, 0, 1.0]])
    pose = camera_pose if camera_pose is not None else \
        pose_matrix(cfg.camera.pose.position, rpy_to_matrix(*cfg.camera.pose.rpy))
    color, depth = render(BOXES, pose, k, table_z=cfg.workspace.table_z, width=width, height=height,
                          depth_scale=cfg.camera.depth_scale)
    return Frame(color=color, depth=depth, depth_scale=cfg.camera.depth_scale, intrinsics=k, camera_pose=pose)


def _rs_intrinsics(k: np.ndarray, width: int, height: int):
    intr = rs.intrinsics()
    intr.width, intr.height = width, height
    intr.fx, intr.fy, intr.ppx, intr.ppy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    intr.model = rs.distortion.brown_conrady
    intr.coeffs = [0.0] * 5
    return intr


class SoftwareD415:
    """A librealsense software_device shaped like a D415: a Z16 depth sensor and an RGB8 colour sensor.

    ``depth_to_color`` is the 4x4 transform taking depth-camera points into the
    colour camera (identity: the depth is already registered to colour).
    """

    def __init__(self, depth_k: np.ndarray, color_k: np.ndarray, size=(640, 480), depth_scale: float = 0.001,
                 depth_to_color: np.ndarray | None = None, serial: str = SERIAL, fps: int = 30):
        w, h = size
        self.size, self.depth_scale, self.fps = size, depth_scale, fps
        self.device = rs.software_device()
        self.device.register_info(rs.camera_info.name, "Intel RealSense D415 (software)")
        self.device.register_info(rs.camera_info.serial_number, serial)
        self.depth_sensor = self.device.add_sensor("Stereo Module")
        self.color_sensor = self.device.add_sensor("RGB Camera")
        self.depth_profile = self._stream(self.depth_sensor, rs.stream.depth, rs.format.z16, 2, depth_k, 0)
        self.color_profile = self._stream(self.color_sensor, rs.stream.color, rs.format.rgb8, 3, color_k, 1)
        self.depth_sensor.add_read_only_option(rs.option.depth_units, depth_scale)
        t = np.eye(4) if depth_to_color is None else depth_to_color
        ext = rs.extrinsics()
        ext.rotation = [float(v) for v in t[:3, :3].T.ravel()]  # librealsense stores it column-major
        ext.translation = [float(v) for v in t[:3, 3]]
        self.depth_profile.register_extrinsics_to(self.color_profile, ext)
        self.device.create_matcher(rs.matchers.dlr_c)
        self._n = 0

    def _stream(self, sensor, kind, fmt, bpp, k, uid):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = kind, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = self.size[0], self.size[1], self.fps, bpp, fmt
        vs.intrinsics = _rs_intrinsics(k, *self.size)
        return sensor.add_video_stream(vs).as_video_stream_profile()

    def feed(self, depth: np.ndarray, color: np.ndarray) -> None:
        """Push one depth + colour pair with a common timestamp, as the camera's firmware would."""
        w, _ = self.size
        stamp = self._n * 1000.0 / self.fps
        for sensor, profile, pixels, bpp in ((self.depth_sensor, self.depth_profile, depth, 2),
                                             (self.color_sensor, self.color_profile, color, 3)):
            f = rs.software_video_frame()
            f.pixels = np.ascontiguousarray(pixels)
            f.stride, f.bpp = w * bpp, bpp
            f.timestamp, f.frame_number = stamp, self._n
            f.domain = rs.timestamp_domain.hardware_clock
            f.profile = profile
            if bpp == 2:
                f.depth_units = self.depth_scale
            sensor.on_video_frame(f)
        self._n += 1

    @contextlib.contextmanager
    def streaming(self, depth: np.ndarray, color: np.ndarray):
        """Feed the same pair at the camera's rate from a thread, like a live camera, until the block ends."""
        stop = threading.Event()

        def run() -> None:
            while not stop.is_set():
                self.feed(depth, color)
                stop.wait(1.0 / self.fps)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        try:
            yield self
        finally:
            stop.set()
            thread.join(timeout=5)


def registered_camera(frame: Frame, **kw) -> SoftwareD415:
    h, w = frame.depth.shape
    return SoftwareD415(frame.intrinsics, frame.intrinsics, (w, h), frame.depth_scale, **kw)


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
