"""Calibration watch: is the table still where ``camera.pose`` says the camera sees it?

Why: a camera knocked 1.6 cm and 1.6 degrees from its calibrated pose takes the shipped policy from 91 % to under
30 % grasp success in every scene, and nothing faults: the daemon only saw a falling rate.  Yet every frame shows
the table, and perception places it with the configured pose: with a correct pose the table is the flat plane
``workspace.z[0]``.  Its plane fitted in each frame, outside the objects, gives the tilt and the height offset of
the camera's error, which is the part of it that matters most to a top-down grasp.

What the table cannot show: a camera slid parallel to the table, or turned about the vertical, sees the same flat
table at the same height.  Those errors move objects sideways in the heightmap and are left to the grasp rate.

Why the frame's points and not the heightmap: the heightmap keeps the highest point of each cell (on a noisy depth
camera the table reads ~2 mm high) and clamps everything below the table to 0, so a camera raised by 1 cm gives a
perfectly flat heightmap at 0.  The points are projected here as perception projects them (same intrinsics, depth
scale and pose), without the maximum and the clamp.  Cells without a reading (the heightmap's ``unknown``) have no
point and so no say; objects are left out with clutter's object filter, applied to heights above the fitted plane.

The contact depths of guarded grasp descents are not used: a descent is planned ``robot.grasp_depth`` into the
surface between the fingers, and stops short where a finger meets something, mostly a neighbouring object.  Where
that is says nothing about the table until it is modelled per finger against the heightmap, which this watch
does not do.

Frames are noisy and scenes change, so a drift is reported only when the median of the newest ``window``
estimates stays beyond a limit for ``confirm_frames`` frames, and cleared only when it stays within
``CLEAR_FRACTION`` of both limits as long: one event per episode, never a flapping one.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from flgd.clutter import min_region_pixels, object_mask
from flgd.config import CalibrationWatchConfig, RewardConfig, WorkspaceConfig

if TYPE_CHECKING:
    from flgd.cell import Frame

__all__ = ["TablePlane", "WatchEvent", "CalibrationWatch", "table_points", "fit_table_plane", "REMEDY",
           "CLEAR_FRACTION"]

REMEDY = "flgd calibrate"
# A drift is cleared when the estimate is back within this share of both limits (hysteresis: no flapping).
CLEAR_FRACTION = 0.8
# Every POINT_STRIDE-th pixel of every POINT_STRIDE-th row: ~40,000 table points at 640 x 480, plenty for 3 numbers.
POINT_STRIDE = 2
# Points this far below the table are still considered (a camera raised by up to 10 cm); lower ones are not table.
LOWEST_TABLE = -0.10
# Coarse first fit: the workspace in COARSE_BLOCKS x COARSE_BLOCKS blocks, each represented by a low quantile of its
# points (objects stand above the table, so a block's low points are table unless an object covers nearly all of it).
COARSE_BLOCKS = 8
COARSE_QUANTILE = 0.2
MIN_BLOCK_POINTS = 30
# Pixels the object mask is widened by: object edges, mixed pixels and the shadow beside an object are not table.
OBJECT_MARGIN_PX = 4
# Points within this distance of the coarse plane (outside objects) start the fine fit; then 3 robust sigmas.
TABLE_BAND = 0.008
MIN_SIGMA = 0.0005
FINE_ITERATIONS = 4
# A frame is judged only when its table points cover at least this share of the workspace's extent in x and in y
# (a tilt measured on one corner is a guess) and there are at least MIN_TABLE_POINTS of them.
MIN_SPREAD = 0.5
MIN_TABLE_POINTS = 2000


@dataclass(frozen=True)
class TablePlane:
    """The table in one frame: z = slope_x * (x - xc) + slope_y * (y - yc) + offset, heights above workspace.z[0],
    (xc, yc) the workspace centre."""

    slope_x: float
    slope_y: float
    offset: float       # m: the table's height at the workspace centre (0 for a calibrated camera)
    points: int         # table points the fit rests on
    rms: float          # m: their scatter about the plane

    @property
    def tilt_degrees(self) -> float:
        return math.degrees(math.atan(math.hypot(self.slope_x, self.slope_y)))


@dataclass(frozen=True)
class WatchEvent:
    """A change of the watch's verdict: ``kind`` is ``calibration_drift`` (beyond a limit) or
    ``calibration_ok`` (back within); ``message`` is for the event log."""

    kind: str
    message: str


def table_points(depth: np.ndarray, depth_scale: float, intrinsics: np.ndarray, camera_pose: np.ndarray,
                 workspace: WorkspaceConfig, depth_range: tuple[float, float] = (0.0, math.inf),
                 stride: int = POINT_STRIDE) -> np.ndarray:
    """N x 3 base-frame points (x, y, height above workspace.z[0]) of the valid depth pixels over the workspace.

    As ``flgd.perception.make_heightmaps`` projects them, but every ``stride``-th pixel, unclamped, and from
    ``LOWEST_TABLE`` below the table up to the top of the workspace.
    """
    d = np.asarray(depth)[::stride, ::stride].astype(np.float64) * float(depth_scale)
    k = np.asarray(intrinsics, dtype=np.float64)
    pose = np.asarray(camera_pose, dtype=np.float64)
    h, w = np.shape(depth)
    v, u = np.meshgrid(np.arange(0, h, stride, dtype=np.float64), np.arange(0, w, stride, dtype=np.float64),
                       indexing="ij")
    ok = (d > max(depth_range[0], 0.0)) & (d < depth_range[1])
    d = d[ok]
    cx, cy = (u[ok] - k[0, 2]) / k[0, 0] * d, (v[ok] - k[1, 2]) / k[1, 1] * d
    rot, t = pose[:3, :3], pose[:3, 3]
    pts = np.empty((d.size, 3))
    for i in range(3):  # the rotation row by row (no BLAS threads, as in _lstsq_plane)
        pts[:, i] = rot[i, 0] * cx + rot[i, 1] * cy + rot[i, 2] * d + t[i]
    pts[:, 2] -= workspace.table_z
    keep = ((pts[:, 0] >= workspace.x[0]) & (pts[:, 0] < workspace.x[1]) & (pts[:, 1] >= workspace.y[0])
            & (pts[:, 1] < workspace.y[1]) & (pts[:, 2] >= LOWEST_TABLE) & (pts[:, 2] <= workspace.z[1] - workspace.z[0]))
    return pts[keep]


def _lstsq_plane(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(slope_x, slope_y, offset) of z = a x + b y + c by least squares (normal equations: x and y are centred on
    the workspace, so the 3 x 3 system is well conditioned)."""
    # elementwise sums, not BLAS dot products: those spin up threads that a busy cell PC makes slow
    sx, sy, sxy = float(x.sum()), float(y.sum()), float((x * y).sum())
    m = np.array([[float((x * x).sum()), sxy, sx], [sxy, float((y * y).sum()), sy], [sx, sy, float(x.size)]])
    return np.linalg.solve(m, np.array([float((x * z).sum()), float((y * z).sum()), float(z.sum())]))


