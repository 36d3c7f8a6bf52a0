"""Grasps whose pads meet steep sides: how far an object's side slopes where the closing fingers touch it.

The RG2's pads are vertical.  Closing on a vertical side they press straight across it; closing on a side that
slopes (a triangular prism lying with its ridge up, a plate's corner gripped across its bevel) they press
partly upward, and once that slope is steeper than the pad's friction can hold, the object is squeezed up out
of the grip while the arm carries it.  Lifted objects that fell out of the gripper on the simulated cell were
mostly held that way (``benchmarks/results/drops-in-view-off/``).

From above, the side a pad meets is the heightmap's profile along the closing line, outward from the grasp
point: the pad touches where the object ends at the fingertips' height (``robot.grasp_depth`` below the grasped
surface, never below ``floor``), and a vertical side still ends there ``rise`` higher; a sloping one ends
nearer the grasp point.  The difference (the side's *taper*, m) is what ``side_tapers`` measures, for each pad.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["SIDE_RISE", "side_tapers", "steep_sides"]

SIDE_RISE = 0.01   # m above the fingertips where a side's taper is read: the pad's lowest centimetre holds the object


def _steps(angle: float, reach: int) -> list[tuple[int, int]]:
    """(row, column) offsets of the pixels 1 ... ``reach`` steps out from a grasp along ``angle``: one rounding for
    the single grasp and the mask, so that the two always agree."""
    return [(int(np.rint(k * math.sin(angle))), int(np.rint(k * math.cos(angle)))) for k in range(1, reach + 1)]


def _extent(profile: np.ndarray, level: float) -> int:
    """Samples from the start of ``profile`` (the grasp point outward) that stand at or above ``level`` without a
    gap: where a pad coming in from outside first touches at that height."""
    below = np.flatnonzero(~(profile >= level))
    return int(below[0]) if below.size else len(profile)


def side_tapers(height: np.ndarray, row: int, col: int, angle: float, resolution: float, open_width: float,
                grasp_depth: float, rise: float, floor: float) -> tuple[float, float]:
    """(taper on the side along +angle, on the side along -angle), m: how much nearer the grasp point the object
    ends ``rise`` above the fingertips' height than at it, along the closing line (``angle`` from the x axis;
    columns along x, rows along y) within the open fingers' reach.  0 for a vertical side; an object lower than
    the fingertips' height plus ``rise`` is measured over the lower three quarters of the height it has above them.  NaN heights read as table."""
    h = np.nan_to_num(np.asarray(height, dtype=np.float32), nan=0.0)
    rows, cols = h.shape
    if not (0 <= row < rows and 0 <= col < cols):
        raise ValueError(f"grasp pixel ({row}, {col}) is outside the heightmap {list(h.shape)}")
    if not (resolution > 0.0 and open_width > 0.0 and rise > 0.0 and grasp_depth >= 0.0):
        raise ValueError(f"side tapers: resolution={resolution} open_width={open_width} rise={rise} "
                         f"grasp_depth={grasp_depth}: expected positive sizes")
    surface = float(h[row, col])
    fingertips = max(surface - grasp_depth, floor)
    upper = min(fingertips + rise, fingertips + 0.75 * max(surface - fingertips, 0.0))
    reach = int(math.ceil(open_width / 2.0 / resolution))
    steps = np.array(_steps(angle, reach))
    out = []
    for sign in (1, -1):
        r, c = row + sign * steps[:, 0], col + sign * steps[:, 1]
        inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
        profile = np.where(inside, h[np.clip(r, 0, rows - 1), np.clip(c, 0, cols - 1)], 0.0)
        if upper <= fingertips:
            out.append(0.0)
            continue
        out.append((_extent(profile, fingertips) - _extent(profile, upper)) * resolution)
    return out[0], out[1]


def _shifted(h: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """``h`` moved so that out[r, c] = h[r + dr, c + dc]; table (0) beyond the border."""
    rows, cols = h.shape
    out = np.zeros_like(h)
    r0, r1 = max(0, -dr), min(rows, rows - dr)
    c0, c1 = max(0, -dc), min(cols, cols - dc)
    if r0 < r1 and c0 < c1:
        out[r0:r1, c0:c1] = h[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
    return out


def steep_sides(height: np.ndarray, rotations: int, resolution: float, open_width: float, grasp_depth: float,
                rise: float, floor: float, limit: float) -> np.ndarray:
    """uint8 [rotations, rows, cols]: 1 where a grasp at that pixel, closing along theta = 2 pi i / rotations,
    meets sides whose tapers (``side_tapers``) are both at most ``limit`` (m).  A closing line and its reverse
    share one answer: the RG2's two pads are alike."""
    if rotations <= 0 or not (limit >= 0.0):
        raise ValueError(f"steep sides: rotations={rotations} limit={limit}: expected rotations > 0, limit >= 0")
    h = np.nan_to_num(np.asarray(height, dtype=np.float32), nan=0.0)
    fingertips = np.maximum(h - np.float32(grasp_depth), np.float32(floor))
    upper = np.minimum(fingertips + np.float32(rise), fingertips + np.float32(0.75) * np.maximum(h - fingertips, 0))
    flat = upper <= fingertips
    reach = int(math.ceil(open_width / 2.0 / resolution))
    allowed = int(math.floor(limit / resolution + 1e-6))
    out = np.empty((rotations,) + h.shape, dtype=np.uint8)
    half = rotations // 2 if rotations % 2 == 0 else None
    for i in range(rotations):
        if half is not None and i >= half:   # the same closing line, its sides swapped
            out[i] = out[i - half]
            continue
        theta = 2.0 * math.pi * i / rotations
        steps = _steps(theta, reach)
        ok = flat.copy()
        taper_ok = np.ones(h.shape, dtype=bool)
        for sign in (1, -1):
            lower_run = np.ones(h.shape, dtype=bool)
            upper_run = np.ones(h.shape, dtype=bool)
            lower_ext = np.zeros(h.shape, dtype=np.int16)
            upper_ext = np.zeros(h.shape, dtype=np.int16)
            for dr, dc in steps:
                s = _shifted(h, sign * dr, sign * dc)
                lower_run &= s >= fingertips
                upper_run &= s >= upper
                lower_ext += lower_run
                upper_ext += upper_run
            taper_ok &= lower_ext - upper_ext <= allowed
        out[i] = ok | taper_ok
    return out
