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

import numpy as np

from sim_cell import shapes
from sim_cell.scenes import Scene

__all__ = ["PACKED_SHAPES", "packed_scene"]

PACKED_SHAPES = ("cube", "bar", "plate", "cylinder", "hexagonal_prism", "triangular_prism", "half_cylinder")
GAP = (0.0, 0.003)           # m between neighbours in a row
GROUP_CLEARANCE = 0.03       # m between the footprints of two groups
PLACEMENT_TRIES = 60


def _footprint(geom: shapes.BlockGeometry) -> tuple[float, float, float]:
    ex, ey, ez = (float(v) for v in geom.extents)
    return ex, ey, ez


def _group(rng: np.random.Generator) -> list[tuple[str, tuple[float, ...], float, float, float, float]]:
    """One group in its own frame: (shape, dims, x, y, yaw, half height) per block, rows along +x."""
    rows = 2 if rng.random() < 0.3 else 1
    per_row = int(rng.integers(2, 6))
    blocks = []
    y_cursor = 0.0
    for _ in range(rows):
        row = []
        for _ in range(per_row):
            shape = PACKED_SHAPES[int(rng.integers(len(PACKED_SHAPES)))]
            dims = shapes.random_block_dims(shape, rng)
            ex, ey, ez = _footprint(shapes.make_block(shape, dims))
            across = rng.random() < 0.5          # long side across the row
            if (ex >= ey) == across:
                yaw, along, width = math.pi / 2, ey, ex
            else:
                yaw, along, width = 0.0, ex, ey
            row.append((shape, dims, yaw, along, width, ez))
        row_width = max(r[4] for r in row)
        x = 0.0
        for shape, dims, yaw, along, width, ez in row:
            blocks.append((shape, dims, x + along / 2, y_cursor + row_width / 2, yaw, ez / 2))
            x += along + float(rng.uniform(*GAP))
        y_cursor += row_width + float(rng.uniform(*GAP))
    # centre the group on its own origin
    xs = [b[2] for b in blocks]
    ys = [b[3] for b in blocks]
    cx, cy = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
    return [(s, d, x - cx, y - cy, yaw, hz) for s, d, x, y, yaw, hz in blocks]


def _radius(group, shape_cache) -> float:
    """A circle around the group's footprint (centre at its origin)."""
    r = 0.0
    for shape, dims, x, y, _yaw, _hz in group:
        ex, ey, _ = shape_cache[(shape, dims)]
        r = max(r, math.hypot(x, y) + math.hypot(ex, ey) / 2)
    return r


def packed_scene(rng: np.random.Generator, half_x: float, half_y: float, margin: float,
                 block_spec, groups: int | None = None) -> Scene:
    """A packed arrangement in the workspace frame (origin at the workspace centre on the table).

    ``half_x``/``half_y``: half the workspace size (m); ``margin``: kept free inside its edge;
    ``block_spec(shape, dims)`` gives a block's ObjectSpec (colour, mass, friction; the pose is set
    here).  ``groups`` (1-3) defaults to a random count.
    A group that does not fit anywhere is left out, so a scene has at least one group.
    """
    if groups is None:
        groups = int(rng.integers(1, 4))
    if not 1 <= groups <= 3:
        raise ValueError(f"packed scene: groups: got {groups!r}, expected 1..3")
    placed: list[tuple[float, float, float]] = []   # (x, y, radius) of groups already placed
    specs: list[ObjectSpec] = []
    cache: dict = {}
    for g in range(groups):
        group = _group(rng)
        for shape, dims, *_ in group:
            if (shape, dims) not in cache:
                cache[(shape, dims)] = _footprint(shapes.make_block(shape, dims))
        radius = _radius(group, cache)
        spot = None
        for _ in range(PLACEMENT_TRIES):
            lim_x, lim_y = half_x - margin - radius, half_y - margin - radius
            if lim_x <= 0 or lim_y <= 0:
                break
            x, y = float(rng.uniform(-lim_x, lim_x)), float(rng.uniform(-lim_y, lim_y))
            if all(math.hypot(x - px, y - py) >= radius + pr + GROUP_CLEARANCE for px, py, pr in placed):
                spot = (x, y)
                break
        if spot is None:
            if g == 0:   # always a scene: the first group goes to the centre, it fits an empty table
                spot = (0.0, 0.0)
            else:
                continue
        placed.append((*spot, radius))
        psi = float(rng.uniform(0.0, math.pi))
        c, s = math.cos(psi), math.sin(psi)
        for shape, dims, x, y, yaw, hz in group:
            wx, wy = spot[0] + c * x - s * y, spot[1] + s * x + c * y
            a = (psi + yaw) / 2
            specs.append(block_spec(shape, dims).moved((wx, wy, hz + 0.0005), (0.0, 0.0, math.sin(a), math.cos(a))))
    return Scene(objects=tuple(specs), source="<packed arrangement>")
