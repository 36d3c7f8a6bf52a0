"""What failed in this scene, so that the agent does not choose it again (design notes: "Not repeating what fails").

A greedy policy whose inputs did not change makes the same choice again: after a
failed grasp the scene barely changed, so the same grasp -- or one a few
millimetres away -- wins the argmax again.  The paper's anti-repeat rule only
excludes the identical pixel.  This memory suppresses a *region*: a disk of
``exploration.failure_radius`` around the failed action's pixel, in that
action's channel (grasp or move), at its rotation and ``failure_rotations``
steps either side (for a grasp also the twin rotation half a turn on, which
closes the two fingers the same way).

With ``exploration.failure_retries`` = k a spot is suppressed only at its
(k+1)-th failure: the first failures leave a *pending* region (shown, not
enforced), and a failure inside a pending region of the same channel and
rotations makes it count.  A failed grasp often nudges its object, and one more
try at nearly the same spot then succeeds; the retries allow that and still
stop the loop.

A region, pending or suppressed, is released when the heightmap changes inside it (more
than ``RELEASE_SHARE`` of its pixels moved by more than ``rewards.delta``, a
count that single noise pixels cannot reach) -- something moved there, so the
old failure no longer says anything -- and everything is released when a new
scene starts.

The escalation ladder reads its counts from here: actions since the last
successful grasp (``since_success``) and the most recent failed grasp
(``last_failed_grasp``), which the two-failures move aims at.  The memory is
state of the cell's episode, never of the network: the learner's targets do
not see it.
"""

from __future__ import annotations

from typing import Any

from dataclasses import dataclass

import numpy as np

from flgd.actions import Action

__all__ = ["Suppression", "FailureMemory", "RELEASE_SHARE"]

# share of a suppressed disk's pixels whose height must change by more than rewards.delta to release it
RELEASE_SHARE = 0.1


@dataclass(frozen=True)
class Suppression:
    """One failed action's region: channel (0 grasp, 1 move), pixel, rotation, and the heights it was judged on."""

    channel: int
    row: int
    col: int
    rotation: int
    kind: str                 # grasp / push / shift as executed
    heights: np.ndarray       # float32, the disk's heights after the failure (for the release test)
    failures: int = 1         # failures counted in this region


