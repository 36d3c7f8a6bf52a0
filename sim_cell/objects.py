"""Putting objects into a pybullet world: procedural blocks, OBJ meshes and URDF models.

One ``ObjectSpec`` describes an object the way a scene file does (what it is,
its size, colour and pose in the base frame); ``spawn`` turns it into a body
and remembers its corner points, which the cell uses for footprints, heights
and the scripted oracle.
"""

from __future__ import annotations

import glob
import math
import os
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import pybullet as p
import pybullet_data

from sim_cell import shapes

__all__ = ["ObjectSpec", "SpawnedObject", "spawn", "read_obj", "resolve_object_set", "resolve_object_groups",
           "draw_object_kind", "PYBULLET_DATA",
           "NAMED_NOVEL_OBJECTS", "body_aabb", "natural_size", "natural_extents", "graspable_scale",
           "quaternion_from_matrix", "MESH_PREFIX", "mesh_volume"]

PYBULLET_DATA = Path(pybullet_data.getDataPath())
GRASPABLE_FRACTION = 0.9  # a novel object's worst-case width across the fingers is at most this share of the opening
# Short names for pybullet_data models usable in sim.object_set.
NAMED_NOVEL_OBJECTS = {
    "duck": "duck_vhacd.urdf",
    "teddy": "teddy_vhacd.urdf",
    "mug": "objects/mug.urdf",
    "lego": "lego/lego.urdf",
    "jenga": "jenga/jenga.urdf",
    "cube_small": "cube_small.urdf",
    "sphere_small": "sphere_small.urdf",
    "soccerball": "soccerball.urdf",
}
MESH_PREFIX = "mesh:"  # object kinds that are OBJ files, as resolve_object_groups names them
# A mesh whose faces leave a vertex this far on the outside of some face plane is concave.
_CONCAVITY = 0.003   # m
_SLABS = 12          # convex slabs of a concave mesh
# Rolling resistance (m, pybullet's rollingFriction; times the other surface's friction it is the
# lever arm of the rolling resistance, here about 1 mm as for wood on wood).  With 0.1 mm a
# half-disk on its rim or a half-cylinder on its round side rocked for seconds and a cylinder on
# its side rolled on: 9 objects of 6 fresh 20-block scenes still moved when the first picture was
# taken, some rolled out of the workspace during the first grasp, and grasps closed on rocking blocks.
ROLLING_FRICTION = 0.002
SPINNING_FRICTION = 0.001  # m, torsional friction about the contact normal


@dataclass(frozen=True)
class ObjectSpec:
    """One object: exactly one of ``shape`` (procedural block), ``mesh`` (OBJ file) or ``urdf``.

    Pose in the robot base frame: ``position`` (m) and ``orientation`` (quaternion x, y, z, w).
    ``size`` are the block dimensions (see shapes.random_block_dims), ``scale`` scales a mesh
    or URDF.  ``mass`` (kg) and ``friction`` are physical parameters; None = defaults.
    """

    shape: str = ""
    size: tuple[float, ...] = ()
    mesh: str = ""
    urdf: str = ""
    scale: float = 1.0
    color: tuple[float, float, float] = (0.6, 0.6, 0.6)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    mass: float | None = None
    friction: float | None = None

    @property
    def kind(self) -> str:
        return "block" if self.shape else "mesh" if self.mesh else "urdf"

    @property
    def label(self) -> str:
        return self.shape or os.path.basename(self.mesh or self.urdf)

    def moved(self, position, orientation) -> "ObjectSpec":
        return replace(self, position=tuple(float(v) for v in position),
                       orientation=tuple(float(v) for v in orientation))


