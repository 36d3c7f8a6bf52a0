"""Grasps whose fingers come down free: where both open fingers reach below the grasped surface.

A grasp at a pixel brings the open fingers down ``gripper.open_width`` / 2 either side of it along its closing
line, to ``robot.grasp_depth`` below the surface there.  Where anything under a finger's footprint stands higher
than that, the guarded descent stops on it and the fingers close on the top millimetres of the object, or on
nothing: a neighbouring block in a packed row, or the grasped block itself where it is wider than the opening
or the grasp is off its middle.  The masks of ``flgd.clutter`` allow every object pixel at every rotation, so a
policy can keep choosing such grasps (on VPG's packed cases it does).  ``exploration.finger_clearance`` (c)
allows a grasp only at the rotations where nothing under either footprint is higher than the grasped surface
less c: the fingertips get at least c down the object before they touch anything.  On an object lower than
``rewards.min_height`` + c the fingers must come down on table (nothing above ``rewards.min_height``).

Only grasps are limited: an object none of whose grasps is free stays a place to push or shift, the pre-grasp
that frees it.  The footprints are those of ``flgd.grasp_view`` (the RG2's fingers, sim_cell's rg2.urdf).
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np

from flgd.grasp_view import FINGER_DEPTH, FINGER_HALF_WIDTH

__all__ = ["finger_kernels", "fingers_clear"]


@lru_cache(maxsize=16)
def finger_kernels(rotations: int, resolution: float, open_width: float) -> tuple[np.ndarray, ...]:
    """One uint8 kernel per rotation (closing along theta = 2 pi i / rotations from the x axis; columns along
    x, rows along y), centred on the grasp pixel: 1 on the pixels under either open finger.  Cached; callers
    must not write to them."""
    if rotations <= 0 or not resolution > 0.0 or not open_width > 0.0:
        raise ValueError(f"finger kernels: rotations={rotations} resolution={resolution} open_width={open_width}: "
                         "expected positive values")
    inner, outer = open_width / 2.0, open_width / 2.0 + FINGER_DEPTH
    n = int(math.ceil(outer / resolution)) + 1
    offsets = np.arange(-n, n + 1) * resolution
    ox, oy = np.meshgrid(offsets, offsets)       # ox along columns (x), oy along rows (y)
    kernels = []
    for i in range(rotations):
        theta = 2.0 * math.pi * i / rotations
        along = ox * math.cos(theta) + oy * math.sin(theta)
        across = -ox * math.sin(theta) + oy * math.cos(theta)
        k = ((np.abs(along) >= inner) & (np.abs(along) <= outer) & (np.abs(across) <= FINGER_HALF_WIDTH))
        k = k.astype(np.uint8)
        k.setflags(write=False)
        kernels.append(k)
    return tuple(kernels)


def fingers_clear(height: np.ndarray, objects: np.ndarray, rotations: int, resolution: float, open_width: float,
                  clearance: float, floor: float) -> np.ndarray:
    """uint8 [rotations, rows, cols]: 1 where a grasp at that pixel and rotation brings both fingers at least
    ``clearance`` (m) below the surface there before they touch anything, or, on a surface lower than
    ``floor`` + ``clearance``, down on nothing higher than ``floor`` (m above the table).

    Only ``objects`` (uint8 [rows, cols], the filtered object mask of ``flgd.clutter``) can stand under a finger:
    a depth camera's specks above ``floor`` elsewhere do not refuse a grasp.  Unknown heights (NaN) and a depth
    hole read as table, and beyond the heightmap's border counts as free: with ``exploration.grasp_in_view`` off,
    what the camera does not see is not checked."""
    if not clearance > 0.0:
        raise ValueError(f"finger clearance {clearance} m: expected > 0")
    h = np.nan_to_num(np.asarray(height, dtype=np.float32), nan=0.0)
    if objects.shape != h.shape:
        raise ValueError(f"objects {list(objects.shape)} does not match the heightmap {list(h.shape)}")
    floor32 = np.float32(floor)
    standing = np.ascontiguousarray(np.where(objects > 0, h, np.minimum(h, floor32)))
    allowed = np.maximum(h - np.float32(clearance), floor32)
    out = np.empty((rotations,) + h.shape, dtype=np.uint8)
    for i, kernel in enumerate(finger_kernels(int(rotations), float(resolution), float(open_width))):
        highest = cv2.dilate(standing, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
        out[i] = highest <= allowed
    return out
