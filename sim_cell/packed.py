"""Packed arrangements: blocks laid flush against each other in rows, the kind of scene a drop never makes.

Random drops and the preset piles scatter blocks with gaps and tilts; what
defeats a grasp-only policy is blocks standing face to face, where no finger
fits between neighbours and a push or a shift has to make room first (the idea
behind VPG's hand-built hard test cases; none of their data is used here).
A packed scene is one to three groups, each one or two rows of two to five
blocks side by side (0-3 mm apart, every block turned with its row or across
it), at a random place and yaw in the workspace, groups apart from each other.

Shapes are the procedural blocks (sim_cell.shapes) that stand on a flat face
with straight sides to pack against: cubes, bars, plates, cylinders, hexagonal
and triangular prisms, half-cylinders.  Scenes are built from a seeded
generator only, so a validation set of packed scenes is fixed by its seed.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sim_cell import shapes
from sim_cell.scenes import Scene

__all__ = ["PACKED_SHAPES", "packed_scene"]

PACKED_SHAPES = ("cube", "bar", "plate", "cylinder", "hexagonal_prism", "triangular_prism", "half_cylinder")
GAP = (0.0, 0.003)           # m between neighbours in a row
GROUP_CLEARANCE = 0.03       # m between the footprints of two groups
PLACEMENT_TRIES = 60


def _group(rng: np.random.Generator, max_per_row: int = 5) -> list[tuple]:
    """One group in its own frame, rows along +x: per block (shape, dims, x, y, yaw, extents x, y, z)."""
    rows = 2 if rng.random() < 0.3 else 1
    per_row = int(rng.integers(2, max(2, max_per_row) + 1))
    blocks = []
    y_cursor = 0.0
    for _ in range(rows):
        row = []
        for _ in range(per_row):
            shape = PACKED_SHAPES[int(rng.integers(len(PACKED_SHAPES)))]
            dims = shapes.random_block_dims(shape, rng)
            ex, ey, ez = (float(v) for v in shapes.make_block(shape, dims).extents)
            across = rng.random() < 0.5          # long side across the row
            if (ex >= ey) == across:
                yaw, along, width = math.pi / 2, ey, ex
            else:
                yaw, along, width = 0.0, ex, ey
            row.append((shape, dims, yaw, along, width, (ex, ey, ez)))
        row_width = max(r[4] for r in row)
        x = 0.0
        for shape, dims, yaw, along, width, extents in row:
            blocks.append((shape, dims, x + along / 2, y_cursor + row_width / 2, yaw, extents))
            x += along + float(rng.uniform(*GAP))
        y_cursor += row_width + float(rng.uniform(*GAP))
    # centre the group on its own origin
    xs = [b[2] for b in blocks]
    ys = [b[3] for b in blocks]
    cx, cy = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
    return [(s, d, x - cx, y - cy, yaw, *ext) for s, d, x, y, yaw, ext in blocks]


def _corners(group, psi: float, spot: tuple[float, float]) -> list[np.ndarray]:
    """Each block's footprint rectangle (4 x 2, workspace frame) for the group turned by ``psi`` at ``spot``."""
    c, s = math.cos(psi), math.sin(psi)
    out = []
    for _shape, _dims, x, y, yaw, ex, ey, _ez in group:
        a = psi + yaw
        ca, sa = math.cos(a), math.sin(a)
        local = np.array([[-ex, -ey], [ex, -ey], [ex, ey], [-ex, ey]]) / 2
        rot = local @ np.array([[ca, sa], [-sa, ca]])
        out.append(rot + np.array([spot[0] + c * x - s * y, spot[1] + s * x + c * y]))
    return out


def packed_scene(rng: np.random.Generator, half_x: float, half_y: float, margin: float,
                 block_spec, groups: int | None = None) -> Scene:
    """A packed arrangement in the workspace frame (origin at the workspace centre on the table).

    ``half_x``/``half_y``: half the workspace size (m); ``margin``: kept free inside its edge;
    ``block_spec(shape, dims)`` gives a block's ObjectSpec (colour, mass, friction; the pose is set
    here).  ``groups`` (1-3) defaults to a random count.  A group that fits nowhere (inside the
    margin, ``GROUP_CLEARANCE`` from the others) is laid again smaller, then left out; the first
    group always fits.
    """
    if groups is None:
        groups = int(rng.integers(1, 4))
    if not 1 <= groups <= 3:
        raise ValueError(f"packed scene: groups: got {groups!r}, expected 1..3")
    grid_m = 0.005                                 # occupancy grid of the table, m per grid cell
    shape_px = (int(math.ceil(2 * half_y / grid_m)), int(math.ceil(2 * half_x / grid_m)))
    taken = np.zeros(shape_px, np.uint8)
    specs: list = []

    def raster(rects: list[np.ndarray], grow: float) -> np.ndarray:
        img = np.zeros(shape_px, np.uint8)
        for r in rects:
            centre = r.mean(axis=0)
            grown = r + np.sign(r - centre) * grow
            px = np.round((grown + [half_x, half_y]) / grid_m).astype(np.int32)
            cv2.fillConvexPoly(img, px, 1)
        return img

    for g in range(groups):
        for attempt in range(3):
            group = _group(rng, 5 - attempt)
            rects = None
            for _ in range(PLACEMENT_TRIES):
                psi = float(rng.uniform(0.0, math.pi))
                spot = (float(rng.uniform(-half_x, half_x)), float(rng.uniform(-half_y, half_y)))
                cand = _corners(group, psi, spot)
                pts = np.concatenate(cand)
                if np.any(np.abs(pts[:, 0]) > half_x - margin) or np.any(np.abs(pts[:, 1]) > half_y - margin):
                    continue
                if np.any(raster(cand, GROUP_CLEARANCE) & taken):
                    continue
                rects = cand
                break
            if rects is not None:
                break
        if rects is None and g == 0:   # an empty table: the last (smallest) group goes to its centre
            psi, rects = 0.0, _corners(group, 0.0, (0.0, 0.0))
        if rects is None:
            continue
        taken |= raster(rects, 0.0)
        for (shape, dims, _x, _y, yaw, _ex, _ey, ez), r in zip(group, rects):
            centre = r.mean(axis=0)
            a = (psi + yaw) / 2
            specs.append(block_spec(shape, dims).moved((float(centre[0]), float(centre[1]), ez / 2 + 0.0005),
                                                       (0.0, 0.0, math.sin(a), math.cos(a))))
    return Scene(objects=tuple(specs), source="<packed arrangement>")
