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

import abc
import threading
import time
from typing import Any

import numpy as np

from flgd.cell import CellFault, Frame
from flgd.config import CellConfig
from flgd.geometry import pose_matrix, rpy_to_matrix
from flgd.hardware import hardware_library

__all__ = ["D415Camera", "CameraFault", "TEMPORAL_FILTER_FRAMES", "LIVE_WARMUP_FRAMES"]

# Consecutive frames fed to the temporal filter per capture (camera.temporal_filter).
TEMPORAL_FILTER_FRAMES = 5
# Frames dropped after a live start so that auto-exposure settles (about 1 s at 30 Hz).
LIVE_WARMUP_FRAMES = 30
# Streams closer than this to "already registered" are not re-aligned (see _registered).
_REGISTERED_TOL = 1e-6


class CameraFault(CellFault):
    """The camera stopped delivering usable frames (timeout, disconnect, library error)."""


def _rs():
    return hardware_library("pyrealsense2")


# --------------------------------------------------------------------------- sources

class _FrameSource(abc.ABC):
    """Where framesets come from; hides the pipeline / sensor+syncer difference."""

    description: str = "RealSense"

    @abc.abstractmethod
    def wait(self, timeout_s: float) -> Any | None:
        """The next frameset holding depth and colour, or None after ``timeout_s``."""

    @abc.abstractmethod
    def drop_queued(self) -> None:
        """Discard framesets already queued (taken before the caller's moment of interest)."""

    @property
    @abc.abstractmethod
    def device(self) -> Any:
        """The ``rs.device`` behind this source."""

    @abc.abstractmethod
    def depth_scale(self) -> float:
        """Metres per raw depth unit, as the device reports it."""

    def still_connected(self) -> bool:
        """False when the device is known to be gone (asked only after a timeout)."""
        return True

    @abc.abstractmethod
    def close(self) -> None:
        """Stop streaming; safe to call twice."""


def _has_depth_and_color(frames) -> bool:
    return bool(frames) and bool(frames.get_depth_frame()) and bool(frames.get_color_frame())


class _PipelineSource(_FrameSource):
    """An ``rs.pipeline`` already started (a live device or a recording)."""

    def __init__(self, pipeline: Any, profile: Any, description: str, serial: str = "", live: bool = False):
        self._pipeline = pipeline
        self._profile = profile
        self._serial = serial
        self._live = live
        self._closed = False
        self.description = description

    def wait(self, timeout_s: float):
        deadline_ms = max(1, int(timeout_s * 1000))
        ok, frames = self._pipeline.try_wait_for_frames(deadline_ms)
        if ok and _has_depth_and_color(frames):
            frames.keep()
            return frames
        return None

    def drop_queued(self) -> None:
        while True:
            frames = self._pipeline.poll_for_frames()
            if not frames:
                return

    @property
    def device(self):
        return self._profile.get_device()

    def depth_scale(self) -> float:
        return float(self.device.first_depth_sensor().get_depth_scale())

    def still_connected(self) -> bool:
        if not self._live:
            return True
        rs = _rs()
        serials = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
        return self._serial in serials

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass  # already stopped (device gone): nothing left to release


