"""Actions the camera sees whole: the gripper's fingers come down (and a move's travel ends) inside the heightmap.

A heightmap ends where the workspace ends, the table does not: an object pushed
past the edge (nothing removes it on a real table) shows as a sliver along the
border.  A grasp on that sliver closing across the border brings one finger down
where the camera has no height, onto the object's hidden part; the guarded descent
stops on it, centimetres short, and the grasp fails -- again and again, since the
heightmap never shows why.  Such grasps are left out per rotation: a grasp at a
pixel near the border is allowed only at the rotations whose finger footprints stay
inside the heightmap (closing along the border, for a sliver).

A push or shift near the border would come down on such a part too (closed fingers, no guarded descent: a
protective stop) or drag its fingers past the border: a move is allowed only where its closed fingers stay
inside where they come down and where their travel ends.

The footprint is the RG2's fingers: from each pad face (``gripper.open_width`` / 2
from the centre) ``FINGER_DEPTH`` outward along the closing line, and
``FINGER_HALF_WIDTH`` either side of it (sim_cell's rg2.urdf is built to the same),
kept ``VIEW_MARGIN`` inside the heightmap: its last centimetre is the least known
(a part leaning over the border, the depth camera's shadow beside a tall object
reading as table, a few millimetres of calibration).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

__all__ = ["FINGER_DEPTH", "FINGER_HALF_WIDTH", "VIEW_MARGIN", "grasps_in_view", "moves_in_view"]

FINGER_DEPTH = 0.015       # m a finger reaches beyond its pad face, along the closing line
FINGER_HALF_WIDTH = 0.011  # m a finger reaches either side of the closing line
VIEW_MARGIN = 0.01         # m the fingers stay inside the heightmap's border


def grasps_in_view(rows: int, cols: int, rotations: int, resolution: float, open_width: float) -> np.ndarray:
    """uint8 [rotations, rows, cols]: 1 where a grasp at that pixel and rotation (closing along theta =
    2 pi i / rotations from the base x axis; columns along x, rows along y) keeps both fingers
    ``VIEW_MARGIN`` inside the heightmap.  Cached: one array per cell geometry; callers must not write to it."""
    return _in_view(int(rows), int(cols), int(rotations), float(resolution), open_width / 2.0 + FINGER_DEPTH, 0.0)


def moves_in_view(rows: int, cols: int, rotations: int, resolution: float, travel: float) -> np.ndarray:
    """uint8 [rotations, rows, cols]: 1 where a push or shift from that pixel along theta keeps the closed fingers
    ``VIEW_MARGIN`` inside the heightmap where they come down and where their ``travel`` (m) ends.  A closed
    finger pair reaches ``FINGER_DEPTH`` either way along theta (the gripper's closing line, and the travel's)."""
    return _in_view(int(rows), int(cols), int(rotations), float(resolution), FINGER_DEPTH, float(travel))


@lru_cache(maxsize=16)
def _in_view(rows: int, cols: int, rotations: int, resolution: float, reach: float, travel: float) -> np.ndarray:
    if rows <= 0 or cols <= 0 or rotations <= 0 or not resolution > 0.0 or not reach > 0.0 or not travel >= 0.0:
        raise ValueError(f"in view: rows={rows} cols={cols} rotations={rotations} resolution={resolution} "
                         f"reach={reach} travel={travel}: expected positive sizes")
    x = (np.arange(cols) + 0.5) * resolution    # pixel centres, m from the heightmap's edge
    y = (np.arange(rows) + 0.5) * resolution
    out = np.zeros((rotations, rows, cols), dtype=np.uint8)
    for i in range(rotations):
        theta = 2.0 * math.pi * i / rotations
        c, s = abs(math.cos(theta)), abs(math.sin(theta))
        half_x = reach * c + FINGER_HALF_WIDTH * s   # the fingers' bounding box around where they come down
        half_y = reach * s + FINGER_HALF_WIDTH * c
        dx, dy = travel * math.cos(theta), travel * math.sin(theta)   # and where the travel ends
        ok_x = (np.minimum(x, x + dx) - half_x >= VIEW_MARGIN - 1e-9) & \
               (np.maximum(x, x + dx) + half_x <= cols * resolution - VIEW_MARGIN + 1e-9)
        ok_y = (np.minimum(y, y + dy) - half_y >= VIEW_MARGIN - 1e-9) & \
               (np.maximum(y, y + dy) + half_y <= rows * resolution - VIEW_MARGIN + 1e-9)
        out[i] = ok_y[:, None] & ok_x[None, :]
    out.setflags(write=False)
    return out
