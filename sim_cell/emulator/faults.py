"""Faults on demand: what a robot cell does to its controller on a bad day, raised in the emulator by a command.

``flgd emulate`` listens on a Unix socket (``--faults PATH``) for one command per line and answers one JSON
line; ``flgd emulate --inject KIND [--during-motion]`` is its client.  The kinds:

``protective-stop``   the arm's protective stop (a collision): motion ends, the program stops, unlock after 5 s
``emergency-stop``    the emergency stop: motion ends, the arm is powered off until ``release-emergency-stop``
``release-emergency-stop``  the button pulled out again (the arm stays powered off: power on, brake release)
``drop-rtde``         every RTDE connection closed by the controller (a network glitch); clients may reconnect
``stop-script``       the control program stops (someone pressed stop on the pendant)
``gripper-trip``      the RG2's safety switch trips (``gripper-reset`` clears it)
``camera-stop``       the camera stops delivering frames (``camera-resume`` delivers again)
``power-on``          a person at the pendant powers the arm on and releases the brakes (after an e-stop)
``refill``            a person lays a new scene on the table (the daemon pauses on an empty one)
``status``            what has been raised so far, and the arm motions begun since the last fault

``--during-motion`` arms the fault instead of raising it at once: it is raised at a random instant of the
arm's next linear motion (after 0 to ``MAX_MOTION_DELAY`` s of motion), so that a fault lands mid-move as
on a real cell.  Faults that only make sense on the arm can be armed; the others are raised at once.
"""

from __future__ import annotations

import json
import logging
import os
import random
import socket
import threading
import time
from pathlib import Path
from typing import Any, Callable

from sim_cell.emulator.tcp_service import read_line

__all__ = ["FaultInjector", "FaultError", "KINDS", "ARMABLE", "inject", "MAX_MOTION_DELAY"]

log = logging.getLogger(__name__)

KINDS = ("protective-stop", "emergency-stop", "release-emergency-stop", "drop-rtde", "stop-script",
         "gripper-trip", "gripper-reset", "camera-stop", "camera-resume", "power-on", "refill", "status")
ARMABLE = frozenset({"protective-stop", "emergency-stop", "drop-rtde", "stop-script", "gripper-trip",
                     "camera-stop"})
MAX_MOTION_DELAY = 0.5   # seconds of arm motion before an armed fault is raised, at most
POLL = 0.002             # seconds between looks at the arm while a fault is armed
MAX_LINE = 256


class FaultError(ValueError):
    """A fault command that cannot be carried out (unknown kind, no such device)."""


