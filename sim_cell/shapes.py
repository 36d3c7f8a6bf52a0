"""Procedural toy blocks in the spirit of VPG's set: extruded polygons of 2.5-10 cm.

Every shape is a prism: one or more convex 2-D polygons extruded by a length,
then turned so that it rests on a flat face.  That gives an exact visual mesh
(triangulated here) and a collision model pybullet handles well: a single
convex hull, or a compound of boxes for the box-like and concave shapes (the
arch's round opening is a staircase of thin boxes, < 1 mm off).  The cylinder
is the convex hull of its 24-sided visual prism, not pybullet's native
cylinder: a finger pad closing on a native cylinder can sink 15-20 mm into it
instead of being stopped (about 1 grasp in 20 at its centre), which no real
gripper does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["SHAPES", "BlockGeometry", "make_block", "random_block_dims"]

Polygon = list[tuple[float, float]]


@dataclass(frozen=True)
class BlockGeometry:
    """A block in its own frame (origin at the bounding-box centre, resting face down).

    ``boxes``: (half_extents, centre) of box collision parts, or ``hull`` the vertices of a
    single convex collision hull.
    ``mesh_vertices`` / ``mesh_indices``: the visual triangle mesh; ``vertices`` all
    corner points (used for footprints and heights).
    """

    shape: str
    dims: tuple[float, ...]
    mesh_vertices: np.ndarray
    mesh_indices: np.ndarray
    boxes: list[tuple[tuple[float, float, float], tuple[float, float, float]]] = field(default_factory=list)
    hull: np.ndarray | None = None

    @property
    def vertices(self) -> np.ndarray:
        return self.mesh_vertices

    @property
    def extents(self) -> np.ndarray:
        return self.mesh_vertices.max(axis=0) - self.mesh_vertices.min(axis=0)


def _circle(r: float, start: float, stop: float, n: int, cx: float = 0.0, cy: float = 0.0) -> Polygon:
    return [(cx + r * math.cos(start + (stop - start) * i / n), cy + r * math.sin(start + (stop - start) * i / n))
            for i in range(n + 1)]


def _rect(x0: float, y0: float, x1: float, y1: float) -> Polygon:
    return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]


def _prism_mesh(polys: list[Polygon], length: float, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of convex polygons (u, v) extruded along w in [-length/2, length/2].

    ``axes`` maps (u, v, w) to the block frame.
    """
    verts: list[tuple[float, float, float]] = []
    tris: list[tuple[int, int, int]] = []
    for poly in polys:
        n = len(poly)
        base = len(verts)
        for (u, v) in poly:
            verts.append((u, v, -length / 2))
        for (u, v) in poly:
            verts.append((u, v, length / 2))
        for i in range(1, n - 1):
            tris.append((base, base + i + 1, base + i))          # bottom cap
            tris.append((base + n, base + n + i, base + n + i + 1))  # top cap
        for i in range(n):
            j = (i + 1) % n
            tris.append((base + i, base + j, base + n + j))
            tris.append((base + i, base + n + j, base + n + i))
    v = np.asarray(verts) @ axes.T
    return v, np.asarray(tris, dtype=np.int32)


# axis maps: polygon plane -> block frame
_XY = np.eye(3)                                                     # extrude along z (upright prism)
_XZ = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # polygon in x-z, extrude along y


def _centre(v: np.ndarray) -> np.ndarray:
    return (v.max(axis=0) + v.min(axis=0)) / 2.0


def _build(shape: str, dims: tuple[float, ...], visual: list[Polygon], length: float, axes: np.ndarray,
           boxes: list[Polygon] | None = None) -> BlockGeometry:
    mv, mi = _prism_mesh(visual, length, axes)
    c = _centre(mv)
    mv = mv - c
    box_parts = []
    hull = None
    if boxes:
        for rect in boxes:
            bv, _ = _prism_mesh([rect], length, axes)
            lo, hi = bv.min(axis=0) - c, bv.max(axis=0) - c
            box_parts.append((tuple(((hi - lo) / 2).tolist()), tuple(((hi + lo) / 2).tolist())))
    else:
        hull = mv.copy()
    return BlockGeometry(shape=shape, dims=tuple(float(d) for d in dims), mesh_vertices=mv, mesh_indices=mi,
                         boxes=box_parts, hull=hull)


def _cuboid(shape: str, lx: float, ly: float, lz: float) -> BlockGeometry:
    r = _rect(-lx / 2, -ly / 2, lx / 2, ly / 2)
    return _build(shape, (lx, ly, lz), [r], lz, _XY, boxes=[r])


def cube(a: float) -> BlockGeometry:
    return _cuboid("cube", a, a, a)


def bar(length: float, width: float, height: float) -> BlockGeometry:
    return _cuboid("bar", length, width, height)


def plate(length: float, width: float, height: float) -> BlockGeometry:
    return _cuboid("plate", length, width, height)


def cylinder(radius: float, height: float) -> BlockGeometry:
    poly = _circle(radius, 0.0, 2 * math.pi, 24)[:-1]
    return _build("cylinder", (radius, height), [poly], height, _XY)


