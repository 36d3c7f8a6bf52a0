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

__all__ = ["UR5E_DH", "JOINT_LIMITS", "forward", "inverse", "nearest_solution", "pose_error"]

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
