"""Blended corners: where a move that blends into the next leaves its straight line and where it rejoins.

A MoveL with ``blend`` r > 0 does not stop at its pose P: the tool leaves the incoming line r before P and joins
the outgoing line r after it, on a curve between those two points with P as its control point (a quadratic
Bezier: tangent to both lines, inside the triangle they span).  The UR controller's own blend stays within the
same sphere of radius r around P.  Every cell that runs a blended path follows this curve, and the safety
envelope checks points on it, so the corner is checked where the tool actually goes.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

__all__ = ["corner_curve", "corner_problem", "CORNER_SAMPLES"]

CORNER_SAMPLES = 9   # points on a corner the envelope checks (both ends included)


def _unit(v: np.ndarray) -> np.ndarray | None:
    n = float(np.linalg.norm(v))
    return None if n < 1e-12 else v / n


def corner_problem(before: Sequence[float], corner: Sequence[float], after: Sequence[float],
                   radius: float) -> str | None:
    """Why a corner of ``radius`` at ``corner`` between the lines from ``before`` and to ``after`` cannot be
    blended, or None: the radius must fit in half of each line (two corners of one line never overlap)."""
    if not (math.isfinite(radius) and radius >= 0.0):
        return f"blend radius {radius!r} m is not a finite distance >= 0"
    a, p, b = (np.asarray(v, dtype=float) for v in (before, corner, after))
    for name, length in (("incoming", float(np.linalg.norm(p - a))), ("outgoing", float(np.linalg.norm(b - p)))):
        if radius > 0.5 * length + 1e-9:
            return (f"blend radius {radius:.4f} m is more than half the {name} line ({length:.4f} m): "
                    f"the corner would reach past the middle of that line")
    return None


def corner_curve(before: Sequence[float], corner: Sequence[float], after: Sequence[float], radius: float,
                 samples: int = CORNER_SAMPLES) -> np.ndarray:
    """(samples, 3) positions along the blended corner, from where it leaves the incoming line to where it joins
    the outgoing one; just the corner itself when ``radius`` is 0 or a line has no length."""
    a, p, b = (np.asarray(v, dtype=float) for v in (before, corner, after))
    u_in, u_out = _unit(p - a), _unit(b - p)
    if radius <= 0.0 or u_in is None or u_out is None:
        return p[None, :].copy()
    entry, exit_ = p - radius * u_in, p + radius * u_out
    t = np.linspace(0.0, 1.0, max(int(samples), 2))[:, None]
    return (1 - t) ** 2 * entry + 2 * (1 - t) * t * p + t ** 2 * exit_