@dataclass
class SpawnedObject:
    body: int
    spec: ObjectSpec
    local_points: np.ndarray  # corner points in the body frame, for footprints
    extra: dict = field(default_factory=dict)

    def world_points(self, client: int) -> np.ndarray:
        pos, orn = p.getBasePositionAndOrientation(self.body, physicsClientId=client)
        r = np.asarray(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
        return self.local_points @ r.T + np.asarray(pos)


def read_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n x 3) and triangles (m x 3) of a Wavefront OBJ file (polygons fanned)."""
    verts, tris = [], []
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise ValueError(f"mesh {path}: cannot read ({exc})") from None
    for line in text.splitlines():
        t = line.split()
        if not t:
            continue
        if t[0] == "v":
            verts.append([float(x) for x in t[1:4]])
        elif t[0] == "f":
            idx = [int(x.split("/")[0]) for x in t[1:]]
            idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
            for k in range(1, len(idx) - 1):
                tris.append((idx[0], idx[k], idx[k + 1]))
    if not verts or not tris:
        raise ValueError(f"mesh {path}: expected an OBJ file with vertices and faces")
    return np.asarray(verts, dtype=float), np.asarray(tris, dtype=np.int64)


def _concavity(v: np.ndarray, tris: np.ndarray) -> float:
    """How far some vertex lies on the far side of a face plane (0 for a convex mesh)."""
    worst = 0.0
    for a, b, c in tris:
        n = np.cross(v[b] - v[a], v[c] - v[a])
        area2 = float(np.linalg.norm(n))
        if area2 < 4e-5:  # sliver faces have unreliable planes
            continue
        d = (v - v[a]) @ (n / area2)
        worst = max(worst, min(float(d.max()), float(-d.min())))
    return worst


def _slabs(v: np.ndarray, tris: np.ndarray, count: int) -> list[np.ndarray]:
    """Cut a mesh into ``count`` slabs along its longest extent; the points of each slab
    (its vertices plus where edges cross the cut planes).  Their convex hulls approximate a
    mesh that is concave across that axis only (an arch, a U)."""
    ext = v.max(axis=0) - v.min(axis=0)
    axis = int(np.argmax(ext))
    cuts = np.linspace(v[:, axis].min(), v[:, axis].max(), count + 1)
    edges = {tuple(sorted((int(a), int(b)))) for t in tris for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    crossings: list[list[np.ndarray]] = [[] for _ in cuts]
    for a, b in edges:
        xa, xb = v[a, axis], v[b, axis]
        for k, c in enumerate(cuts):
            if (xa - c) * (xb - c) < 0:
                s = (c - xa) / (xb - xa)
                crossings[k].append(v[a] + s * (v[b] - v[a]))
    out = []
    for k in range(count):
        lo, hi = cuts[k], cuts[k + 1]
        pts = [v[(v[:, axis] >= lo - 1e-9) & (v[:, axis] <= hi + 1e-9)]]
        for j in (k, k + 1):
            if crossings[j]:
                pts.append(np.asarray(crossings[j]))
        pts_arr = np.concatenate(pts)
        if len(pts_arr) >= 4:
            out.append(pts_arr)
    return out


@lru_cache(maxsize=64)
def _mesh_parts(path: str, scale: float) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    v, tris = read_obj(path)
    v = v * scale
    if _concavity(v, tris) > _CONCAVITY:
        return tuple(_slabs(v, tris, _SLABS)), v
    return (v,), v


def body_aabb(body: int, client: int) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds of a body over all its links."""
    lo, hi = (np.asarray(x) for x in p.getAABB(body, -1, physicsClientId=client))
    for link in range(p.getNumJoints(body, physicsClientId=client)):
        a, b = p.getAABB(body, link, physicsClientId=client)
        lo, hi = np.minimum(lo, a), np.maximum(hi, b)
    return lo, hi


def _block_body(client: int, spec: ObjectSpec) -> tuple[int, np.ndarray]:
    geom = shapes.make_block(spec.shape, spec.size)
    rgba = [*spec.color, 1.0]
    vis = p.createVisualShape(p.GEOM_MESH, vertices=geom.mesh_vertices.tolist(),
                              indices=geom.mesh_indices.reshape(-1).tolist(), rgbaColor=rgba,
                              physicsClientId=client)
    if geom.boxes:
        col = p.createCollisionShapeArray([p.GEOM_BOX] * len(geom.boxes),
                                          halfExtents=[list(b[0]) for b in geom.boxes],
                                          collisionFramePositions=[list(b[1]) for b in geom.boxes],
                                          physicsClientId=client)
    else:
        col = p.createCollisionShape(p.GEOM_MESH, vertices=geom.hull.tolist(), physicsClientId=client)
    volume = _volume(geom.mesh_vertices, geom.mesh_indices)
    mass = spec.mass if spec.mass is not None else max(volume * 600.0, 0.02)  # light wood
    body = p.createMultiBody(mass, col, vis, list(spec.position), list(spec.orientation),
                             physicsClientId=client)
    return body, geom.mesh_vertices


def _volume(v: np.ndarray, tris: np.ndarray) -> float:
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    return abs(float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0)


@lru_cache(maxsize=64)
def mesh_volume(path: str, scale: float = 1.0) -> float:
    """Volume (m^3) enclosed by an OBJ mesh at ``scale``: a random mesh object's mass is density times it."""
    v, tris = read_obj(path)
    return _volume(v * scale, tris)