class _SensorSource(_FrameSource):
    """Depth and colour sensors of an ``rs.device`` started into one ``rs.syncer``."""

    def __init__(self, device: Any, width: int, height: int, fps: int, description: str):
        rs = _rs()
        self._device = device
        self._syncer = rs.syncer()
        self._sensors: list[Any] = []
        self.description = description
        depth = _find_profile(device, rs.stream.depth, (rs.format.z16,), width, height, fps)
        color = _find_profile(device, rs.stream.color, (rs.format.rgb8, rs.format.bgr8), width, height, fps)
        self._depth_sensor = depth[0] if depth else None
        if depth is None or color is None:
            missing = " and ".join(n for n, p in (("depth (z16)", depth), ("colour (rgb8/bgr8)", color)) if p is None)
            raise CameraFault(f"{description}: the device offers no {missing} stream")
        try:
            for sensor, profile in (depth, color):
                sensor.open(profile)
                self._sensors.append(sensor)
                sensor.start(self._syncer)
        except RuntimeError as exc:
            self.close()
            raise CameraFault(f"{description}: cannot start streaming: {exc}") from exc

    def wait(self, timeout_s: float):
        remaining_ms = max(1, int(timeout_s * 1000))
        # The syncer may hand out a lone frame before its partner arrives; wait on for the pair.
        while remaining_ms > 0:
            step = min(remaining_ms, 100)
            ok, frames = self._syncer.try_wait_for_frames(step)
            remaining_ms -= step
            if ok and _has_depth_and_color(frames):
                frames.keep()
                return frames
        return None

    def drop_queued(self) -> None:
        while True:
            frames = self._syncer.poll_for_frames()
            if not frames:
                return

    @property
    def device(self):
        return self._device

    def depth_scale(self) -> float:
        # A recorder's or software sensor is not always typed as a depth_sensor; the option is always there.
        return float(self._depth_sensor.get_option(_rs().option.depth_units))

    def close(self) -> None:
        self._device = None  # lets an rs.recorder be destroyed, which finalises its file
        sensors, self._sensors = self._sensors, []
        for sensor in sensors:
            for action in (sensor.stop, sensor.close):
                try:
                    action()
                except RuntimeError:
                    pass  # not started / already closed


