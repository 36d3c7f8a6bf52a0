"""The RealSense D415 through pyrealsense2: aligned depth + colour frames as ``flgd.cell.Frame``.

The intrinsics and the depth scale are read from the device (or the recording),
never from the config: they differ per unit and per resolution.  The camera
pose comes from the config (``camera.pose``, written by ``flgd calibrate``).

Frames come from a *source*: a live device opened by serial number, a
recording (``.db3``/``.bag``) played through ``rs.pipeline``, or any
``rs.device`` whose sensors we start ourselves -- a ``software_device`` fed
by a test or by ``flgd emulate``'s camera feed (``camera.emulator``), or an
``rs.recorder`` wrapping one.  The same capture code runs on all of them, so
the tests exercise the real librealsense processing (alignment, filters,
recording and playback).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from flgd.cell import Frame
from flgd.config import CellConfig
from flgd.geometry import pose_matrix, rpy_to_matrix
from flgd.hardware.camera import CameraFault
from flgd.hardware.frame_sources import EmulatorSource, FrameSource, PipelineSource, SensorSource, rs_library

__all__ = ["D415Camera", "TEMPORAL_FILTER_FRAMES", "LIVE_WARMUP_FRAMES"]

# Consecutive frames fed to the temporal filter per capture (camera.temporal_filter).
TEMPORAL_FILTER_FRAMES = 5
# Frames dropped after a live start so that auto-exposure settles (about 1 s at 30 Hz).
LIVE_WARMUP_FRAMES = 30
# Streams closer than this to "already registered" are not re-aligned (see _registered).
_REGISTERED_TOL = 1e-6


def _intrinsics_matrix(intr) -> np.ndarray:
    return np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])


def _registered(depth_profile, color_profile) -> bool:
    """True when depth is already pixel-registered to colour (same size, intrinsics, identity extrinsics).

    ``rs.align`` is then a geometric identity, but its pixel-footprint rounding
    still punches rows and columns of holes into the depth; skipping it keeps
    such frames (recordings of registered data, simulated cameras) exact.
    A real D415 has a baseline between its imagers and is always aligned.
    """
    d = depth_profile.as_video_stream_profile()
    c = color_profile.as_video_stream_profile()
    di, ci = d.get_intrinsics(), c.get_intrinsics()
    same = (di.width, di.height) == (ci.width, ci.height) and all(
        abs(a - b) <= _REGISTERED_TOL for a, b in ((di.fx, ci.fx), (di.fy, ci.fy), (di.ppx, ci.ppx), (di.ppy, ci.ppy)))
    if not same or any(abs(k) > _REGISTERED_TOL for k in list(di.coeffs) + list(ci.coeffs)):
        return False
    ext = d.get_extrinsics_to(c)
    return bool(np.allclose(np.asarray(ext.rotation, float), np.eye(3).ravel(), atol=_REGISTERED_TOL)
                and np.allclose(np.asarray(ext.translation, float), 0.0, atol=_REGISTERED_TOL))


class D415Camera:
    """Aligned RGB-D frames from a RealSense source, with the device's intrinsics and depth scale.

    Build it with :meth:`open` (live camera), :meth:`from_recording` or
    :meth:`from_device`.  ``capture`` raises :class:`CameraFault` (a CellFault)
    when no frame arrives in ``camera.frame_timeout`` seconds or the library fails.
    """

    def __init__(self, config: CellConfig, source: FrameSource, *, discard_queued: bool = True,
                 warmup_frames: int = 0):
        rs = rs_library()
        self.config = config
        self._source = source
        self._discard_queued = discard_queued
        self._lock = threading.Lock()
        cam = config.camera
        self.camera_pose = pose_matrix(cam.pose.position, rpy_to_matrix(*cam.pose.rpy))
        try:
            self._check_serial(rs, source)
            self.device_depth_scale = source.depth_scale()
        except RuntimeError as exc:
            source.close()
            raise CameraFault(f"{source.description}: cannot read the depth scale: {exc}") from exc
        if not self.device_depth_scale > 0:
            source.close()
            raise CameraFault(f"{source.description}: device reports depth scale {self.device_depth_scale!r}")
        try:
            self._filters = self._make_filters(rs)
            self._align = rs.align(rs.stream.color)
            for _ in range(warmup_frames):
                self._next_frames()
        except BaseException as exc:
            # Why: a started stream left behind keeps the device busy, so the next open
            # (flgctl reset) would fail too, however healthy the camera is by then.
            source.close()
            if isinstance(exc, RuntimeError) and not isinstance(exc, CameraFault):
                raise CameraFault(f"{source.description}: librealsense error while starting: {exc}") from exc
            raise

    # -- constructors
    @classmethod
    def open(cls, config: CellConfig, warmup_frames: int = LIVE_WARMUP_FRAMES) -> "D415Camera":
        """The live camera named by ``camera.serial`` (the only one when the serial is empty), or the
        emulator's feed when ``camera.emulator`` is set."""
        rs = rs_library()
        cam = config.camera
        if cam.emulator:
            source: FrameSource = EmulatorSource(cam.emulator, cam.frame_timeout, cam.intrinsics.width,
                                                   cam.intrinsics.height)
            return cls(config, source, discard_queued=True, warmup_frames=warmup_frames)
        try:
            serials = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
        except RuntimeError as exc:
            raise CameraFault(f"cannot list RealSense devices: {exc}") from exc
        if cam.serial:
            if cam.serial not in serials:
                found = ", ".join(serials) or "none"
                raise CameraFault(f"RealSense {cam.serial} (camera.serial in {config.source}) is not connected; "
                                  f"connected: {found}")
            serial = cam.serial
        elif len(serials) == 1:
            serial = serials[0]
        else:
            raise CameraFault(f"camera.serial is empty in {config.source} and {len(serials)} RealSense cameras are "
                              f"connected ({', '.join(serials) or 'none'}); set camera.serial")
        rs_config = rs.config()
        rs_config.enable_device(serial)
        w, h = cam.intrinsics.width, cam.intrinsics.height
        rs_config.enable_stream(rs.stream.depth, w, h, rs.format.z16, cam.fps)
        rs_config.enable_stream(rs.stream.color, w, h, rs.format.rgb8, cam.fps)
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(rs_config)
        except RuntimeError as exc:
            raise CameraFault(f"RealSense {serial}: cannot stream depth+colour {w}x{h} at {cam.fps} Hz "
                              f"(camera.intrinsics / camera.fps in {config.source}): {exc}") from exc
        source = PipelineSource(pipeline, profile, f"RealSense {serial}", serial=serial, live=True)
        return cls(config, source, discard_queued=True, warmup_frames=warmup_frames)

    @classmethod
    def from_recording(cls, config: CellConfig, path: str) -> "D415Camera":
        """Play a librealsense recording (``.db3`` or ``.bag``) frame by frame, not in real time."""
        rs = rs_library()
        rs_config = rs.config()
        pipeline = rs.pipeline()
        try:
            rs_config.enable_device_from_file(str(path), repeat_playback=False)
            profile = pipeline.start(rs_config)
            profile.get_device().as_playback().set_real_time(False)
        except RuntimeError as exc:
            raise CameraFault(f"cannot play RealSense recording {path}: {exc}") from exc
        source = PipelineSource(pipeline, profile, f"RealSense recording {path}")
        return cls(config, source, discard_queued=False)

    @classmethod
    def from_device(cls, config: CellConfig, device: Any, *, discard_queued: bool = True,
                    warmup_frames: int = 0) -> "D415Camera":
        """Stream an existing ``rs.device`` (a software_device, an ``rs.recorder`` around one, ...)."""
        cam, info = config.camera, rs_library().camera_info
        name = device.get_info(info.name) if device.supports(info.name) else "device"
        source = SensorSource(device, cam.intrinsics.width, cam.intrinsics.height, cam.fps, f"RealSense {name}")
        return cls(config, source, discard_queued=discard_queued, warmup_frames=warmup_frames)

    # -- capture
    def capture(self) -> Frame:
        """One aligned frame; with the temporal filter, the last of a few consecutive frames."""
        rs = rs_library()
        with self._lock:
            try:
                if self._discard_queued:
                    self._source.drop_queued()
                count = TEMPORAL_FILTER_FRAMES if self.config.camera.temporal_filter else 1
                frames = None
                for _ in range(count):
                    frames = self._filter(self._next_frames())
                return self._to_frame(rs, frames)
            except CameraFault:
                raise  # already says what is wrong (CameraFault is a RuntimeError too)
            except RuntimeError as exc:
                raise CameraFault(f"{self._source.description}: librealsense error: {exc}") from exc

    def close(self) -> None:
        self._source.close()

    def __enter__(self) -> "D415Camera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals
    def _check_serial(self, rs, source: FrameSource) -> None:
        want = self.config.camera.serial
        dev = source.device
        if want and dev.supports(rs.camera_info.serial_number):
            have = dev.get_info(rs.camera_info.serial_number)
            if have != want:
                raise CameraFault(f"{source.description} has serial {have}, but camera.serial in "
                                  f"{self.config.source} is {want}")

    def _make_filters(self, rs) -> list:
        cam = self.config.camera
        filters: list = []
        if cam.spatial_filter or cam.temporal_filter:
            # librealsense's recommended order: smooth in the disparity domain, then back to depth.
            filters.append(rs.disparity_transform(True))
            if cam.spatial_filter:
                filters.append(rs.spatial_filter())
            if cam.temporal_filter:
                filters.append(rs.temporal_filter())
            filters.append(rs.disparity_transform(False))
        if cam.hole_filling:
            filters.append(rs.hole_filling_filter())
        return filters

    def _filter(self, frames):
        out = frames
        for block in self._filters:
            out = block.process(out)
        return out.as_frameset() if self._filters else frames

    def _next_frames(self):
        timeout = self.config.camera.frame_timeout
        frames = self._source.wait(timeout)
        if frames is None:
            if not self._source.still_connected():
                raise CameraFault(f"{self._source.description} was disconnected (no frame within {timeout} s)")
            raise CameraFault(f"{self._source.description}: no depth+colour frame within {timeout} s "
                              f"(camera.frame_timeout); cable, USB bandwidth or the end of a recording?")
        return frames

    def _to_frame(self, rs, frames) -> Frame:
        depth_frame, color_frame = frames.get_depth_frame(), frames.get_color_frame()
        if not _registered(depth_frame.get_profile(), color_frame.get_profile()):
            frames = self._align.process(frames)
            depth_frame, color_frame = frames.get_depth_frame(), frames.get_color_frame()
            if not depth_frame or not color_frame:
                raise CameraFault(f"{self._source.description}: alignment to colour produced no frame")
        color = np.asanyarray(color_frame.get_data())
        if color_frame.get_profile().format() == rs.format.bgr8:
            color = color[..., ::-1]
        color = np.ascontiguousarray(color, dtype=np.uint8).copy()
        depth = np.asanyarray(depth_frame.get_data()).astype(np.uint16, copy=True)
        intr = color_frame.get_profile().as_video_stream_profile().get_intrinsics()
        scale = self.device_depth_scale * self.config.camera.depth_scale_correction
        return Frame(color=color, depth=depth, depth_scale=scale, intrinsics=_intrinsics_matrix(intr),
                     camera_pose=self.camera_pose.copy(), timestamp=frames.get_timestamp() / 1000.0)
