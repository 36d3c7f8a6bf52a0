"""The camera-to-base fit of ``flgd calibrate``: a pure function of matched points.

Given marker positions measured by the camera (camera frame, from aligned
depth) and the same positions known in the robot base frame (from the arm's
TCP pose), find the rigid transform camera -> base and a depth-scale
correction factor ``s``: base = R (s * p_camera) + t.  Scaling the depth
scales the whole deprojected point, so ``s`` is the scale of a similarity
transform, solved in closed form with an SVD (Umeyama 1991; with ``s`` fixed
to 1 it is the Kabsch solution).  Gross outliers (a misdetection) are dropped
and the fit repeated (at most two rounds).

``fit_camera_pose_and_offset`` also estimates the marker's offset on the tool.
The robot-side point is p_base = p_tcp + R_tool o, with o the marker centre in
the tool frame.  If every pose had the same R_tool, an error in o would add the
same vector to every point and vanish into the camera translation with no rise
in the residual, so the calibration grid varies the tool yaw and o is fitted
jointly: for a fixed R and s, base = R (s p) + t is linear in (t, o_x, o_y),
so the fit alternates (similarity with the current o; then t and o_x, o_y by
linear least squares) until o stops moving.  o_z is NOT observable: every
calibration pose is top-down, the tool z axis is always vertical, and
R_tool (0, 0, o_z) is the same vector for every pose -- it is kept at the
caller's value and must be measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

__all__ = ["CalibrationFit", "fit_camera_pose", "fit_camera_pose_and_offset", "CalibrationError"]

MIN_POINTS = 4
MIN_SPREAD = 0.02         # m: the points must span at least this much in two directions
OUTLIER_FLOOR = 0.005     # m: a point is an outlier only if its error exceeds this ...
OUTLIER_FACTOR = 4.0      # ... and this many times the median error
MIN_YAW_SPREAD = 0.3      # the tool's x/y axes must vary this much (RMS about their mean) to fit o_x, o_y
OFFSET_ITERATIONS = 50    # cap on the pose/offset alternation
OFFSET_CONVERGED = 1e-7   # m: the alternation stops when o moves less than this


class CalibrationError(ValueError):
    """The points cannot determine a camera pose (too few, collinear, mismatched)."""


@dataclass(frozen=True)
class CalibrationFit:
    camera_pose: np.ndarray           # 4x4 camera -> base
    depth_scale_correction: float     # multiplies the depth scale the camera points were made with
    rms_mm: float                     # residual over the inliers
    max_mm: float
    inliers: np.ndarray               # bool mask over the input points
    marker_offset: np.ndarray | None = None  # (3,) tool-frame offset the fit used (x, y estimated), if fitted

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


def fit_camera_pose_and_offset(camera_points: np.ndarray, tcp_positions: np.ndarray, tool_rotations: np.ndarray,
                               marker_offset, *, estimate_scale: bool = True) -> CalibrationFit:
    """Fit base = R (s p) + t and the marker offset's x, y; see the module docstring.

    ``tcp_positions`` (N, 3) and ``tool_rotations`` (N, 3, 3) are the poses the arm reported;
    ``marker_offset`` is the user's (x, y, z) in the tool frame, the starting point and the source of o_z.
    The returned fit's ``marker_offset`` is the estimate; its residual is that of the joint fit.
    Raises ``CalibrationError`` when the tool's yaws do not vary enough for o_x, o_y to be determined.
    """
    p = np.asarray(camera_points, dtype=float)
    tcp = np.asarray(tcp_positions, dtype=float)
    rot = np.asarray(tool_rotations, dtype=float)
    o = np.array(marker_offset, dtype=float).reshape(3)
    if tcp.shape != p.shape or rot.shape != (len(p), 3, 3):
        raise CalibrationError(f"expected (N, 3) camera points, (N, 3) TCP positions and (N, 3, 3) tool "
                               f"rotations, got {p.shape}, {tcp.shape} and {rot.shape}")
    if not (np.all(np.isfinite(tcp)) and np.all(np.isfinite(rot)) and np.all(np.isfinite(o))):
        raise CalibrationError("the tool poses or the marker offset contain NaN or infinite values")

    def base_points(off: np.ndarray) -> np.ndarray:
        return tcp + rot @ off

    def check_spread(keep: np.ndarray) -> None:
        axes = rot[keep][:, :, :2]                          # the tool's x and y axes, which o_x, o_y scale
        centred = (axes - axes.mean(axis=0)).reshape(-1, 2)
        spread = np.linalg.svd(centred, compute_uv=False) / np.sqrt(max(int(keep.sum()), 1))
        if spread[-1] < MIN_YAW_SPREAD:
            raise CalibrationError(f"the tool yaws of the usable detections do not vary enough to check the "
                                   f"marker offset (spread {spread.round(3).tolist()}, need {MIN_YAW_SPREAD})")

    check_spread(np.ones(len(p), dtype=bool))
    fit = fit_camera_pose(p, base_points(o), estimate_scale=estimate_scale)
    for _ in range(OFFSET_ITERATIONS):
        keep = fit.inliers
        check_spread(keep)
        r, s = fit.camera_pose[:3, :3], fit.depth_scale_correction
        # R (s p_i) + t = tcp_i + R_i[:, :2] o_xy + R_i[:, 2] o_z   ->   t - R_i[:, :2] o_xy = rhs_i
        rhs = (tcp[keep] + rot[keep][:, :, 2] * o[2] - (s * p[keep]) @ r.T).reshape(-1)
        a = np.zeros((3 * int(keep.sum()), 5))
        a[:, :3] = np.tile(np.eye(3), (int(keep.sum()), 1))
        a[:, 3:] = -rot[keep][:, :, :2].reshape(-1, 2)
        sol = np.linalg.lstsq(a, rhs, rcond=None)[0]
        new_o = np.array([sol[3], sol[4], o[2]])
        moved = float(np.linalg.norm(new_o - o))
        o = new_o
        fit = fit_camera_pose(p, base_points(o), estimate_scale=estimate_scale)
        if moved < OFFSET_CONVERGED:
            break
    return replace(fit, marker_offset=o)
