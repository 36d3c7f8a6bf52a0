"""Orthographic heightmaps from a raw RGB-D frame, and the inverse pixel -> base-frame map.

Both cells hand out raw frames; this one projection turns them into the
224 x 224 colour and height maps the network sees, so that simulated and real
frames go through identical code.

Heightmap conventions: rows follow base y and columns follow base x, both
increasing with the coordinate; pixel (r, c) covers
[x0 + c*res, x0 + (c+1)*res) x [y0 + r*res, y0 + (r+1)*res).  Heights are
metres above the table (workspace.z[0]); the highest point in a cell wins.

Cells with no valid point -- a depth camera's holes: dropouts, the stereo
shadow beside tall objects, edges where matching fails, and cells the camera
cannot see -- are *unknown*, not table.  ``Heightmaps.unknown`` marks them
for every cell, so that pictures can show them, and ``camera.depth_fill`` says
what height they get:

* ``lowest``: each hole (connected unknown cells) takes the lowest height on
  its rim (OpenCV's connected components and a grey-level erosion; colours are
  inpainted): a hole inside an object gets the object's height, a hole that
  touches the table -- the shadow a tall object casts, which hides table --
  gets the table's, as an unfilled map had it;
* ``inpaint``: OpenCV's inpainting (the Navier-Stokes method), colour and
  height alike: smooth ramps across holes, also across a shadow beside an object;
* ``none`` (the default): unknown cells stay 0 (table).  A hole inside an
  object then looks like a gap the fingers fit into, but the shipped policy was
  trained on such heightmaps: filled ones cost it picks per action on a noisy
  cell and in packed arrangements (BENCHMARKS.md), so filling waits for a policy
  trained on them.

A frame with too few valid cells to fill from (``FILL_MIN_VALID``) is left as
it is: there is nothing trustworthy to fill from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from flgd.config import WorkspaceConfig

__all__ = ["Heightmaps", "make_heightmaps", "fill_unknown", "FILL_METHODS", "pixel_to_base", "base_to_pixel"]

# Points this far below the table are still table (depth noise); lower ones are dropped.
TABLE_TOLERANCE = 0.02
# radius (px) of the neighbourhood an unknown cell is filled from
FILL_RADIUS = 3
# below this share of valid cells a heightmap is not filled (a covered lens, a camera that lost its depth)
FILL_MIN_VALID = 0.5
FILL_METHODS = ("lowest", "inpaint", "none")
_NO_READING = np.float32(1.0e6)  # above any height: never the lowest neighbour
_KERNEL3 = np.ones((3, 3), np.uint8)


@dataclass(frozen=True)
class Heightmaps:
    """colour: HxWx3 uint8 RGB; height: HxW float32 metres above the table; unknown: HxW bool, True where no
    depth reading fell (filled or left at 0 by the fill method; None: not known, e.g. a stored state)."""

    color: np.ndarray
    height: np.ndarray
    unknown: np.ndarray | None = None


def fill_unknown(color: np.ndarray, height: np.ndarray, unknown: np.ndarray,
                 method: str = "lowest") -> tuple[np.ndarray, np.ndarray, bool]:
    """(colour, height, filled?): ``unknown`` cells filled from their valid neighbours by ``method`` (module doc).

    Returns the inputs unchanged (and False) when nothing is unknown, too little is known to fill from, or
    ``method`` is ``none``.
    """
    if method not in FILL_METHODS:
        raise ValueError(f"fill method: got {method!r}, expected one of {', '.join(FILL_METHODS)}")
    unknown = np.asarray(unknown, dtype=bool)
    n_unknown = int(np.count_nonzero(unknown))
    if method == "none" or n_unknown == 0 or n_unknown > (1.0 - FILL_MIN_VALID) * unknown.size:
        return color, height, False
    if method == "lowest":
        return _fill_lowest(color, height, unknown)
    mask = unknown.astype(np.uint8)
    height = cv2.inpaint(np.ascontiguousarray(height, dtype=np.float32), mask, FILL_RADIUS, cv2.INPAINT_NS)
    color = cv2.inpaint(np.ascontiguousarray(color, dtype=np.uint8), mask, FILL_RADIUS, cv2.INPAINT_NS)
    return color, np.maximum(height, 0.0), True


def _fill_lowest(color: np.ndarray, height: np.ndarray, unknown: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Each hole (8-connected unknown cells) takes the lowest height on its rim; colours are inpainted."""
    count, labels = cv2.connectedComponents(unknown.astype(np.uint8), connectivity=8)
    # the rim: valid cells next to a hole; each unknown cell next to the rim sees its lowest rim neighbour
    lowest_near = cv2.erode(np.where(unknown, _NO_READING, height).astype(np.float32), _KERNEL3)
    touching = unknown & (lowest_near < _NO_READING)
    rim_min = np.full(count, _NO_READING, dtype=np.float32)
    np.minimum.at(rim_min, labels[touching], lowest_near[touching])
    rim_min[rim_min >= _NO_READING] = 0.0  # a hole with no valid rim (cannot happen above FILL_MIN_VALID)
    out = np.array(height, dtype=np.float32, copy=True)
    out[unknown] = rim_min[labels[unknown]]
    colour = cv2.inpaint(np.ascontiguousarray(color, dtype=np.uint8), unknown.astype(np.uint8), 1, cv2.INPAINT_NS)
    return colour, out, True