def _mesh_body(client: int, spec: ObjectSpec) -> tuple[int, np.ndarray]:
    path = str(Path(spec.mesh).resolve())
    parts, verts = _mesh_parts(path, float(spec.scale))
    rgba = [*spec.color, 1.0]
    vis = p.createVisualShape(p.GEOM_MESH, fileName=path, meshScale=[spec.scale] * 3, rgbaColor=rgba,
                              physicsClientId=client)
    _, tris = read_obj(path)
    total = spec.mass if spec.mass is not None else max(_volume(verts, tris) * 600.0, 0.02)
    cols = [p.createCollisionShape(p.GEOM_MESH, vertices=part.tolist(), physicsClientId=client)
            for part in parts]
    if len(cols) == 1:
        body = p.createMultiBody(total, cols[0], vis, list(spec.position), list(spec.orientation),
                                 physicsClientId=client)
        return body, verts
    # Concave: convex slabs as fixed links of one body, mass by slab extent.
    weights = np.array([np.prod(np.maximum(part.max(0) - part.min(0), 1e-4)) for part in parts])
    masses = total * weights / weights.sum()
    n = len(cols) - 1
    body = p.createMultiBody(float(masses[0]), cols[0], vis, list(spec.position), list(spec.orientation),
                             linkMasses=masses[1:].tolist(), linkCollisionShapeIndices=cols[1:],
                             linkVisualShapeIndices=[-1] * n, linkPositions=[[0, 0, 0]] * n,
                             linkOrientations=[[0, 0, 0, 1]] * n,
                             linkInertialFramePositions=[part.mean(axis=0).tolist() for part in parts[1:]],
                             linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
                             linkParentIndices=[0] * n, linkJointTypes=[p.JOINT_FIXED] * n,
                             linkJointAxis=[[0, 0, 1]] * n, physicsClientId=client)
    return body, verts


def _urdf_path(name: str) -> Path:
    path = Path(name)
    if not path.is_absolute():
        path = PYBULLET_DATA / NAMED_NOVEL_OBJECTS.get(name, name)
    if not path.is_file():
        raise ValueError(f"object URDF {name!r}: file {path} not found")
    return path


