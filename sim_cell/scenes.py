"""Scene files: what objects stand where, readable and writable; VPG test cases imported as they are.

Format (YAML, see scenes/README.md)::

    format: flgd-scene
    version: 1
    objects:
      - shape: cube              # or  mesh: file.obj  /  urdf: duck_vhacd.urdf
        size: [0.04]
        scale: 1.0               # mesh / urdf only
        color: [0.9, 0.2, 0.1]
        position: [0.02, -0.05, 0.02]      # m, workspace frame
        orientation: [0, 0, 0, 1]          # quaternion x y z w  (or  rpy: [r, p, y])
        mass: 0.05               # optional, kg
        friction: 0.7            # optional

The workspace frame has its origin at the centre of the workspace on the
table surface and axes parallel to the robot base frame, so a scene fits any
cell whose workspace has the same size.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from flgd.config import WorkspaceConfig
from flgd.geometry import rpy_to_matrix
from sim_cell.objects import ObjectSpec, quaternion_from_matrix
from sim_cell.shapes import SHAPES

__all__ = ["SceneError", "Scene", "load_scene", "save_scene", "load_vpg_test_case", "workspace_origin",
           "VPG_WORKSPACE_CENTRE", "VPG_MESH_FRAMES"]

FORMAT = "flgd-scene"
VERSION = 1
_KEYS = {"shape", "size", "mesh", "urdf", "scale", "color", "position", "orientation", "rpy", "mass", "friction"}


class SceneError(ValueError):
    """A scene file is unusable; the message names the file, the key, the value and what was expected."""


@dataclass(frozen=True)
class Scene:
    """Objects with poses in the workspace frame."""

    objects: tuple[ObjectSpec, ...]
    source: str = ""
    skipped: int = 0   # entries of an imported file that are not part of the scene (parked, outside)


def workspace_origin(ws: WorkspaceConfig) -> np.ndarray:
    """Base-frame position of the workspace frame's origin."""
    return np.array([(ws.x[0] + ws.x[1]) / 2.0, (ws.y[0] + ws.y[1]) / 2.0, ws.z[0]])


def _numbers(value, n: int | None, where: str, what: str, lo: float = -math.inf, hi: float = math.inf) -> tuple:
    ok = isinstance(value, (list, tuple)) and (n is None or len(value) == n) and len(value) > 0 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and lo <= v <= hi
        for v in value)
    if not ok:
        count = f"{n} " if n is not None else ""
        raise SceneError(f"{where}: got {value!r}, expected a list of {count}numbers{what}")
    return tuple(float(v) for v in value)


def _object_from_dict(entry, where: str, base_dir: Path) -> ObjectSpec:
    if not isinstance(entry, dict):
        raise SceneError(f"{where}: got {entry!r}, expected a mapping")
    unknown = set(entry) - _KEYS
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {sorted(unknown)}; valid keys: {sorted(_KEYS)}")
    kinds = [k for k in ("shape", "mesh", "urdf") if k in entry]
    if len(kinds) != 1:
        raise SceneError(f"{where}: expected exactly one of shape, mesh, urdf; got {kinds or 'none'}")
    kind = kinds[0]
    spec: dict = {}
    value = entry[kind]
    if not isinstance(value, str) or not value:
        raise SceneError(f"{where}.{kind}: got {value!r}, expected a non-empty string")
    if kind == "shape":
        if value not in SHAPES:
            raise SceneError(f"{where}.shape: got {value!r}, expected one of {', '.join(SHAPES)}")
        spec["shape"] = value
        spec["size"] = _numbers(entry.get("size"), None, f"{where}.size", " in metres (0.005-0.2)", 0.005, 0.2)
    elif kind == "mesh":
        path = Path(value)
        if not path.is_absolute():
            path = base_dir / path
        if not path.is_file():
            raise SceneError(f"{where}.mesh: file {path} not found")
        spec["mesh"] = str(path)
    else:
        spec["urdf"] = value
    if "scale" in entry:
        spec["scale"] = _numbers([entry["scale"]], 1, f"{where}.scale", " > 0", 1e-4)[0]
    if "color" in entry:
        spec["color"] = _numbers(entry["color"], 3, f"{where}.color", " in 0..1", 0.0, 1.0)
    spec["position"] = _numbers(entry.get("position"), 3, f"{where}.position", " (m, workspace frame)")
    if "orientation" in entry and "rpy" in entry:
        raise SceneError(f"{where}: give orientation or rpy, not both")
    if "orientation" in entry:
        q = np.asarray(_numbers(entry["orientation"], 4, f"{where}.orientation", " (quaternion x y z w)"))
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            raise SceneError(f"{where}.orientation: got {entry['orientation']!r}, expected a unit quaternion "
                             f"(norm {norm:.4f})")
        spec["orientation"] = tuple((q / norm).tolist())
    elif "rpy" in entry:
        rpy = _numbers(entry["rpy"], 3, f"{where}.rpy", " (radians)")
        spec["orientation"] = quaternion_from_matrix(rpy_to_matrix(*rpy))
    for key, lo in (("mass", 1e-4), ("friction", 0.0)):
        if key in entry:
            spec[key] = _numbers([entry[key]], 1, f"{where}.{key}", f" >= {lo}", lo)[0]
    return ObjectSpec(**spec)


