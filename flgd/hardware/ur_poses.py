"""UR poses [x, y, z, rx, ry, rz] (metres, rotation vector): how far apart two are, how long a moveL between
them takes, and the same flange's pose under another TCP (a fresh control script runs the installation's)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from flgd.geometry import matrix_to_rotvec, rotvec_to_matrix

__all__ = ["pose_error", "move_duration", "for_tcp"]


def pose_error(actual: Sequence[float], target: Sequence[float]) -> tuple[float, float]:
    """(position error m, rotation error rad) between two UR poses [x, y, z, rx, ry, rz]."""
    dp = float(np.linalg.norm(np.asarray(actual[:3], float) - np.asarray(target[:3], float)))
    r = rotvec_to_matrix(actual[3:6]).T @ rotvec_to_matrix(target[3:6])
    angle = math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1.0) / 2.0)))
    return dp, angle


def move_duration(distance: float, speed: float, acceleration: float) -> float:
    """Time of a trapezoidal (or triangular) speed profile over ``distance``."""
    if distance <= 0:
        return 0.0
    ramp = speed * speed / acceleration
    if distance < ramp:
        return 2.0 * math.sqrt(distance / acceleration)
    return distance / speed + speed / acceleration


def for_tcp(pose: Sequence[float], tcp: Sequence[float], other: Sequence[float]) -> list[float]:
    """``pose`` of the TCP ``tcp`` (both [x, y, z, rx, ry, rz], the TCP in the flange frame) expressed as the pose
    of the TCP ``other`` on the same flange."""
    def matrix(v: Sequence[float]) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = rotvec_to_matrix(np.asarray(v[3:6], dtype=float))
        out[:3, 3] = np.asarray(v[:3], dtype=float)
        return out

    m = matrix(pose) @ np.linalg.inv(matrix(tcp)) @ matrix(other)
    return [float(v) for v in m[:3, 3]] + [float(v) for v in matrix_to_rotvec(m[:3, :3])]
