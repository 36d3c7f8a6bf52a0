"""The emulator's one physics world: a SimCell, the lock every pybullet call takes, and the clock that steps it.

The emulated devices (arm, gripper, camera) share one pybullet client, and
pybullet is not thread-safe, so every call into it -- arm motion, finger motion,
rendering, a scene reset -- happens under ``EmulatorWorld.lock``.  The lock is
the SimCell's own (``Cell._lock``): the cell's public methods (``capture``,
``reset_scene`` ...) already take it, so the devices and the cell never step
the world at the same time and no second lock can be taken in the wrong order.

The world runs on its own clock thread (:meth:`start`): physics steps of
``config.sim.time_step`` paced to real time divided by ``time_scale`` (2 =
twice as fast as real time); on a machine too busy to keep up, simulated time
slows down instead of jumping ahead.  Simulated time is the emulated
controller's clock (its RTDE ``timestamp``): the daemon times moves on it, and
a cycle's ``cell_time`` is counted on it, so they are the arm's times whatever
the load.  :meth:`clock_report` says how fast that clock actually ran (the
real-time factor); a clock that falls below half the asked-for speed is logged
as a warning once a minute.  Before each step the registered tick callbacks
run under the lock (the arm's controller, the fingers), so a device never
steps the world itself.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Callable

import pybullet as p

from flgd.config import CellConfig
from sim_cell.cell import SimCell
from sim_cell.stability import Unstable
from sim_cell.world import BIN_HALF_SIZE

__all__ = ["EmulatorWorld", "TickCallback", "slow_clock_warning", "in_bin", "BIN_HALF_SIZE"]

log = logging.getLogger(__name__)

TickCallback = Callable[[float], None]   # called with the physics time step (s) before each step
BIN_CHECK_STEPS = 24                     # physics steps between looks into the bin (0.1 s at 240 Hz)
MAX_BURST_STEPS = 2                      # steps taken at once when behind: the RTDE stream gets its turn between
MAX_LAG_STEPS = 24                       # steps behind real time before the clock gives up catching up
RATE_WINDOW_S = 10.0                     # wall seconds over which the recent real-time factor is measured
SLOW_WARNING_EVERY_S = 60.0              # at most one "running slow" warning this often


def slow_clock_warning(samples: list[tuple[float, float]], time_scale: float) -> str | None:
    """What to warn about when (wall, sim) samples spanning most of ``RATE_WINDOW_S`` show the simulated clock at
    less than half the asked-for speed; None otherwise."""
    if len(samples) < 2:
        return None
    wall, sim = samples[-1][0] - samples[0][0], samples[-1][1] - samples[0][1]
    if wall < 0.9 * RATE_WINDOW_S or sim / wall >= 0.5 * time_scale:
        return None
    return (f"emulator: the simulated clock runs at {sim / wall:.2f}x real time (asked for {time_scale:g}x): the "
            f"PC is too busy for it; moves and cycle times stay on the emulator's clock, but waits timed on the "
            f"wall clock (gripper, camera) may run out")


class EmulatorWorld:
    """One SimCell, its lock and the physics clock that steps it for the emulated devices."""

    def __init__(self, config: CellConfig, *, time_scale: float = 1.0):
        """``config.robot.place`` stands over a bin (as on a cell): what comes to rest inside its square leaves the
        table, so placed objects do not pile up beside the workspace."""
        if time_scale <= 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale!r}")
        self.config = config
        self.cell = SimCell(config)
        self.lock: threading.RLock = self.cell._lock
        self.dt = float(config.sim.time_step)
        self.time_scale = float(time_scale)
        self._ticks: list[TickCallback] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.steps = 0
        self._started: tuple[float, float] | None = None          # (wall, sim) when the clock started
        self._samples: collections.deque[tuple[float, float]] = collections.deque()   # (wall, sim), last window
        self._warned_at = float("-inf")

    # ------------------------------------------------------------------ devices
    def add_tick(self, callback: TickCallback) -> None:
        """Run ``callback(dt)`` under the lock before every physics step (a device's controller)."""
        with self.lock:
            self._ticks.append(callback)

    def remove_tick(self, callback: TickCallback) -> None:
        with self.lock:
            if callback in self._ticks:
                self._ticks.remove(callback)

    @property
    def sim_time(self) -> float:
        return self.cell.sim_time

    def step(self, n: int = 1) -> None:
        """``n`` physics steps now (tick callbacks first); for the clock thread and for tests."""
        with self.lock:
            for _ in range(n):
                for tick in list(self._ticks):
                    tick(self.dt)
                try:
                    self.cell._world.step(1)
                except Unstable as exc:
                    log.warning("emulator: unstable physics (%s): the scene is reset", exc)
                    self.cell._world.stats["unstable_resets"] += 1
                    self.cell.reset_scene()
                self.steps += 1
                if self.steps % BIN_CHECK_STEPS == 0:
                    self._empty_bin()

    def _empty_bin(self) -> None:
        """Take out what lies in the bin under the place pose and touches nothing of the arm (lock held)."""
        world, ws = self.cell._world, self.config.workspace
        px, py = self.config.robot.place.position[:2]
        for body in in_bin(world.client, list(world.objects), world.robot.body, (px, py), BIN_HALF_SIZE):
            (x, y, _z), _ = p.getBasePositionAndOrientation(body, physicsClientId=world.client)
            if not (ws.x[0] <= x <= ws.x[1] and ws.y[0] <= y <= ws.y[1]):   # a place over the workspace has no bin
                world.remove(body, "grasped_out")

    # ------------------------------------------------------------------ clock
    def start(self) -> None:
        """Start the clock thread (idempotent)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="emulator-physics", daemon=True)
        self._thread.start()

    def clock_report(self) -> dict[str, float | None]:
        """How fast the simulated clock ran: since the clock started and over the last ``RATE_WINDOW_S``
        (simulated seconds per wall second; ``time_scale`` is what was asked for)."""
        now, sim = time.monotonic(), self.sim_time
        started = self._started
        samples = list(self._samples)
        overall = (sim - started[1]) / (now - started[0]) if started and now > started[0] else None
        recent = ((sim - samples[0][1]) / (now - samples[0][0])
                  if samples and now - samples[0][0] > 0.5 else overall)
        return {"time_scale": self.time_scale, "sim_s": sim - started[1] if started else 0.0,
                "wall_s": now - started[0] if started else 0.0, "real_time_factor": overall,
                "recent_real_time_factor": recent}

    def _sample_rate(self, now: float) -> None:
        """Keep the window of (wall, sim) samples; warn when the clock runs at less than half its speed."""
        if self._samples and now - self._samples[-1][0] < 0.5:
            return
        self._samples.append((now, self.sim_time))
        while now - self._samples[0][0] > RATE_WINDOW_S:
            self._samples.popleft()
        warning = slow_clock_warning(list(self._samples), self.time_scale)
        if warning and now - self._warned_at >= SLOW_WARNING_EVERY_S:
            self._warned_at = now
            log.warning("%s", warning)

    def _run(self) -> None:
        period = self.dt / self.time_scale
        next_at = time.monotonic()
        self._started = (next_at, self.sim_time)
        self._samples.clear()
        while not self._stop.is_set():
            now = time.monotonic()
            self._sample_rate(now)
            if now < next_at:
                self._stop.wait(next_at - now)
                continue
            # a machine too busy to keep up slows the simulated time down rather than jumping it forward: a real
            # controller publishes every 2 ms, so the arm never moves far between two states a client can see
            due = min(int((now - next_at) / period) + 1, MAX_BURST_STEPS)
            try:
                self.step(due)
            except Exception:  # a device's bug must not stop the clock of the others
                log.exception("emulator: a physics tick failed")
            next_at += due * period
            if time.monotonic() - next_at > MAX_LAG_STEPS * period:
                next_at = time.monotonic()   # slower than real time: do not try to catch up for ever
            time.sleep(0)   # let the servers' threads run between bursts

    def close(self) -> None:
        """Stop the clock and close the cell; safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.cell.close()

    def __enter__(self) -> "EmulatorWorld":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def in_bin(client: int, bodies: list[int], robot: int, centre: tuple[float, float], half: float) -> list[int]:
    """Of ``bodies``, those whose centre lies within ``half`` (m) of ``centre`` (x, y) and that touch nothing of
    the robot (an object still in the gripper over the bin has not been let go)."""
    out = []
    for body in bodies:
        (x, y, _z), _ = p.getBasePositionAndOrientation(body, physicsClientId=client)
        if abs(x - centre[0]) <= half and abs(y - centre[1]) <= half and \
                not p.getContactPoints(bodyA=body, bodyB=robot, physicsClientId=client):
            out.append(body)
    return out
