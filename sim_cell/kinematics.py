"""UR5e forward and analytic inverse kinematics from the published DH parameters.

The simulated arm follows straight TCP lines by solving IK at every physics
step, so the solver must be exact and fast: the closed-form UR solution (up to
eight configurations) costs a few tens of microseconds and has no iteration
that can stall, unlike pybullet's damped least-squares IK.  Picking the
solution nearest to the previous joint vector keeps the arm in one
configuration along a line, as the real controller does.

Frames: the DH base frame is the robot base frame of the config (the frame
ur_rtde reports poses in); the DH frame 6 is the tool flange.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["UR5E_DH", "JOINT_LIMITS", "forward", "inverse", "nearest_solution", "pose_error",
           "forward_many", "inverse_many"]

# Standard DH parameters of the UR5e (Universal Robots' published values).
UR5E_DH = {
    "d": (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
    "a": (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
    "alpha": (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0),
}
_D = UR5E_DH["d"]
_A = UR5E_DH["a"]
_ALPHA = UR5E_DH["alpha"]


def _dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct],
                     [st, ct * ca, -ct * sa, a * st],
                     [0.0, sa, ca, d],
                     [0.0, 0.0, 0.0, 1.0]])


def _rigid_inverse(t: np.ndarray) -> np.ndarray:
    out = np.empty((4, 4))
    r = t[:3, :3].T
    out[:3, :3] = r
    out[:3, 3] = -r @ t[:3, 3]
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def forward(q) -> np.ndarray:
    """4x4 flange pose in the base frame for joint angles ``q`` (6 radians)."""
    t = np.eye(4)
    for i in range(6):
        t = t @ _dh(float(q[i]), _D[i], _A[i], _ALPHA[i])
    return t


def inverse(target: np.ndarray) -> list[np.ndarray]:
    """All closed-form joint solutions (each in (-pi, pi]) reaching flange pose ``target``.

    Returns an empty list when the pose is out of reach.  Near the wrist
    singularity (joint 5 ~ 0) joint 6 is taken as 0.
    """
    t = np.asarray(target, dtype=float)
    d1, d4, d5, d6 = _D[0], _D[3], _D[4], _D[5]
    a2, a3 = _A[1], _A[2]
    p05 = t @ np.array([0.0, 0.0, -d6, 1.0])
    r = math.hypot(p05[0], p05[1])
    if r < abs(d4) + 1e-9:
        return []
    psi = math.atan2(p05[1], p05[0])
    phi = math.acos(max(-1.0, min(1.0, d4 / r)))
    out: list[np.ndarray] = []
    for s1 in (1.0, -1.0):
        th1 = psi + s1 * phi + math.pi / 2
        c1, sn1 = math.cos(th1), math.sin(th1)
        c5 = (t[0, 3] * sn1 - t[1, 3] * c1 - d4) / d6
        if abs(c5) > 1.0 + 1e-9:
            continue
        c5 = max(-1.0, min(1.0, c5))
        for s5 in (1.0, -1.0):
            th5 = s5 * math.acos(c5)
            sin5 = math.sin(th5)
            if abs(sin5) < 1e-9:
                th6 = 0.0
            else:
                th6 = math.atan2((-t[0, 1] * sn1 + t[1, 1] * c1) / sin5,
                                 (t[0, 0] * sn1 - t[1, 0] * c1) / sin5)
            t01 = _dh(th1, d1, 0.0, _ALPHA[0])
            t45 = _dh(th5, d5, 0.0, _ALPHA[4])
            t56 = _dh(th6, d6, 0.0, _ALPHA[5])
            t14 = _rigid_inverse(t01) @ t @ _rigid_inverse(t45 @ t56)
            # Joints 2, 3, 4 are parallel: frame 4 is frame 1 turned by th2 + th3 + th4 about z.
            th234 = math.atan2(t14[1, 0], t14[0, 0])
            # Frame 4 sits d4 along its -y from the end of the planar two-link chain (joints 2, 3).
            px = t14[0, 3] - d4 * t14[0, 1]  # the planar chain lies in frame 1's x-y plane
            py = t14[1, 3] - d4 * t14[1, 1]
            dist2 = px * px + py * py
            c3 = (dist2 - a2 * a2 - a3 * a3) / (2 * a2 * a3)
            if abs(c3) > 1.0 + 1e-9:
                continue
            c3 = max(-1.0, min(1.0, c3))
            for s3 in (1.0, -1.0):
                th3 = s3 * math.acos(c3)
                th2 = math.atan2(py, px) - math.atan2(a3 * math.sin(th3), a2 + a3 * math.cos(th3))
                th4 = th234 - th2 - th3
                q = np.array([th1, th2, th3, th4, th5, th6])
                out.append(np.remainder(q + math.pi, 2 * math.pi) - math.pi)
    return out


def pose_error(q, target: np.ndarray) -> tuple[float, float]:
    """(position error m, rotation error rad) of ``forward(q)`` against ``target``."""
    t = forward(q)
    dp = float(np.linalg.norm(t[:3, 3] - target[:3, 3]))
    cos_a = (np.trace(t[:3, :3].T @ target[:3, :3]) - 1.0) / 2.0
    return dp, math.acos(max(-1.0, min(1.0, cos_a)))


# Joint limits of the UR5e: +-2*pi except the elbow (+-pi, self-collision).
JOINT_LIMITS = np.array([2 * math.pi, 2 * math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi])


def nearest_solution(solutions: list[np.ndarray], q_ref) -> np.ndarray | None:
    """The solution closest to ``q_ref`` in joint space, each joint shifted by 2*pi where that
    is nearer and stays within the joint limits (UR joints turn +-2*pi)."""
    if not solutions:
        return None
    q_ref = np.asarray(q_ref, dtype=float)
    qs = np.asarray(solutions)
    shifted = q_ref + np.remainder(qs - q_ref + math.pi, 2 * math.pi) - math.pi
    shifted = np.where(np.abs(shifted) > JOINT_LIMITS, qs, shifted)
    cost = np.sum((shifted - q_ref) ** 2, axis=1)
    return shifted[int(np.argmin(cost))]


def _dh_many(theta: np.ndarray, d: float, a: float, alpha: float) -> np.ndarray:
    """``_dh`` for an array of angles: (n, 4, 4)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    out = np.zeros(theta.shape + (4, 4))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2], out[..., 0, 3] = ct, -st * ca, st * sa, a * ct
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2], out[..., 1, 3] = st, ct * ca, -ct * sa, a * st
    out[..., 2, 1], out[..., 2, 2], out[..., 2, 3] = sa, ca, d
    out[..., 3, 3] = 1.0
    return out


