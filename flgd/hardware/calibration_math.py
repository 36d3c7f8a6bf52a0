"""The camera-to-base fit of ``flgd calibrate``: a pure function of matched points.

Given marker positions measured by the camera (camera frame, from aligned
depth) and the same positions known in the robot base frame (from the arm's
TCP pose), find the rigid transform camera -> base and a depth-scale
correction factor ``s``: base = R (s * p_camera) + t.  Scaling the depth
scales the whole deprojected point, so ``s`` is the scale of a similarity
transform, solved in closed form with an SVD (Umeyama 1991; with ``s`` fixed
to 1 it is the Kabsch solution).  Gross outliers (a misdetection) are dropped
and the fit repeated (at most two rounds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["CalibrationFit", "fit_camera_pose", "CalibrationError"]

MIN_POINTS = 4
MIN_SPREAD = 0.02         # m: the points must span at least this much in two directions
OUTLIER_FLOOR = 0.005     # m: a point is an outlier only if its error exceeds this ...
OUTLIER_FACTOR = 4.0      # ... and this many times the median error


class CalibrationError(ValueError):
    """The points cannot determine a camera pose (too few, collinear, mismatched)."""


@dataclass(frozen=True)
class CalibrationFit:
    camera_pose: np.ndarray           # 4x4 camera -> base
    depth_scale_correction: float     # multiplies the depth scale the camera points were made with
    rms_mm: float                     # residual over the inliers
    max_mm: float
    inliers: np.ndarray               # bool mask over the input points

    @property
    def used(self) -> int:
        return int(self.inliers.sum())


def _similarity(p: np.ndarray, q: np.ndarray, with_scale: bool) -> tuple[np.ndarray, float, np.ndarray]:
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    pc, qc = p - mp, q - mq
    cov = qc.T @ pc / len(p)
    u, d, vt = np.linalg.svd(cov)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    r = u @ flip @ vt
    s = float(np.trace(np.diag(d) @ flip) / np.mean(np.sum(pc * pc, axis=1))) if with_scale else 1.0
    t = mq - s * r @ mp
    return r, s, t


def fit_camera_pose(camera_points: np.ndarray, base_points: np.ndarray, *,
                    estimate_scale: bool = True) -> CalibrationFit:
    """Fit base = R (s p) + t to matched (N, 3) point arrays; see the module docstring."""
    p = np.asarray(camera_points, dtype=float)
    q = np.asarray(base_points, dtype=float)
    if p.ndim != 2 or p.shape[1:] != (3,) or p.shape != q.shape:
        raise CalibrationError(f"expected two matched (N, 3) point arrays, got {p.shape} and {q.shape}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise CalibrationError("the points contain NaN or infinite values")
    if len(p) < MIN_POINTS:
        raise CalibrationError(f"{len(p)} points; at least {MIN_POINTS} are needed")
    # Both sides must span a plane: with (nearly) collinear or coincident camera points (a frozen frame, a
    # depth reading stuck on one spot) the scale and rotation are undetermined and the fit would be NaN.
    for side, pts in (("robot-side", q), ("camera-side", p)):
        spread = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False) / np.sqrt(len(pts))
        if spread[1] < MIN_SPREAD / 2:
            raise CalibrationError(f"the {side} points are (nearly) collinear (spread {spread.round(4).tolist()} m); "
                                   f"use a grid that spans the workspace")
    keep = np.ones(len(p), dtype=bool)
    for _ in range(2):
        r, s, t = _similarity(p[keep], q[keep], estimate_scale)
        err = np.linalg.norm((s * p) @ r.T + t - q, axis=1)
        limit = max(OUTLIER_FLOOR, OUTLIER_FACTOR * float(np.median(err[keep])))
        new_keep = err <= limit
        if new_keep.sum() < MIN_POINTS or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    r, s, t = _similarity(p[keep], q[keep], estimate_scale)
    err = np.linalg.norm((s * p[keep]) @ r.T + t - q[keep], axis=1)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t)) and math.isfinite(s) and s > 0):
        raise CalibrationError(f"the fit is degenerate (scale {s!r}); check the detections")
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = r, t
    return CalibrationFit(camera_pose=pose, depth_scale_correction=s, rms_mm=float(np.sqrt(np.mean(err ** 2)) * 1e3),
                          max_mm=float(err.max() * 1e3), inliers=keep)
