"""Where a D415's frames come from: a pipeline (a live device by serial number, or a recording), the sensors of
any ``rs.device`` started here (a ``software_device`` fed by a test, an ``rs.recorder`` wrapping one), or
``flgd emulate``'s camera feed pushed into a software device.  ``flgd.hardware.d415.D415Camera`` runs the same
capture code on each."""

from __future__ import annotations

import abc
import threading
import time
from typing import Any

from flgd.hardware import hardware_library
from flgd.hardware.camera import CameraFault

__all__ = ["FrameSource", "PipelineSource", "SensorSource", "EmulatorSource", "rs_library"]


def rs_library():
    return hardware_library("pyrealsense2")


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

class FrameSource(abc.ABC):
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


def _drain(queue: Any) -> None:
    """Drop every frame set ``queue`` (a pipeline or a syncer) holds, without waiting."""
    while queue.poll_for_frames():
        pass


def _has_depth_and_color(frames) -> bool:
    return bool(frames) and bool(frames.get_depth_frame()) and bool(frames.get_color_frame())


class PipelineSource(FrameSource):
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
        _drain(self._pipeline)

    @property
    def device(self):
        return self._profile.get_device()

    def depth_scale(self) -> float:
        return float(self.device.first_depth_sensor().get_depth_scale())

    def still_connected(self) -> bool:
        if not self._live:
            return True
        rs = rs_library()
        serials = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
        return self._serial in serials

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass  # already stopped (device gone): nothing left to release


class SensorSource(FrameSource):
    """Depth and colour sensors of an ``rs.device`` started into one ``rs.syncer``."""

    def __init__(self, device: Any, width: int, height: int, fps: int, description: str):
        rs = rs_library()
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
        _drain(self._syncer)

    @property
    def device(self):
        return self._device

    def depth_scale(self) -> float:
        # A recorder's or software sensor is not always typed as a depth_sensor; the option is always there.
        return float(self._depth_sensor.get_option(rs_library().option.depth_units))

    def close(self) -> None:
        self._device = None  # lets an rs.recorder be destroyed, which finalises its file
        sensors, self._sensors = self._sensors, []
        for sensor in sensors:
            for action in (sensor.stop, sensor.close):
                try:
                    action()
                except RuntimeError:
                    pass  # not started / already closed


class EmulatorSource(SensorSource):
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