def _coarse_plane(x: np.ndarray, y: np.ndarray, z: np.ndarray, workspace: WorkspaceConfig) -> np.ndarray | None:
    """A first plane through the blocks' low quantiles, blocks far above it (covered by objects) dropped."""
    bx = np.clip(((x + (workspace.x[1] - workspace.x[0]) / 2) / (workspace.x[1] - workspace.x[0])
                  * COARSE_BLOCKS).astype(np.int64), 0, COARSE_BLOCKS - 1)
    by = np.clip(((y + (workspace.y[1] - workspace.y[0]) / 2) / (workspace.y[1] - workspace.y[0])
                  * COARSE_BLOCKS).astype(np.int64), 0, COARSE_BLOCKS - 1)
    block = by * COARSE_BLOCKS + bx
    order = np.lexsort((z, block))
    counts = np.bincount(block, minlength=COARSE_BLOCKS * COARSE_BLOCKS)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    full = np.flatnonzero(counts >= MIN_BLOCK_POINTS)
    if full.size < 6:
        return None
    pick = order[starts[full] + (COARSE_QUANTILE * counts[full]).astype(np.int64)]
    bxs, bys, bzs = x[pick], y[pick], z[pick]
    keep = np.ones(full.size, dtype=bool)
    coef = _lstsq_plane(bxs, bys, bzs)
    for _ in range(3):
        r = bzs - (coef[0] * bxs + coef[1] * bys + coef[2])
        keep = r < TABLE_BAND / 2  # objects are above the table: only high blocks are dropped
        if keep.sum() < 6:
            return None
        coef = _lstsq_plane(bxs[keep], bys[keep], bzs[keep])
    return coef


