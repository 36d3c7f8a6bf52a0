"""Small rigid-body helpers shared by perception, plans and cells."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (extrinsic x-y-z, as in the config)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def matrix_to_rpy(r: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rpy_to_matrix` (pitch in [-pi/2, pi/2])."""
    pitch = math.asin(-max(-1.0, min(1.0, float(r[2, 0]))))
    if abs(math.cos(pitch)) > 1e-9:
        roll = math.atan2(r[2, 1], r[2, 2])
        yaw = math.atan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: put everything in yaw
        roll = 0.0
        yaw = math.atan2(-r[0, 1], r[1, 1])
    return roll, pitch, yaw


def pose_matrix(position, rotation: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = np.asarray(position, dtype=float)
    return t


def rotvec_to_matrix(rv) -> np.ndarray:
    """Axis-angle (UR's pose convention) to a rotation matrix (Rodrigues)."""
    rv = np.asarray(rv, dtype=float)
    angle = float(np.linalg.norm(rv))
    if angle < 1e-12:
        return np.eye(3)
    k = rv / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation matrix to axis-angle, robust near 0 and pi."""
    r = np.asarray(r, dtype=float)
    cos_a = max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0))
    angle = math.acos(cos_a)
    if angle < 1e-9:
        return np.zeros(3)
    if math.pi - angle < 1e-6:
        # axis from the symmetric part: R = 2kk^T - I
        m = (r + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(m)))
        k = m[:, i] / math.sqrt(max(m[i, i], 1e-12))
        return k / np.linalg.norm(k) * angle
    k = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2 * math.sin(angle))
    return k * angle


def top_down_rotation(yaw: float) -> np.ndarray:
    """Tool orientation pointing straight down, fingers closing along (cos yaw, sin yaw, 0).

    Tool frame: x = finger closing direction, z = approach direction (down).
    """
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, s, 0.0],
                     [s, -c, 0.0],
                     [0.0, 0.0, -1.0]])


def wrap_symmetric_yaw(yaw: float) -> float:
    """Map a yaw to (-pi/2, pi/2]: a parallel gripper looks the same turned by pi,
    and a smaller wrist turn is faster and keeps the cable unwound."""
    y = math.remainder(yaw, math.pi)
    return math.pi / 2 if y <= -math.pi / 2 + 1e-12 else y


# How far (rad) a plan turns the wrist from the home pose's yaw at most: at least a quarter turn, so that every
# grasp angle has an equivalent (the RG2 is symmetric) within reach of any wrist angle, and under half a turn, so
# that the way back to the home yaw is always the shorter way round.
WRIST_YAW_LIMIT = 0.75 * math.pi
# A turn between two plans is kept this much under half a turn: a controller that turns the shorter way round
# must never face a near tie.
TURN_MARGIN = 0.1   # rad


def nearest_symmetric_yaw(yaw: float, current: float, centre: float, limit: float) -> float:
    """Of the wrist angles that grip like ``yaw`` (it plus any multiple of pi), the one nearest ``current``
    (the wrist's yaw where the move starts) that lies within ``limit`` of ``centre``.

    Why: a parallel gripper needs at most a quarter turn to any grasp from wherever the wrist stands, and at high
    speeds a moveL is bound by the wrist's turn.  With ``current`` within ``limit`` of ``centre`` (``limit`` at
    least a quarter turn) the turn from it is always under half a turn less ``TURN_MARGIN``, so a controller that
    turns the shorter way round turns the way the plan names.  With ``current`` at ``centre`` it is
    ``wrap_symmetric_yaw`` about it."""
    if not all(map(math.isfinite, (yaw, current, centre, limit))):
        raise ValueError(f"nearest_symmetric_yaw: non-finite yaw={yaw!r} current={current!r} centre={centre!r} "
                         f"limit={limit!r}")
    base = current + wrap_symmetric_yaw(yaw - current)
    candidates = sorted((base + k * math.pi for k in (0, -1, 1)), key=lambda c: (abs(c - current), -c))
    for c in candidates:
        if abs(c - centre) <= limit + 1e-9 and abs(c - current) <= math.pi - TURN_MARGIN:
            return c
    return centre + wrap_symmetric_yaw(yaw - centre)


def top_down_yaw(rotation: np.ndarray, centre: float = 0.0) -> float:
    """The yaw of a top-down tool orientation (``top_down_rotation``'s argument), the one within half a turn of
    ``centre``: a plan's yaws all lie within ``WRIST_YAW_LIMIT`` of the home yaw, so about it this is the yaw the
    plan named, whatever the home yaw."""
    r = np.asarray(rotation, dtype=float)
    return centre + math.remainder(math.atan2(float(r[1, 0]), float(r[0, 0])) - centre, 2 * math.pi)


@dataclass(frozen=True)
class ToolPose:
    """TCP position (m) and orientation (3x3 rotation, tool z = approach axis) in the base frame."""

    position: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...]

    @staticmethod
    def top_down(x: float, y: float, z: float, yaw: float) -> "ToolPose":
        r = top_down_rotation(yaw)
        return ToolPose((float(x), float(y), float(z)), tuple(tuple(float(v) for v in row) for row in r))

    @property
    def matrix(self) -> np.ndarray:
        return np.asarray(self.rotation, dtype=float)

    @property
    def rotvec(self) -> np.ndarray:
        return matrix_to_rotvec(self.matrix)

    def as_ur_pose(self) -> list[float]:
        """[x, y, z, rx, ry, rz] as ur_rtde expects."""
        return [*self.position, *self.rotvec.tolist()]
