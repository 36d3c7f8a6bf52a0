"""A D415 played by librealsense's own software_device: frames rendered by the simulated cell or by the
analytic box renderer reach pyrealsense2 as a camera's would (import only where pyrealsense2 loads)."""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from pathlib import Path

import numpy as np
import pyrealsense2 as rs

from flgd.cell import Frame
from flgd.config import CellConfig, load_config
from flgd.geometry import pose_matrix, rpy_to_matrix
from tests.fakes.scene import Box, render

ROOT = Path(__file__).resolve().parents[2]
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
