"""A D415 played by librealsense's own ``software_device``: frames pushed in by our code reach pyrealsense2's
syncer, alignment and filters as a camera's would.

Why it is in flgd and not only in the tests: the emulated cell (``camera.emulator``) feeds the daemon's
camera through it, so that ``D415Camera`` runs unchanged on rendered frames.  pyrealsense2 is loaded on
first use (:func:`flgd.hardware.hardware_library`), like every hardware library here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from flgd.hardware import hardware_library

__all__ = ["SoftwareD415", "EMULATED_SERIAL"]

EMULATED_SERIAL = "821212345678"   # a D415-shaped serial number for a device that has none


def _rs_intrinsics(rs: Any, k: np.ndarray, width: int, height: int) -> Any:
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

    def __init__(self, depth_k: np.ndarray, color_k: np.ndarray, size: tuple[int, int] = (640, 480),
                 depth_scale: float = 0.001, depth_to_color: np.ndarray | None = None,
                 serial: str = EMULATED_SERIAL, fps: int = 30):
        rs = self._rs = hardware_library("pyrealsense2")
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

    def _stream(self, sensor: Any, kind: Any, fmt: Any, bpp: int, k: np.ndarray, uid: int) -> Any:
        vs = self._rs.video_stream()
        vs.type, vs.index, vs.uid = kind, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = self.size[0], self.size[1], self.fps, bpp, fmt
        vs.intrinsics = _rs_intrinsics(self._rs, k, *self.size)
        return sensor.add_video_stream(vs).as_video_stream_profile()

    @property
    def next_frame_number(self) -> int:
        """The frame number the next :meth:`feed` gives its pair."""
        return self._n

    def feed(self, depth: np.ndarray, color: np.ndarray) -> None:
        """Push one depth + colour pair with a common timestamp, as the camera's firmware would."""
        rs = self._rs
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