def fit_table_plane(points: np.ndarray, workspace: WorkspaceConfig, rewards: RewardConfig) -> TablePlane | None:
    """The table's plane among ``points`` (``table_points``), objects left out; None when too little table shows.

    A coarse plane through the blocks' low points; heights above it are put through clutter's object filter
    (``rewards.min_height``, ``rewards.min_object_area``) and the objects, widened by ``OBJECT_MARGIN_PX``, are
    dropped; the rest near the plane are fitted by least squares, rejecting points beyond 3 robust sigmas.
    """
    if len(points) < MIN_TABLE_POINTS:
        return None
    xc, yc = (workspace.x[0] + workspace.x[1]) / 2, (workspace.y[0] + workspace.y[1]) / 2
    x, y, z = points[:, 0] - xc, points[:, 1] - yc, points[:, 2]
    coef = _coarse_plane(x, y, z, workspace)
    if coef is None:
        return None
    rows, cols = workspace.shape
    res = workspace.resolution
    r_px = np.clip(((points[:, 1] - workspace.y[0]) / res).astype(np.int64), 0, rows - 1)
    c_px = np.clip(((points[:, 0] - workspace.x[0]) / res).astype(np.int64), 0, cols - 1)
    cell = r_px * cols + c_px
    above = z - (coef[0] * x + coef[1] * y + coef[2])
    relief = np.zeros(rows * cols, dtype=np.float32)
    np.maximum.at(relief, cell, above.astype(np.float32))
    objects = object_mask(relief.reshape(rows, cols), rewards.min_height, min_region_pixels(rewards, res))
    if OBJECT_MARGIN_PX > 0:
        objects = cv2.dilate(objects, np.ones((2 * OBJECT_MARGIN_PX + 1,) * 2, np.uint8))
    keep = (objects.reshape(-1)[cell] == 0) & (np.abs(above) < TABLE_BAND)
    for _ in range(FINE_ITERATIONS):
        if keep.sum() < MIN_TABLE_POINTS:
            return None
        coef = _lstsq_plane(x[keep], y[keep], z[keep])
        r = z - (coef[0] * x + coef[1] * y + coef[2])
        sigma = max(1.4826 * float(np.median(np.abs(r[keep]))), MIN_SIGMA)
        keep &= np.abs(r) < 3.0 * sigma
    n = int(keep.sum())
    if n < MIN_TABLE_POINTS:
        return None
    xs, ys = x[keep], y[keep]
    spread_x = float(np.percentile(xs, 95) - np.percentile(xs, 5)) / (workspace.x[1] - workspace.x[0])
    spread_y = float(np.percentile(ys, 95) - np.percentile(ys, 5)) / (workspace.y[1] - workspace.y[0])
    if min(spread_x, spread_y) < MIN_SPREAD:
        return None
    r = z[keep] - (coef[0] * xs + coef[1] * ys + coef[2])
    return TablePlane(slope_x=float(coef[0]), slope_y=float(coef[1]), offset=float(coef[2]), points=n,
                      rms=float(np.sqrt(np.mean(r * r))))