def half_cylinder(radius: float, length: float) -> BlockGeometry:
    """Lies on its flat face, the round side up."""
    poly = _circle(radius, 0.0, math.pi, 16)
    return _build("half_cylinder", (radius, length), [poly], length, _XZ)


def triangular_prism(base: float, height: float, length: float) -> BlockGeometry:
    poly = [(-base / 2, 0.0), (base / 2, 0.0), (0.0, height)]
    return _build("triangular_prism", (base, height, length), [poly], length, _XZ)


def half_disk(radius: float, thickness: float) -> BlockGeometry:
    """A flat semicircular plate lying on one of its faces."""
    poly = _circle(radius, 0.0, math.pi, 16)
    return _build("half_disk", (radius, thickness), [poly], thickness, _XY)


def hexagonal_prism(radius: float, height: float) -> BlockGeometry:
    poly = _circle(radius, 0.0, 2 * math.pi, 6)[:-1]
    return _build("hexagonal_prism", (radius, height), [poly], height, _XY)


def arch(length: float, depth: float, height: float, opening: float) -> BlockGeometry:
    """A bridge: a bar of ``length`` x ``height`` with a half-circle opening of radius
    ``opening`` cut from the middle of its underside, ``depth`` thick."""
    n = 12
    visual: list[Polygon] = [_rect(-length / 2, 0.0, -opening, height), _rect(opening, 0.0, length / 2, height)]
    arc = _circle(opening, math.pi, 0.0, n)
    for (u0, v0), (u1, v1) in zip(arc[:-1], arc[1:]):
        visual.append([(u0, v0), (u1, v1), (u1, height), (u0, height)])
    # collision staircase: each slice rests on the higher end of its arc segment
    boxes = [_rect(-length / 2, 0.0, -opening, height), _rect(opening, 0.0, length / 2, height)]
    for (u0, v0), (u1, v1) in zip(arc[:-1], arc[1:]):
        boxes.append(_rect(min(u0, u1), min(v0, v1), max(u0, u1), height))
    return _build("arch", (length, depth, height, opening), visual, depth, _XZ, boxes=boxes)


def l_block(arm_a: float, arm_b: float, width: float, height: float) -> BlockGeometry:
    rects = [_rect(0.0, 0.0, arm_a, width), _rect(0.0, width, width, arm_b)]
    return _build("l_block", (arm_a, arm_b, width, height), rects, height, _XY, boxes=rects)


SHAPES = ("cube", "bar", "plate", "cylinder", "half_cylinder", "triangular_prism", "arch", "half_disk",
          "hexagonal_prism", "l_block")


def random_block_dims(shape: str, rng: np.random.Generator) -> tuple[float, ...]:
    """Random dimensions (metres) of a block of ``shape``, all between 2.5 and 10 cm."""
    u = rng.uniform
    if shape == "cube":
        return (u(0.03, 0.05),)
    if shape == "bar":
        return (u(0.07, 0.10), u(0.025, 0.035), u(0.025, 0.035))
    if shape == "plate":
        return (u(0.05, 0.08), u(0.04, 0.06), u(0.02, 0.03))
    if shape == "cylinder":
        return (u(0.0125, 0.025), u(0.03, 0.06))
    if shape == "half_cylinder":
        return (u(0.02, 0.03), u(0.04, 0.07))
    if shape == "triangular_prism":
        return (u(0.04, 0.06), u(0.03, 0.045), u(0.03, 0.05))
    if shape == "arch":
        length = u(0.07, 0.10)
        return (length, u(0.03, 0.045), u(0.035, 0.05), 0.22 * length)
    if shape == "half_disk":
        return (u(0.025, 0.04), u(0.02, 0.03))
    if shape == "hexagonal_prism":
        return (u(0.0175, 0.028), u(0.03, 0.05))
    if shape == "l_block":
        return (u(0.06, 0.08), u(0.05, 0.07), u(0.025, 0.03), u(0.025, 0.035))
    raise ValueError(f"unknown block shape {shape!r}; expected one of {', '.join(SHAPES)}")


_BUILDERS = {
    "cube": cube, "bar": bar, "plate": plate, "cylinder": cylinder, "half_cylinder": half_cylinder,
    "triangular_prism": triangular_prism, "arch": arch, "half_disk": half_disk,
    "hexagonal_prism": hexagonal_prism, "l_block": l_block,
}
_ARITY = {"cube": 1, "bar": 3, "plate": 3, "cylinder": 2, "half_cylinder": 2, "triangular_prism": 3,
          "arch": 4, "half_disk": 2, "hexagonal_prism": 2, "l_block": 4}


def make_block(shape: str, dims) -> BlockGeometry:
    """The geometry of block ``shape`` with ``dims`` (see random_block_dims for their meaning)."""
    if shape not in _BUILDERS:
        raise ValueError(f"unknown block shape {shape!r}; expected one of {', '.join(SHAPES)}")
    dims = tuple(float(d) for d in dims)
    if len(dims) != _ARITY[shape] or not all(0.005 <= d <= 0.2 for d in dims):
        raise ValueError(f"block {shape!r}: got size {list(dims)!r}, expected {_ARITY[shape]} numbers "
                         f"between 0.005 and 0.2 m")
    return _BUILDERS[shape](*dims)
