"""Free spans of a line: the ticks where the swept gripper box cannot touch any object.

The cell jumps over such spans instead of stepping the physics (see sim_cell.cell's module docstring,
"Speed"): the box swept by the TCP path, inflated by the gripper's half-size and by what it carries, from
the TCP (or the carried object's bottom) up, must keep ``FREE_MARGIN`` from every other object's
bounding box.  Pure geometry over axis-aligned boxes, apart from reading the boxes.
"""

from __future__ import annotations

import numpy as np

from sim_cell import objects

FREE_MARGIN = 0.02          # m between the swept gripper box and any object for a free move
GRIPPER_HALF_SIZE = 0.075   # m, gripper + open fingers around the TCP in x/y

Box = tuple[np.ndarray, np.ndarray]   # (lower corner, upper corner), m in the base frame


def obstacles(client: int, bodies, carried: set[int]) -> list[Box]:
    """Bounding boxes of every object in ``bodies`` not carried by the gripper."""
    return [objects.body_aabb(b, client) for b in bodies if b not in carried]


def carry_extent(client: int, tcp: np.ndarray, carried: set[int]) -> tuple[float, float]:
    """(xy half-size around the TCP position ``tcp``, depth below it) of the gripper with what it carries."""
    half, below = GRIPPER_HALF_SIZE, 0.0
    for body in carried:
        lo, hi = objects.body_aabb(body, client)
        half = max(half, float(np.max(np.abs(np.concatenate([lo[:2], hi[:2]]) - np.tile(tcp[:2], 2)))))
        below = max(below, float(tcp[2] - lo[2]))
    return half, below


def clear(pts: np.ndarray, half: float, below: float, boxes: list[Box]) -> bool:
    """Whether the box swept by the gripper (+ held objects) along ``pts`` keeps FREE_MARGIN to all ``boxes``."""
    lo = pts.min(axis=0) - (half + FREE_MARGIN)
    hi = pts.max(axis=0) + (half + FREE_MARGIN)
    lowest = pts[:, 2].min() - below - FREE_MARGIN
    for a, b in boxes:
        if a[0] < hi[0] and b[0] > lo[0] and a[1] < hi[1] and b[1] > lo[1] and b[2] > lowest:
            return False
    return True


def free_span(pts: np.ndarray, half: float, below: float, boxes: list[Box], from_end: bool) -> int:
    """Number of TCP positions ``pts`` at the start (or end) of a line whose swept box is ``clear``."""
    n = len(pts)
    order = range(n - 1, -1, -1) if from_end else range(n)
    count = 0
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in order:
        lo, hi = np.minimum(lo, pts[i]), np.maximum(hi, pts[i])
        if not clear(np.stack([lo, hi]), half, below, boxes):
            break
        count += 1
    return count
