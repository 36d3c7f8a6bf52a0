"""Analytic RGB-D frames of boxes on a table, ray-cast exactly: ground truth for perception tests."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flgd.geometry import pose_matrix, rpy_to_matrix


@dataclass(frozen=True)
class Box:
    """An upright box: centre (x, y) on the table, size (sx, sy, height), yaw about z, RGB colour."""

    x: float
    y: float
    sx: float
    sy: float
    height: float
    yaw: float = 0.0
    color: tuple[int, int, int] = (200, 60, 40)

    def contains_xy(self, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        lx = c * (px - self.x) + s * (py - self.y)
        ly = -s * (px - self.x) + c * (py - self.y)
        return (np.abs(lx) <= self.sx / 2) & (np.abs(ly) <= self.sy / 2)


def intrinsics_matrix(fx=615.0, fy=615.0, cx=320.0, cy=240.0) -> np.ndarray:
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def camera_looking_down(x: float, y: float, z: float, tilt: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """Camera-to-base pose of an OpenCV camera at (x, y, z) looking down, tilted about its x axis."""
    return pose_matrix((x, y, z), rpy_to_matrix(math.pi + tilt, 0.0, yaw))


def render(boxes: list[Box], camera_pose: np.ndarray, intrinsics: np.ndarray, table_z: float = 0.0,
           width: int = 640, height: int = 480, depth_scale: float = 0.001,
           table_color=(90, 90, 90)) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the table plane and the boxes; return (colour uint8 HxWx3, raw depth uint16 HxW).

    Depth is the optical-axis distance (z in the camera frame), as a RealSense reports it.
    """
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    dirs_cam = np.stack([(u - intrinsics[0, 2]) / intrinsics[0, 0],
                         (v - intrinsics[1, 2]) / intrinsics[1, 1],
                         np.ones_like(u)], axis=-1)  # z-component 1: the ray parameter is the depth
    r = camera_pose[:3, :3]
    o = camera_pose[:3, 3]
    d = dirs_cam @ r.T  # base-frame directions, HxWx3
    best = np.full((height, width), np.inf)
    color = np.zeros((height, width, 3), np.uint8)

    with np.errstate(divide="ignore", invalid="ignore"):
        t_table = (table_z - o[2]) / d[..., 2]
    hit = t_table > 0
    best[hit] = t_table[hit]
    color[hit] = table_color

    for box in boxes:
        # Work in the box frame: rotate rays by -yaw about z.
        c, s = math.cos(box.yaw), math.sin(box.yaw)
        ox = c * (o[0] - box.x) + s * (o[1] - box.y)
        oy = -s * (o[0] - box.x) + c * (o[1] - box.y)
        oz = o[2] - table_z
        dx = c * d[..., 0] + s * d[..., 1]
        dy = -s * d[..., 0] + c * d[..., 1]
        dz = d[..., 2]
        lo = np.array([-box.sx / 2, -box.sy / 2, 0.0])
        hi = np.array([box.sx / 2, box.sy / 2, box.height])
        tmin = np.full((height, width), -np.inf)
        tmax = np.full((height, width), np.inf)
        for oc, dc, a, b in ((ox, dx, lo[0], hi[0]), (oy, dy, lo[1], hi[1]), (oz, dz, lo[2], hi[2])):
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (a - oc) / dc
                t2 = (b - oc) / dc
            near = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
            far = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
            parallel = dc == 0
            outside = parallel & ((oc < a) | (oc > b))
            near = np.where(parallel, -np.inf, near)
            far = np.where(parallel, np.where(outside, -np.inf, np.inf), far)
            tmin = np.maximum(tmin, near)
            tmax = np.minimum(tmax, far)
        hit = (tmax >= tmin) & (tmin > 0) & (tmin < best)
        best[hit] = tmin[hit]
        # The top face gets the box colour, the sides a darker shade (so tests can tell them apart).
        on_top = np.abs(oz + tmin * dz - box.height) < 1e-9
        color[hit & on_top] = box.color
        color[hit & ~on_top] = tuple(ch // 2 for ch in box.color)

    depth = np.where(np.isfinite(best), np.round(best / depth_scale), 0)
    depth = np.clip(depth, 0, 65535).astype(np.uint16)
    return color, depth
