"""The opening a grasp comes down with: just wide enough for the fingers to land free beside the object.

An RG2 closes at about 110 mm/s.  A grasp that comes down fully open (``gripper.open_width``, 85 mm) on a 30 mm
block spends half a second closing before the pads touch it, every pick.  With ``gripper.preshape_margin`` (m) a
grasp opens only as far as its fingers need: the fingers set to that opening while the arm travels to the grasp
(``flgd.plans.plan_grasp``), and the close at the bottom starts near the object.

The opening is the narrowest with ``preshape_margin`` of free space inside each pad face (for what the heightmap
does not show exactly: an edge blurred by a pixel, a few millimetres of calibration) and nothing under either
finger that would stop the descent sooner than it stops fully open fingers: nothing higher than the fingertips'
depth, or than what the fully open fingers come down on (in clutter they often land on a neighbour).  Heights up to
``rewards.min_height`` are table, as everywhere else.  Where no opening up to ``open_width`` is so, the grasp opens
fully, as without a pre-shape.  The footprints are those of ``flgd.grasp_view`` (the RG2's fingers).
"""

from __future__ import annotations

import math

import numpy as np

from flgd.grasp_view import FINGER_DEPTH, FINGER_HALF_WIDTH

__all__ = ["preshape_width"]


def preshape_width(height: np.ndarray, row: float, col: float, angle: float, fingertips: float,
                   open_width: float, margin: float, resolution: float, floor: float = 0.0) -> float:
    """The narrowest opening (m, at most ``open_width``) of a grasp at pixel (``row``, ``col``) closing along
    ``angle`` (rad from the heightmap's columns towards its rows) that has nothing higher than ``fingertips`` (m
    above the table, where the descent takes them) within ``margin`` (m) inside either pad face, and under either
    finger nothing higher than that or than what the fully open fingers would come down on: the descent gets at
    least as deep as fully open, and the pads never land on the object's side.  ``open_width`` when no narrower
    opening is so.

    Heights up to ``floor`` (m; ``rewards.min_height``, the object/table threshold) are table whatever the
    fingertips' depth: a depth camera reads the table a few millimetres high here and there, and a low object's
    fingertips come down to ``safety.min_table_clearance``, below that noise.

    A pixel stands in a band where its square's extent along and across the closing line reaches into it (a
    little more than the square itself at angles between the axes).  Unknown heights (NaN) read as table; beyond
    the heightmap's border counts as free (``flgd.finger_clearance`` treats them so too)."""
    if not (margin > 0.0 and open_width > 0.0 and resolution > 0.0):
        raise ValueError(f"preshape width: margin={margin} open_width={open_width} resolution={resolution}: "
                         "expected positive values")
    reach = open_width / 2.0 + FINGER_DEPTH + resolution
    n = int(math.ceil(reach / resolution))
    rows, cols = height.shape
    r0, c0 = int(round(row)), int(round(col))
    lo_r, hi_r, lo_c, hi_c = max(r0 - n, 0), min(r0 + n + 1, rows), max(c0 - n, 0), min(c0 + n + 1, cols)
    if lo_r >= hi_r or lo_c >= hi_c:
        return open_width
    patch = np.nan_to_num(np.asarray(height[lo_r:hi_r, lo_c:hi_c], dtype=float), nan=0.0)
    rr, cc = np.mgrid[lo_r:hi_r, lo_c:hi_c]
    dx, dy = (cc - col) * resolution, (rr - row) * resolution
    along = np.abs(dx * math.cos(angle) + dy * math.sin(angle))
    across = np.abs(-dx * math.sin(angle) + dy * math.cos(angle))
    # a pixel's square reaches half_pixel either way along and across the closing line, at any angle (at most)
    half_pixel = resolution / 2.0 * (abs(math.cos(angle)) + abs(math.sin(angle)))
    level = max(fingertips, floor)
    beside = across <= FINGER_HALF_WIDTH + half_pixel
    standing = (patch > level) & beside
    # what the fully open fingers come down on: a narrower finger may land on nothing higher than that
    under_open = beside & (along + half_pixel >= open_width / 2.0) & (along - half_pixel <= open_width / 2.0
                                                                      + FINGER_DEPTH)
    open_top = float(patch[under_open].max()) if under_open.any() else 0.0
    higher = standing & (patch > open_top)
    # a pixel at |along| = a lies in a finger's band [w/2 - margin, w/2 + FINGER_DEPTH] for openings w in
    # [2 (a - FINGER_DEPTH), 2 (a + margin)], and in its margin [w/2 - margin, w/2] for w in [2 a, 2 (a + margin)];
    # each widened by half a pixel either way.  Above the open fingers' top a pixel blocks the band, else the margin.
    a, inward = along[standing], np.where(higher[standing], FINGER_DEPTH, 0.0)
    starts, ends = 2.0 * (a - inward - half_pixel), 2.0 * (a + margin + half_pixel)
    order = np.argsort(starts, kind="stable")
    starts, ends = starts[order], ends[order]
    width = 2.0 * margin
    for start, end in zip(starts, ends):
        if start > width:
            break
        width = max(width, end)
    return min(width, open_width)