class _EmulatorSource(_SensorSource):
    """``flgd emulate``'s camera feed (``camera.emulator``) pushed into a software D415 by a thread.

    The software device has the feed's intrinsics and depth scale, so everything after it (syncer,
    filters, alignment, the depth scale read from the device) is the path a camera's frames take.
    A feed that stops answering leaves the syncer empty: the capture's frame timeout, as for a camera.

    A frame is rendered when the feed answers a request, so one asked for before a capture began can show the
    world as it was before (an arm still on its way) and arrive after the capture dropped what was queued; on a
    loaded PC that lag reaches a large part of a second.  A capture therefore takes only frames asked for after
    it began (checked by frame number), as a live camera's next exposure is.

    Frames are asked for only while a capture waits: a render holds the emulator's physics for tens of
    milliseconds, and a stream rendered through every move would slow the emulated arm by a third.
    """

    KEEP_REQUEST_TIMES = 64  # frame numbers remembered with the moment they were asked for

    def __init__(self, address: str, timeout: float, width: int, height: int):
        from flgd.config import parse_emulator_address
        from flgd.hardware.frame_feed import FrameFeedClient
        from flgd.hardware.software_d415 import SoftwareD415

        description = f"emulated RealSense at {address} (camera.emulator)"
        try:
            host, port = parse_emulator_address(address)
            self._client = FrameFeedClient(host, port, timeout)
        except (OSError, ValueError) as exc:
            kind = "no answer" if isinstance(exc, TimeoutError) else f"{type(exc).__name__}: {exc}"
            raise CameraFault(f"{description}: cannot open the feed: {kind}; is `flgd emulate` running?") from exc
        hello = self._client.hello
        self._camera = SoftwareD415(hello.intrinsics, hello.intrinsics, (hello.width, hello.height),
                                    hello.depth_scale, serial=hello.serial, fps=hello.fps)
        self._lost = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._asked_at: dict[int, float] = {}   # software frame number -> when the pump asked the feed for it
        self._fresh_from = 0.0                  # frames asked for before this moment are stale
        self._wanted = threading.Event()        # set while a capture waits for a frame
        try:
            super().__init__(self._camera.device, width, height, hello.fps, description)
        except CameraFault:
            self._client.close()
            raise
        self._thread = threading.Thread(target=self._pump, name="d415-emulator-feed", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        """Ask for a frame, push it in, keep the feed's rate; a stalled feed is waited on, a broken one ends it."""
        from flgd.hardware.frame_feed import FeedStalled

        period = 1.0 / self._camera.fps
        try:
            while not self._stop.is_set():
                if not self._wanted.wait(0.05):
                    continue
                started = time.monotonic()
                self._client.request()
                while True:
                    try:
                        frame = self._client.receive()
                        break
                    except FeedStalled:
                        if self._stop.is_set():
                            return
                number = self._camera.next_frame_number
                self._asked_at[number] = started   # before the feed: the syncer may hand it out at once
                self._asked_at.pop(number - self.KEEP_REQUEST_TIMES, None)
                self._camera.feed(frame.depth, frame.color)
                self._stop.wait(max(0.0, period - (time.monotonic() - started)))
        except (OSError, RuntimeError):
            self._lost.set()  # the feed closed or broke its format: a camera unplugged

    def wait(self, timeout_s: float):
        """The next frameset asked for after the last :meth:`drop_queued`; older ones are passed over."""
        deadline = time.monotonic() + timeout_s
        self._wanted.set()   # the stream runs while a capture waits (the syncer pairs a frame once the next comes)
        try:
            while True:
                frames = super().wait(max(0.001, deadline - time.monotonic()))
                if frames is None:
                    return None
                asked = self._asked_at.get(frames.get_depth_frame().get_frame_number())
                if asked is None or asked >= self._fresh_from:   # None: older than 64 requests, dropped with the queue
                    return frames
                if time.monotonic() >= deadline:
                    return None
        finally:
            self._wanted.clear()

    def drop_queued(self) -> None:
        self._fresh_from = time.monotonic()
        super().drop_queued()

    def still_connected(self) -> bool:
        return not self._lost.is_set()

    def close(self) -> None:
        self._stop.set()
        self._client.close()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        super().close()


def _find_profile(device: Any, stream: Any, formats: tuple, width: int, height: int, fps: int):
    """(sensor, profile) for ``stream``; the configured size and rate if offered, else the first."""
    fallback = None
    for sensor in device.query_sensors():
        for profile in sensor.get_stream_profiles():
            if profile.stream_type() != stream or profile.format() not in formats:
                continue
            if not profile.is_video_stream_profile():
                continue
            vp = profile.as_video_stream_profile()
            if (vp.width(), vp.height(), vp.fps()) == (width, height, fps):
                return sensor, profile
            if fallback is None:
                fallback = (sensor, profile)
    return fallback


# --------------------------------------------------------------------------- camera

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

    def __init__(self, config: CellConfig, source: _FrameSource, *, discard_queued: bool = True,
                 warmup_frames: int = 0):
        rs = _rs()
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
        rs = _rs()
        cam = config.camera
        if cam.emulator:
            source: _FrameSource = _EmulatorSource(cam.emulator, cam.frame_timeout, cam.intrinsics.width,
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
        source = _PipelineSource(pipeline, profile, f"RealSense {serial}", serial=serial, live=True)
        return cls(config, source, discard_queued=True, warmup_frames=warmup_frames)

    @classmethod
    def from_recording(cls, config: CellConfig, path: str) -> "D415Camera":
        """Play a librealsense recording (``.db3`` or ``.bag``) frame by frame, not in real time."""
        rs = _rs()
        rs_config = rs.config()
        pipeline = rs.pipeline()
        try:
            rs_config.enable_device_from_file(str(path), repeat_playback=False)
            profile = pipeline.start(rs_config)
            profile.get_device().as_playback().set_real_time(False)
        except RuntimeError as exc:
            raise CameraFault(f"cannot play RealSense recording {path}: {exc}") from exc
        source = _PipelineSource(pipeline, profile, f"RealSense recording {path}")
        return cls(config, source, discard_queued=False)

    @classmethod
    def from_device(cls, config: CellConfig, device: Any, *, discard_queued: bool = True,
                    warmup_frames: int = 0) -> "D415Camera":
        """Stream an existing ``rs.device`` (a software_device, an ``rs.recorder`` around one, ...)."""
        cam, info = config.camera, _rs().camera_info
        name = device.get_info(info.name) if device.supports(info.name) else "device"
        source = _SensorSource(device, cam.intrinsics.width, cam.intrinsics.height, cam.fps, f"RealSense {name}")
        return cls(config, source, discard_queued=discard_queued, warmup_frames=warmup_frames)

    # -- capture
    def capture(self) -> Frame:
        """One aligned frame; with the temporal filter, the last of a few consecutive frames."""
        rs = _rs()
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
    def _check_serial(self, rs, source: _FrameSource) -> None:
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