class _RayCache:
    """Per-pixel ray directions in the base frame, reused while the camera is unchanged."""

    def __init__(self) -> None:
        self._key: bytes | None = None
        self._dirs: np.ndarray | None = None

    def get(self, intrinsics: np.ndarray, rotation: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        key = intrinsics.astype(np.float64).tobytes() + rotation.astype(np.float64).tobytes() + \
            np.asarray(shape, np.int64).tobytes()
        if key != self._key:
            h, w = shape
            fx, fy = intrinsics[0, 0], intrinsics[1, 1]
            cx, cy = intrinsics[0, 2], intrinsics[1, 2]
            u = (np.arange(w, dtype=np.float64) - cx) / fx
            v = (np.arange(h, dtype=np.float64) - cy) / fy
            rays = np.empty((3, h, w), dtype=np.float64)
            rays[0] = u[None, :]
            rays[1] = v[:, None]
            rays[2] = 1.0
            dirs = np.ascontiguousarray((rotation @ rays.reshape(3, -1)).astype(np.float32))  # 3 x N
            # Key and rays are replaced together, and the caller gets the rays made for its own key.
            self._key, self._dirs = key, dirs
            return dirs
        assert self._dirs is not None
        return self._dirs


_rays = _RayCache()


def _check_inputs(color: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray, depth_scale: float,
                  camera_pose: np.ndarray) -> None:
    """Refuse frames the projection would silently turn into garbage (wrong colour layout, a NaN pose or
    focal length gives an all-empty heightmap) with a ValueError naming what is wrong."""
    if np.ndim(depth) != 2:
        raise ValueError(f"depth: got shape {np.shape(depth)}, expected H x W")
    h, w = np.shape(depth)
    if np.shape(color) != (h, w, 3) or np.asarray(color).dtype != np.uint8:
        raise ValueError(f"color: got shape {np.shape(color)} {np.asarray(color).dtype}, expected {h} x {w} x 3 "
                         f"uint8 RGB matching the depth image")
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or not (k[0, 0] > 0 and k[1, 1] > 0):
        raise ValueError(f"intrinsics: got {k.tolist()}, expected a finite 3x3 pinhole matrix with fx, fy > 0")
    pose = np.asarray(camera_pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"camera_pose: got {pose.tolist()}, expected a finite 4x4 camera-to-base transform")
    if not (isinstance(depth_scale, (int, float, np.floating, np.integer)) and math.isfinite(depth_scale)
            and depth_scale > 0):
        raise ValueError(f"depth_scale: got {depth_scale!r}, expected a finite number > 0 (metres per unit)")


def make_heightmaps(color: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray, depth_scale: float,
                    camera_pose: np.ndarray, workspace: WorkspaceConfig,
                    depth_range: tuple[float, float] = (0.0, np.inf), fill: str = "none") -> Heightmaps:
    """Project an RGB-D frame orthographically onto the workspace.

    ``depth`` is raw (uint16 units times ``depth_scale`` metres) or float metres
    with ``depth_scale`` 1.  Zero, NaN and out-of-range readings are ignored.
    ``fill``: how cells without a reading are filled (``FILL_METHODS``, module doc); ``none``: they are 0.
    """
    _check_inputs(color, depth, intrinsics, depth_scale, camera_pose)
    h, w = depth.shape
    intrinsics = np.asarray(intrinsics, dtype=np.float64)
    camera_pose = np.asarray(camera_pose, dtype=np.float64)
    dirs = _rays.get(intrinsics, camera_pose[:3, :3], (h, w))
    t = camera_pose[:3, 3].astype(np.float32)

    d = depth.reshape(-1).astype(np.float32)
    if depth_scale != 1.0:
        d *= np.float32(depth_scale)
    lo, hi = np.float32(max(depth_range[0], 0.0)), np.float32(min(depth_range[1], 3.0e38))
    # Whole-frame arithmetic is cheaper than gathering the valid pixels first.
    res = np.float32(workspace.resolution)
    rows, cols = workspace.shape
    table = np.float32(workspace.table_z)
    c = dirs[0] * d
    c += t[0] - np.float32(workspace.x[0])
    c /= res
    r = dirs[1] * d
    r += t[1] - np.float32(workspace.y[0])
    r /= res
    hz = dirs[2] * d
    hz += t[2] - table
    keep = (d > lo) & (d < hi)  # NaN compares False
    keep &= (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
    keep &= (hz >= -TABLE_TOLERANCE) & (hz <= np.float32(workspace.z[1]) - table)
    src = np.flatnonzero(keep)
    cell = r[src].astype(np.int32) * cols + c[src].astype(np.int32)  # truncation = floor here (>= 0)
    hz = np.maximum(hz[src], 0.0)

    height = np.zeros(rows * cols, dtype=np.float32)
    np.maximum.at(height, cell, hz)
    # The colour of a cell is that of a point at the cell's maximum height.
    top = hz >= height[cell]
    rgb = np.ascontiguousarray(color).reshape(-1).view(np.dtype((np.void, 3)))
    color_flat = np.zeros(rows * cols, dtype=np.dtype((np.void, 3)))
    color_flat[cell[top]] = rgb[src[top]]
    color_flat = color_flat.view(np.uint8)
    colour_map, height_map = color_flat.reshape(rows, cols, 3), height.reshape(rows, cols)
    unknown = np.ones(rows * cols, dtype=bool)
    unknown[cell] = False
    unknown = unknown.reshape(rows, cols)
    colour_map, height_map, _ = fill_unknown(colour_map, height_map, unknown, fill)
    return Heightmaps(color=colour_map, height=height_map, unknown=unknown)


def pixel_to_base(row: float, col: float, height: float, workspace: WorkspaceConfig) -> tuple[float, float, float]:
    """Centre of heightmap pixel (row, col) at ``height`` above the table, in the base frame."""
    res = workspace.resolution
    return (workspace.x[0] + (col + 0.5) * res,
            workspace.y[0] + (row + 0.5) * res,
            workspace.table_z + height)


def base_to_pixel(x: float, y: float, workspace: WorkspaceConfig) -> tuple[int, int]:
    """The heightmap pixel (row, col) containing base-frame point (x, y); may be out of range."""
    res = workspace.resolution
    return (int(np.floor((y - workspace.y[0]) / res)), int(np.floor((x - workspace.x[0]) / res)))


def frame_heightmaps(frame, workspace: WorkspaceConfig, depth_range: tuple[float, float],
                     fill: str = "none") -> Heightmaps:
    """Heightmaps of a ``flgd.cell.Frame`` (``fill``: see ``make_heightmaps``)."""
    return make_heightmaps(frame.color, frame.depth, frame.intrinsics, frame.depth_scale,
                           frame.camera_pose, workspace, depth_range, fill)