def _urdf_body(client: int, spec: ObjectSpec) -> tuple[int, np.ndarray]:
    path = _urdf_path(spec.urdf)
    body = p.loadURDF(str(path), list(spec.position), [0, 0, 0, 1], globalScaling=float(spec.scale),
                      physicsClientId=client)
    if body < 0:
        raise ValueError(f"object URDF {spec.urdf!r}: pybullet could not load {path}")
    if spec.color and spec.color != (0.6, 0.6, 0.6):
        p.changeVisualShape(body, -1, rgbaColor=[*spec.color, 1.0], physicsClientId=client)
    if spec.mass is not None:
        p.changeDynamics(body, -1, mass=spec.mass, physicsClientId=client)
    # corner points: the bounding box in the body frame, measured as loaded
    lo, hi = body_aabb(body, client)
    pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=client)
    r = np.asarray(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    p.resetBasePositionAndOrientation(body, list(spec.position), list(spec.orientation), physicsClientId=client)
    return body, (corners - np.asarray(pos)) @ r


def spawn(client: int, spec: ObjectSpec) -> SpawnedObject:
    """Create the body of ``spec`` in ``client``; raises ValueError naming what is wrong."""
    kinds = [k for k in (spec.shape, spec.mesh, spec.urdf) if k]
    if len(kinds) != 1:
        raise ValueError(f"object {spec!r}: expected exactly one of shape, mesh, urdf")
    if spec.shape:
        body, pts = _block_body(client, spec)
    elif spec.mesh:
        body, pts = _mesh_body(client, spec)
    else:
        body, pts = _urdf_body(client, spec)
    if spec.friction is not None:
        for link in range(-1, p.getNumJoints(body, physicsClientId=client)):
            p.changeDynamics(body, link, lateralFriction=spec.friction, physicsClientId=client)
    for link in range(-1, p.getNumJoints(body, physicsClientId=client)):
        p.changeDynamics(body, link, spinningFriction=SPINNING_FRICTION, rollingFriction=ROLLING_FRICTION,
                         physicsClientId=client)
    return SpawnedObject(body=body, spec=spec, local_points=np.asarray(pts, dtype=float))


def resolve_object_groups(object_set: str) -> list[list[str]]:
    """The object kinds named by ``sim.object_set``, one group per comma-separated item.

    A random object first draws an item, then a kind within it, so ``'blocks,random_urdfs/0??/*.urdf'``
    is half blocks and half URDF models however many files the glob matches.  Items: 'blocks' (the
    procedural shapes, ``shapes.SHAPES``), a block shape, a short name (``NAMED_NOVEL_OBJECTS``), a
    URDF path or glob relative to pybullet_data, e.g. 'random_urdfs/00[0-9]/*.urdf', or an OBJ mesh
    path or glob ending in '.obj' (absolute, or relative to pybullet_data; used at its stored size, in
    metres), e.g. VPG's toy blocks '/data/vpg/objects/blocks/*.obj' (kind 'mesh:<absolute path>').
    Each item must match something.
    """
    text = object_set.strip()
    if text == "":
        text = "blocks"
    groups: list[list[str]] = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        if item == "blocks":
            groups.append([f"block:{s}" for s in shapes.SHAPES])
            continue
        if item in shapes.SHAPES:
            groups.append([f"block:{item}"])
            continue
        if item in NAMED_NOVEL_OBJECTS:
            groups.append([NAMED_NOVEL_OBJECTS[item]])
            continue
        base = Path(os.path.expanduser(item))
        base = base if base.is_absolute() else PYBULLET_DATA / base
        if item.lower().endswith(".obj"):
            meshes = sorted(m for m in glob.glob(str(base)) if os.path.isfile(m))
            if not meshes:
                raise ValueError(f"sim.object_set: item {item!r} matches no OBJ file ({base}); give an absolute "
                                 f"path or glob such as '/data/vpg/objects/blocks/*.obj'")
            groups.append([MESH_PREFIX + str(Path(m).resolve()) for m in meshes])
            continue
        matches = sorted(glob.glob(str(base)))
        matches = [m for m in matches if m.endswith(".urdf")]
        if not matches:
            raise ValueError(f"sim.object_set: item {item!r} matches no URDF under {PYBULLET_DATA} "
                             f"(expected 'blocks', a block shape, one of {', '.join(NAMED_NOVEL_OBJECTS)}, "
                             f"or a glob such as 'random_urdfs/0[0-4]?/*.urdf')")
        groups.append([os.path.relpath(m, PYBULLET_DATA) if m.startswith(str(PYBULLET_DATA)) else m
                       for m in matches])
    if not groups:
        raise ValueError(f"sim.object_set: got {object_set!r}, expected at least one object kind")
    return groups


def resolve_object_set(object_set: str) -> list[str]:
    """Every object kind named by ``sim.object_set`` (see ``resolve_object_groups``), in order."""
    return [kind for group in resolve_object_groups(object_set) for kind in group]


def draw_object_kind(groups: list[list[str]], rng: np.random.Generator) -> str:
    """One kind: an item uniformly, then a kind of it uniformly.

    A draw the choice does not need is skipped, so a single item, or a list of single kinds,
    uses the random stream exactly as one uniform draw over all kinds did before groups existed.
    """
    group = groups[int(rng.integers(len(groups)))] if len(groups) > 1 else groups[0]
    return group[int(rng.integers(len(group)))] if len(group) > 1 else group[0]


def natural_extents(urdf: str, client: int) -> tuple[float, float, float]:
    """Extents of a URDF model at scale 1, as loaded (axis-aligned box), smallest first."""
    body = p.loadURDF(str(_urdf_path(urdf)), [0, 0, 5], physicsClientId=client)
    lo, hi = body_aabb(body, client)
    p.removeBody(body, physicsClientId=client)
    a, b, c = sorted(float(v) for v in (hi - lo))
    return a, b, c


def natural_size(urdf: str, client: int) -> float:
    """Largest extent of a URDF model at scale 1."""
    return natural_extents(urdf, client)[2]


def graspable_scale(extents: tuple[float, float, float], largest: float, open_width: float,
                    rotations: int = 16) -> float:
    """The scale that gives the model the ``largest`` extent (m), reduced if the gripper could not span it.

    Why: an object lying on its largest face shows its middle extent as the
    narrower horizontal side, which the fingers must close across; with that
    side wider than the opening less a few mm on either side no grasp can
    succeed, and the evaluation would count the object's size, not the policy.
    The gripper turns in steps of 2*pi/``rotations``, so the best grasp can still
    be half a step off the object's axes; a square side ``b`` then measures
    ``b (cos + sin)(pi/rotations)`` across the fingers (1.18 b at 16 rotations).
    pybullet's cube_small drawn at 7.65 cm (90 % of the RG2's 8.5 cm) was 9.0 cm
    across at that error, so a random yaw left it ungraspable more often than not.
    Only such objects are shrunk, until that worst-case width is 90 % of the
    opening; anything a grasp at the nearest rotation can span keeps its drawn size.
    """
    scale = largest / extents[2]
    half_step = math.pi / max(1, rotations)
    worst_width = extents[1] * (math.cos(half_step) + math.sin(half_step))
    return min(scale, GRASPABLE_FRACTION * open_width / worst_width)


def quaternion_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix."""
    m = np.asarray(r, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)
    n = math.sqrt(sum(x * x for x in q))
    return tuple(x / n for x in q)  # type: ignore[return-value]
