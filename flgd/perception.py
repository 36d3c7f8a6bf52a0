"""Orthographic heightmaps from a raw RGB-D frame, and the inverse pixel -> base-frame map.

Both cells hand out raw frames; this one projection turns them into the
224 x 224 colour and height maps the network sees, so that simulated and real
frames go through identical code.

Heightmap conventions: rows follow base y and columns follow base x, both
increasing with the coordinate; pixel (r, c) covers
[x0 + c*res, x0 + (c+1)*res) x [y0 + r*res, y0 + (r+1)*res).  Heights are
metres above the table (workspace.z[0]); the highest point in a cell wins;
cells with no valid point are 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flgd.config import WorkspaceConfig

__all__ = ["Heightmaps", "make_heightmaps", "pixel_to_base", "base_to_pixel"]

# Points this far below the table are still table (depth noise); lower ones are dropped.
TABLE_TOLERANCE = 0.02


@dataclass(frozen=True)
class Heightmaps:
    """colour: HxWx3 uint8 RGB; height: HxW float32 metres above the table."""

    color: np.ndarray
    height: np.ndarray


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
                    depth_range: tuple[float, float] = (0.0, np.inf)) -> Heightmaps:
    """Project an RGB-D frame orthographically onto the workspace.

    ``depth`` is raw (uint16 units times ``depth_scale`` metres) or float metres
    with ``depth_scale`` 1.  Zero, NaN and out-of-range readings are ignored.
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
    return Heightmaps(color=color_flat.reshape(rows, cols, 3), height=height.reshape(rows, cols))


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


def frame_heightmaps(frame, workspace: WorkspaceConfig, depth_range: tuple[float, float]) -> Heightmaps:
    """Heightmaps of a ``flgd.cell.Frame``."""
    return make_heightmaps(frame.color, frame.depth, frame.intrinsics, frame.depth_scale,
                           frame.camera_pose, workspace, depth_range)