class FailureMemory:
    """Suppressed regions of this scene, and the ladder's counts.

    ``radius_px`` is the disk radius in pixels, ``rotation_span`` the steps either
    side, ``delta`` the height change (m) that counts a pixel as changed.  The
    heightmap shape is the one the failures were recorded on.
    """

    def __init__(self, rotations: int, radius_px: float, rotation_span: int, delta: float, retries: int = 0) -> None:
        self.rotations = int(rotations)
        self.retries = int(retries)
        self.shape: tuple[int, int] = (0, 0)
        self.radius_px = float(radius_px)
        self.rotation_span = int(rotation_span)
        self.delta = float(delta)
        self.entries: list[Suppression] = []
        self.since_success = 0             # actions since the last successful grasp in this scene
        self.last_failed_grasp: Suppression | None = None
        self.released = 0                  # regions released by a change, this scene
        r = int(np.ceil(self.radius_px))
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        self._disk = (yy * yy + xx * xx) <= self.radius_px * self.radius_px
        self._r = r

    # ------------------------------------------------------------------ geometry
    def _window(self, row: int, col: int) -> tuple[slice, slice, np.ndarray]:
        """The heightmap slices of the disk at (row, col), clipped, and the disk's part inside them."""
        h, w = self.shape
        r = self._r
        r0, r1, c0, c1 = max(0, row - r), min(h, row + r + 1), max(0, col - r), min(w, col + r + 1)
        disk = self._disk[r0 - (row - r):r1 - (row - r), c0 - (col - r):c1 - (col - r)]
        return slice(r0, r1), slice(c0, c1), disk

    def _rotations_of(self, s: Suppression) -> set[int]:
        rots = {(s.rotation + k) % self.rotations for k in range(-self.rotation_span, self.rotation_span + 1)}
        if s.channel == 0 and self.rotations % 2 == 0:  # a grasp and its twin half a turn on are one grasp
            rots |= {(r + self.rotations // 2) % self.rotations for r in rots}
        return rots

    # ------------------------------------------------------------------ recording
    def record(self, action: Action, kind: str, success: bool, height_after: np.ndarray | None) -> None:
        """Feed an action's outcome: a failure adds a region (judged on ``height_after``), a successful
        grasp resets the ladder's count.  A move that changed the scene is no failure and adds nothing."""
        if action.primitive == "grasp" and success:
            self.since_success = 0
            self.last_failed_grasp = None
            return
        self.since_success += 1
        if success or height_after is None:
            return
        height = np.asarray(height_after, dtype=np.float32)
        if height.shape != self.shape:  # a heightmap of another size: the old regions mean nothing on it
            self.entries, self.last_failed_grasp, self.shape = [], None, (int(height.shape[0]), int(height.shape[1]))
        rows, cols, disk = self._window(action.row, action.col)
        heights = np.where(disk, height[rows, cols], np.nan).astype(np.float32)
        failures = 1
        for i, old in enumerate(self.entries):  # a failure where one already failed: that region counts one more
            if old.channel == action.channel and action.rotation in self._rotations_of(old) and \
                    (old.row - action.row) ** 2 + (old.col - action.col) ** 2 <= self.radius_px ** 2:
                failures = old.failures + 1
                del self.entries[i]
                break
        entry = Suppression(channel=action.channel, row=int(action.row), col=int(action.col),
                            rotation=int(action.rotation), kind=kind, heights=heights, failures=failures)
        self.entries.append(entry)
        if action.channel == 0:
            self.last_failed_grasp = entry

    def release_changed(self, height: np.ndarray) -> int:
        """Drop the regions where the heightmap changed since their failure; returns how many were dropped."""
        if not self.entries:
            return 0
        height = np.nan_to_num(np.asarray(height, dtype=np.float32), nan=0.0)
        if height.shape != self.shape:
            dropped = len(self.entries)
            self.clear()
            return dropped
        kept: list[Suppression] = []
        for s in self.entries:
            rows, cols, disk = self._window(s.row, s.col)
            diff = np.abs(height[rows, cols] - np.nan_to_num(s.heights, nan=0.0))
            changed = int(np.count_nonzero(disk & (diff > self.delta)))
            if changed > RELEASE_SHARE * int(disk.sum()):
                self.released += 1
                if self.last_failed_grasp is s:
                    self.last_failed_grasp = None
            else:
                kept.append(s)
        dropped = len(self.entries) - len(kept)
        self.entries = kept
        return dropped

    def clear(self) -> None:
        """A new scene (or a fresh start after the cell declared itself stuck): forget everything."""
        self.entries = []
        self.since_success = 0
        self.last_failed_grasp = None
        self.released = 0

    # ------------------------------------------------------------------ reading
    @property
    def enforced(self) -> list[Suppression]:
        """The regions that failed more than ``retries`` times: the ones that forbid actions."""
        return [s for s in self.entries if s.failures > self.retries]

    def suppressed(self) -> np.ndarray:
        """bool [R,2,H,W]: True where the memory forbids an action."""
        out = np.zeros((self.rotations, 2) + self.shape, dtype=bool)
        for s in self.enforced:
            rows, cols, disk = self._window(s.row, s.col)
            for rot in self._rotations_of(s):
                out[rot, s.channel, rows, cols] |= disk
        return out

    @staticmethod
    def near(row: int, col: int, reach_px: float, shape: tuple[int, int]) -> np.ndarray:
        """bool ``shape``: pixels within ``reach_px`` of (row, col) (e.g. where a move changes a failed region)."""
        h, w = shape
        yy, xx = np.ogrid[:h, :w]
        within: np.ndarray = (yy - row) ** 2 + (xx - col) ** 2 <= reach_px * reach_px
        return within

    def footprint(self) -> np.ndarray:
        """uint8 [H,W]: 1 where any region is suppressed, in any channel or rotation (for pictures)."""
        out = np.zeros(self.shape, dtype=np.uint8)
        for s in self.enforced:
            rows, cols, disk = self._window(s.row, s.col)
            out[rows, cols] |= disk.astype(np.uint8)
        return out

    def status(self) -> dict[str, Any]:
        """What a person sees: regions held, released, actions since the last pick."""
        return {"suppressed_regions": len(self.enforced), "pending_regions": len(self.entries) - len(self.enforced),
                "released_regions": self.released,
                "actions_since_success": self.since_success,
                "regions": [{"kind": s.kind, "row": s.row, "col": s.col, "rotation": s.rotation,
                             "failures": s.failures} for s in self.entries]}