class CalibrationWatch:
    """Judges each frame's table plane and reports when the camera has moved (``observe``), and when it is back.

    Cell-independent: frames in, estimates and events out; the caller records the events.
    """

    def __init__(self, config: CalibrationWatchConfig, workspace: WorkspaceConfig, rewards: RewardConfig,
                 depth_range: tuple[float, float] = (0.0, math.inf)):
        self.config = config
        self.workspace = workspace
        self.rewards = rewards
        self.depth_range = depth_range
        self._recent: deque[TablePlane] = deque(maxlen=config.window)
        self.drift = False              # the current verdict: the camera has moved
        self.since: float | None = None  # when the verdict was reached (None: never drifted)
        self._streak = 0                # consecutive estimates that point to the other verdict
        self.frames = 0                 # frames with enough table to judge
        self.unjudged = 0               # frames with too little table (covered, dark, arm in view)
        # (tilt deg, offset m) as of the newest frame: replaced whole, so status() from another thread (a control
        # connection, a scrape) never iterates the window while the run loop appends to it
        self.latest: tuple[float, float] | None = None

    def observe_frame(self, frame: Frame, now: float | None = None) -> WatchEvent | None:
        """Fit the table in a ``flgd.cell.Frame`` and judge it (``observe``)."""
        points = table_points(frame.depth, frame.depth_scale, frame.intrinsics, frame.camera_pose, self.workspace,
                              self.depth_range)
        return self.observe(fit_table_plane(points, self.workspace, self.rewards), now)

    def observe(self, plane: TablePlane | None, now: float | None = None) -> WatchEvent | None:
        """Add one frame's plane (None: too little table to judge) and return the event of a changed verdict."""
        if plane is None:
            self.unjudged += 1
            return None
        self.frames += 1
        self._recent.append(plane)
        self.latest = tilt, offset = self.estimate()  # type: ignore[misc]
        cfg = self.config
        tilt_limit, offset_limit = cfg.max_tilt_degrees, cfg.max_offset_mm / 1000.0
        if self.drift:
            turning = tilt <= CLEAR_FRACTION * tilt_limit and abs(offset) <= CLEAR_FRACTION * offset_limit
        else:
            turning = tilt > tilt_limit or abs(offset) > offset_limit
        self._streak = self._streak + 1 if turning else 0
        if self._streak < cfg.confirm_frames:
            return None
        self._streak = 0
        self.drift = not self.drift
        self.since = time.time() if now is None else now
        seen = (f"the table is seen tilted {tilt:.2f} deg (limit {tilt_limit:g}) and {1000 * offset:+.1f} mm from "
                f"the table height at the workspace centre (limit {cfg.max_offset_mm:g} mm), median of the last "
                f"{len(self._recent)} frames")
        if self.drift:
            return WatchEvent("calibration_drift", f"{seen}: the camera has moved from camera.pose; grasps will "
                                                   f"miss. Remedy: {REMEDY} (docs/real-cell.md, Calibration)")
        return WatchEvent("calibration_ok", f"{seen}: back within the limits")

    def estimate(self) -> tuple[float, float] | None:
        """(tilt in degrees, offset in m) of the median plane of the newest ``window`` frames; None before one."""
        if not self._recent:
            return None
        sx = float(np.median([p.slope_x for p in self._recent]))
        sy = float(np.median([p.slope_y for p in self._recent]))
        offset = float(np.median([p.offset for p in self._recent]))
        return math.degrees(math.atan(math.hypot(sx, sy))), offset

    def status(self) -> dict[str, Any]:
        """What ``flgctl status`` and the metrics show (any thread)."""
        est = self.latest
        return {
            "table_tilt_degrees": None if est is None else est[0],
            "table_offset_m": None if est is None else est[1],
            "frames": self.frames,
            "unjudged_frames": self.unjudged,
            "window": min(self.frames, self.config.window),
            "drift": self.drift,
            "since": self.since,
            "max_tilt_degrees": self.config.max_tilt_degrees,
            "max_offset_mm": self.config.max_offset_mm,
            "remedy": REMEDY,
        }