def _rigid_inverse_many(t: np.ndarray) -> np.ndarray:
    out = np.zeros_like(t)
    r = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = r
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", r, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def forward_many(q: np.ndarray) -> np.ndarray:
    """``forward`` for (n, 6) joint vectors: (n, 4, 4) flange poses."""
    q = np.asarray(q, dtype=float)
    t = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4)).copy()
    for i in range(6):
        t = t @ _dh_many(q[..., i], _D[i], _A[i], _ALPHA[i])
    return t


def inverse_many(targets: np.ndarray) -> np.ndarray:
    """``inverse`` for (n, 4, 4) flange poses at once: (n, 8, 6), NaN rows where a branch has no
    solution.  Branches come in ``inverse``'s order, so the nearest valid one is the same solution."""
    t = np.asarray(targets, dtype=float)
    n = t.shape[0]
    d1, d4, d5, d6 = _D[0], _D[3], _D[4], _D[5]
    a2, a3 = _A[1], _A[2]
    out = np.full((n, 8, 6), np.nan)
    p05 = t[:, :3, 3] - d6 * t[:, :3, 2]
    r = np.hypot(p05[:, 0], p05[:, 1])
    reach = r >= abs(d4) + 1e-9
    r = np.where(reach, r, 1.0)
    psi = np.arctan2(p05[:, 1], p05[:, 0])
    phi = np.arccos(np.clip(d4 / r, -1.0, 1.0))
    k = 0
    for s1 in (1.0, -1.0):
        th1 = psi + s1 * phi + math.pi / 2
        c1, sn1 = np.cos(th1), np.sin(th1)
        c5 = (t[:, 0, 3] * sn1 - t[:, 1, 3] * c1 - d4) / d6
        ok5 = reach & (np.abs(c5) <= 1.0 + 1e-9)
        c5 = np.clip(c5, -1.0, 1.0)
        t01_inv = _rigid_inverse_many(_dh_many(th1, d1, 0.0, _ALPHA[0]))
        for s5 in (1.0, -1.0):
            th5 = s5 * np.arccos(c5)
            sin5 = np.sin(th5)
            small = np.abs(sin5) < 1e-9
            safe = np.where(small, 1.0, sin5)
            th6 = np.where(small, 0.0, np.arctan2((-t[:, 0, 1] * sn1 + t[:, 1, 1] * c1) / safe,
                                                  (t[:, 0, 0] * sn1 - t[:, 1, 0] * c1) / safe))
            t56 = _dh_many(th5, d5, 0.0, _ALPHA[4]) @ _dh_many(th6, d6, 0.0, _ALPHA[5])
            t14 = t01_inv @ t @ _rigid_inverse_many(t56)
            th234 = np.arctan2(t14[:, 1, 0], t14[:, 0, 0])
            px = t14[:, 0, 3] - d4 * t14[:, 0, 1]
            py = t14[:, 1, 3] - d4 * t14[:, 1, 1]
            c3 = (px * px + py * py - a2 * a2 - a3 * a3) / (2 * a2 * a3)
            ok = ok5 & (np.abs(c3) <= 1.0 + 1e-9)
            c3 = np.clip(c3, -1.0, 1.0)
            for s3 in (1.0, -1.0):
                th3 = s3 * np.arccos(c3)
                th2 = np.arctan2(py, px) - np.arctan2(a3 * np.sin(th3), a2 + a3 * np.cos(th3))
                th4 = th234 - th2 - th3
                q = np.stack([th1, th2, th3, th4, th5, th6], axis=1)
                q = np.remainder(q + math.pi, 2 * math.pi) - math.pi
                out[:, k] = np.where(ok[:, None], q, np.nan)
                k += 1
    return out