class FaultInjector:
    """Raises the faults of the module docstring on the emulated devices (any of them may be None)."""

    def __init__(self, *, arm: Any = None, rtde: Any = None, gripper: Any = None, camera: Any = None,
                 rng: random.Random | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.arm = arm
        self.rtde = rtde
        self.gripper = gripper
        self.camera = camera
        self.rng = rng or random.Random()
        self.clock = clock
        self.raised: list[dict[str, Any]] = []   # every fault raised: kind, time, whether the arm was moving
        self._lock = threading.Lock()
        self._armed: list[threading.Thread] = []
        self._closing = threading.Event()
        self.motion_starts: list[float] = []   # when the arm began each motion (``watch``)
        self._was_moving = False
        self.world: Any = None

    def watch(self, world: Any) -> None:
        """Note the start of every arm motion on ``world``'s clock, so ``status`` can say whether the arm moved
        after the last fault (a daemon that went on commanding it would show here)."""
        self.world = world
        world.add_tick(self._note_motion)

    def _note_motion(self, dt: float) -> None:
        moving = bool(self.arm is not None and self.arm.moving)
        if moving and not self._was_moving:
            self.motion_starts.append(self.clock())
        self._was_moving = moving

    # ------------------------------------------------------------------ raising
    def _actions(self) -> dict[str, Callable[[], None]]:
        return {
            "protective-stop": lambda: self._need(self.arm, "arm").protective_stop("protective stop injected"),
            "emergency-stop": lambda: self._need(self.arm, "arm").emergency_stop(),
            "release-emergency-stop": lambda: self._need(self.arm, "arm").release_emergency_stop(),
            "drop-rtde": lambda: self._need(self.rtde, "RTDE server").drop_clients(),
            "stop-script": lambda: self._need(self.arm, "arm").stop_program(),
            "gripper-trip": lambda: self._need(self.gripper, "RG2").trip_safety(),
            "gripper-reset": lambda: self._need(self.gripper, "RG2").reset_safety(),
            "camera-stop": lambda: self._need(self.camera, "camera").stop_frames(),
            "camera-resume": lambda: self._need(self.camera, "camera").resume_frames(),
            "power-on": lambda: self._power_on(self._need(self.arm, "arm")),
            "refill": self._refill,
        }

    def _refill(self) -> None:
        self._need(self.world, "world").cell.reset_scene()
        if self.camera is not None:
            self.camera.invalidate()

    @staticmethod
    def _power_on(arm: Any) -> None:
        arm.power_on()
        arm.brake_release()

    @staticmethod
    def _need(device: Any, name: str) -> Any:
        if device is None:
            raise FaultError(f"this emulator has no {name}")
        return device

    def raise_now(self, kind: str) -> dict[str, Any]:
        """Raise ``kind`` at once; the record of it (kind, time, whether the arm was moving)."""
        actions = self._actions()
        if kind not in actions:
            raise FaultError(f"unknown fault {kind!r}; known: {', '.join(KINDS)}")
        moving = bool(self.arm is not None and self.arm.moving)
        actions[kind]()
        record = {"kind": kind, "time": self.clock(), "during_motion": moving}
        with self._lock:
            self.raised.append(record)
        log.info("fault raised: %s%s", kind, " (arm moving)" if moving else "")
        return record

    def arm_for_motion(self, kind: str, timeout: float = 120.0) -> float:
        """Raise ``kind`` after a random 0..MAX_MOTION_DELAY s of the arm's motion; the delay drawn.

        The motion time is counted only while the arm moves, so a fault never lands between moves; a fault
        not raised within ``timeout`` s (the arm never moved) is dropped with a log line."""
        if kind not in ARMABLE:
            raise FaultError(f"{kind!r} cannot wait for a motion; armable: {', '.join(sorted(ARMABLE))}")
        self._need(self.arm, "arm")
        self._actions()  # an unknown device is refused now, not in the thread
        delay = self.rng.uniform(0.0, MAX_MOTION_DELAY)
        thread = threading.Thread(target=self._wait_and_raise, args=(kind, delay, timeout),
                                  name=f"fault {kind}", daemon=True)
        with self._lock:
            self._armed = [t for t in self._armed if t.is_alive()] + [thread]
        thread.start()
        return delay

    def _wait_and_raise(self, kind: str, delay: float, timeout: float) -> None:
        deadline = self.clock() + timeout
        moved, last = 0.0, self.clock()
        while not self._closing.is_set():
            now = self.clock()
            if self.arm.moving:
                moved += now - last
                if moved >= delay:
                    try:
                        self.raise_now(kind)
                    except Exception as exc:  # the device went away: say so, never kill the emulator
                        log.warning("armed fault %s not raised: %s", kind, exc)
                    return
            last = now
            if now > deadline:
                log.warning("armed fault %s dropped: the arm did not move for %.0f s", kind, timeout)
                return
            time.sleep(POLL)

    @property
    def armed(self) -> int:
        with self._lock:
            return sum(t.is_alive() for t in self._armed)

    def status(self) -> dict[str, Any]:
        """The faults raised, those armed, the arm motions begun since the last fault, and (when watching a
        world) how fast its clock ran."""
        with self._lock:
            last = self.raised[-1]["time"] if self.raised else None
            since = None if last is None else sum(1 for t in list(self.motion_starts) if t > last)
            report = {"raised": list(self.raised), "armed": sum(t.is_alive() for t in self._armed),
                      "motions_since_last_fault": since}
        if self.world is not None:
            report["clock"] = self.world.clock_report()
        return report

    def command(self, line: str) -> dict[str, Any]:
        """One command line of the control socket: ``KIND [--during-motion]``; the reply object."""
        words = line.split()
        if not words:
            raise FaultError("an empty command; send a fault kind, e.g. protective-stop")
        kind, flags = words[0], words[1:]
        if kind == "status":
            return {"ok": True, **self.status()}
        if any(f != "--during-motion" for f in flags):
            raise FaultError(f"unknown option {' '.join(flags)!r}; the only option is --during-motion")
        if flags:
            return {"ok": True, "armed": kind, "after_motion_s": round(self.arm_for_motion(kind), 3)}
        return {"ok": True, "raised": self.raise_now(kind)}

    def close(self) -> None:
        self._closing.set()
        with self._lock:
            threads = list(self._armed)
        for t in threads:
            t.join(timeout=2.0)


class FaultSocket:
    """The Unix socket ``flgd emulate --inject`` talks to (module docstring), one connection at a time."""

    def __init__(self, injector: FaultInjector, path: str | os.PathLike) -> None:
        self.injector = injector
        self.path = Path(path)
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()

    def start(self) -> None:
        if self.path.exists():
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                probe.connect(str(self.path))
            except OSError:
                self.path.unlink()  # left by an emulator that was killed
            else:
                probe.close()
                raise OSError(f"fault socket {self.path}: another flgd emulate is listening there")
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.bind(str(self.path))
        self._sock.listen(4)
        self._sock.settimeout(0.2)
        self._thread = threading.Thread(target=self._serve, name="fault socket", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._closing.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(5.0)
                try:
                    data = read_line(conn, MAX_LINE)
                    try:
                        reply = self.injector.command(data.split(b"\n", 1)[0].decode("utf-8", "replace"))
                    except FaultError as exc:
                        reply = {"ok": False, "error": str(exc)}
                    except Exception as exc:  # a device refused: the emulator keeps running
                        log.warning("fault command failed: %s", exc)
                        reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
                    conn.sendall((json.dumps(reply) + "\n").encode())
                except OSError:
                    continue

    def close(self) -> None:
        self._closing.set()
        if self._sock is not None:
            self._sock.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass


def inject(path: str | os.PathLike, command: str, timeout: float = 10.0) -> dict[str, Any]:
    """Send one fault command to a running ``flgd emulate``; its reply (OSError when none listens)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(str(path))
        s.sendall(command.encode() + b"\n")
        data = read_line(s)
    return json.loads(data.decode() or "{}")