def load_scene(path: str | os.PathLike, vpg_meshes: str | os.PathLike | None = None) -> Scene:
    """Read a scene file: ``.yaml``/``.yml`` in this format, or a VPG test case (``.txt``).

    For a VPG file the block meshes are looked up in ``vpg_meshes`` (default: the
    ``objects/blocks`` folder next to the file's ``test-cases`` folder).
    """
    src = Path(path)
    if src.suffix == ".txt":
        return load_vpg_test_case(src, vpg_meshes)
    try:
        data = yaml.safe_load(src.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SceneError(f"scene {src}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"scene {src}: cannot read ({exc})") from None
    except yaml.YAMLError as exc:
        raise SceneError(f"scene {src}: invalid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise SceneError(f"scene {src}: expected a mapping with 'format' and 'objects'")
    if data.get("format") != FORMAT or data.get("version") != VERSION:
        raise SceneError(f"scene {src}: format/version: got {data.get('format')!r}/{data.get('version')!r}, "
                         f"expected {FORMAT!r}/{VERSION}")
    entries = data.get("objects")
    if not isinstance(entries, list):
        raise SceneError(f"scene {src}: objects: got {entries!r}, expected a list")
    objs = tuple(_object_from_dict(e, f"scene {src}: objects[{i}]", src.parent) for i, e in enumerate(entries))
    return Scene(objects=objs, source=str(src))


def save_scene(scene: Scene, path: str | os.PathLike) -> None:
    """Write ``scene`` (poses in the workspace frame); mesh paths relative to the file when below it."""
    dst = Path(path)
    entries = []
    for o in scene.objects:
        e: dict = {}
        if o.shape:
            e["shape"] = o.shape
            e["size"] = [round(v, 5) for v in o.size]
        elif o.mesh:
            mesh = Path(o.mesh).resolve()
            try:
                e["mesh"] = str(mesh.relative_to(dst.parent.resolve()))
            except ValueError:
                e["mesh"] = str(mesh)
            e["scale"] = o.scale
        else:
            e["urdf"] = o.urdf
            e["scale"] = round(o.scale, 5)
        e["color"] = [round(v, 4) for v in o.color]
        e["position"] = [round(v, 5) for v in o.position]
        e["orientation"] = [round(v, 6) for v in o.orientation]
        if o.mass is not None:
            e["mass"] = round(o.mass, 5)
        if o.friction is not None:
            e["friction"] = round(o.friction, 4)
        entries.append(e)
    text = yaml.safe_dump({"format": FORMAT, "version": VERSION, "objects": entries}, sort_keys=False,
                          default_flow_style=None)
    tmp = dst.with_suffix(dst.suffix + ".tmp")
    tmp.write_text("# flgd scene: poses in the workspace frame (origin at the workspace centre on the table)\n"
                   + text, encoding="utf-8")
    os.replace(tmp, dst)


# ----------------------------------------------------------------------------- VPG test cases

# VPG's simulated workspace: x [-0.724, -0.276], y [-0.224, 0.224], table at z = 0.
VPG_WORKSPACE_CENTRE = np.array([-0.5, 0.0, 0.0])
VPG_WORKSPACE_HALF = np.array([0.224, 0.224])
# Entries below this z are parked out of the scene (VPG's files use z = -726 and alike).
_PARKED_Z = -0.5


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# V-REP re-framed some meshes on import: the pose in a test case is that of V-REP's frame,
# whose axes are these fixed rotations of the OBJ file's axes (v_vrep = F @ v_obj).  Measured
# on the 11 test cases: with them every instance of a mesh rests flat within ~1 mm of the table
# (or on another block).  Mesh 2 is a rounded square plate whose sides are turned 15.4 deg in
# the file; the others are axis permutations.  Meshes not listed need no fix.
VPG_MESH_FRAMES = {
    "0.obj": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    "1.obj": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    "2.obj": _rx(math.radians(-15.4)),
    "7.obj": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "8.obj": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
}


def load_vpg_test_case(path: str | os.PathLike, mesh_dir: str | os.PathLike | None = None) -> Scene:
    """Import a VPG test case (``MESH R G B X Y Z A B G`` per line) unchanged.

    Poses are in VPG's robot frame; V-REP Euler angles compose as R = Rx(A) Ry(B) Rz(G).
    Entries parked below the table and objects whose centre lies outside VPG's
    workspace are not part of the scene (counted in ``Scene.skipped``).
    """
    src = Path(path)
    blocks = Path(mesh_dir) if mesh_dir is not None else src.resolve().parent.parent / "objects" / "blocks"
    try:
        lines = src.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise SceneError(f"VPG test case {src}: cannot read ({exc})") from None
    objs: list[ObjectSpec] = []
    skipped = 0
    for n, line in enumerate(lines, 1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != 10:
            raise SceneError(f"VPG test case {src}, line {n}: got {len(tokens)} fields, expected 10 "
                             f"(MESH R G B X Y Z A B G)")
        mesh = tokens[0]
        try:
            r, g, b, x, y, z, ea, eb, eg = (float(t) for t in tokens[1:])
        except ValueError:
            raise SceneError(f"VPG test case {src}, line {n}: expected numbers after the mesh name, "
                             f"got {tokens[1:]!r}") from None
        if z < _PARKED_Z:
            skipped += 1
            continue
        if np.any(np.abs(np.array([x, y]) - VPG_WORKSPACE_CENTRE[:2]) > VPG_WORKSPACE_HALF):
            skipped += 1
            continue
        mesh_path = blocks / mesh
        if not mesh_path.is_file():
            raise SceneError(f"VPG test case {src}, line {n}: mesh {mesh_path} not found "
                             f"(pass the folder of VPG's block meshes)")
        r_vrep = _rx(ea) @ _ry(eb) @ _rz(eg)
        r_mesh = r_vrep @ VPG_MESH_FRAMES.get(mesh, np.eye(3))
        pos = np.array([x, y, z]) - VPG_WORKSPACE_CENTRE
        objs.append(ObjectSpec(mesh=str(mesh_path.resolve()), color=(r, g, b),
                               position=tuple(pos.tolist()), orientation=quaternion_from_matrix(r_mesh)))
    return Scene(objects=tuple(objs), source=str(src), skipped=skipped)
