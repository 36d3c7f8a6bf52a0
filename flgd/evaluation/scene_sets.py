"""What an evaluation runs on: scene files, random clutter of chosen objects, and named scene sets.

A ``SceneSpec`` is one row of the report.  It is either a scene file (the
project's YAML format, a preset name from sim_cell/scenes, or a VPG test case
``.txt``), loaded unchanged at the start of every run, or random clutter of
``count`` objects drawn from an object set (``sim.object_set`` syntax:
``blocks``, pybullet_data globs such as ``random_urdfs/0[0-9][0-9]/*.urdf``, or
names such as ``duck,teddy,mug``), dropped anew for every run.

Named sets (``--set``):

* ``vpg-hard``       -- VPG's 11 hand-designed hard test cases, read from a copy
  of VPG's files (``--vpg DIR``; never copied into this repository);
* ``presets``        -- the project's highly cluttered piles (sim_cell/scenes);
* ``novel-isolated`` -- each held-out novel object alone (paper Table III,
  "Isolation");
* ``novel-clutter``  -- 10 held-out novel objects mixed (Table III, "Clutter");
* ``urdf-clutter``   -- 10 objects of pybullet_data's random_urdfs/000-099
  (novel shapes that may be used for tuning);
* ``packed``         -- packed arrangements of our blocks (sim_cell.packed: rows
  laid flush, a new arrangement every run, fixed by the seed): hard cases of
  our own, for choosing between policies without VPG's scenes.

The held-out objects (duck, teddy, mug, ...: ``HELD_OUT_OBJECTS``) are never
trained or tuned on; random_urdfs are ours to use.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from flgd.config import WorkspaceConfig

__all__ = ["SceneSpec", "SceneSetError", "SCENE_SETS", "HELD_OUT_OBJECTS", "TUNING_OBJECTS", "CLUTTER_COUNT",
           "scene_from_argument", "clutter_scene", "named_set", "vpg_test_cases", "find_vpg_meshes",
           "check_scene"]

HELD_OUT_OBJECTS = ("duck", "teddy", "mug", "lego", "jenga", "soccerball", "cube_small", "sphere_small")
TUNING_OBJECTS = "random_urdfs/0[0-9][0-9]/*.urdf"
CLUTTER_COUNT = 10
SCENE_SETS = {
    "vpg-hard": "VPG's 11 hard test cases (needs --vpg DIR, a copy of VPG's files)",
    "presets": "the project's highly cluttered piles in sim_cell/scenes",
    "novel-isolated": "each held-out novel object alone: " + ", ".join(HELD_OUT_OBJECTS),
    "novel-clutter": f"{CLUTTER_COUNT} held-out novel objects mixed",
    "urdf-clutter": f"{CLUTTER_COUNT} objects of pybullet_data {TUNING_OBJECTS}",
    "packed": "packed arrangements of blocks (rows laid flush; a new one every run)",
}


class SceneSetError(ValueError):
    """A scene, object set or scene set cannot be used; the message says which and why."""


@dataclass(frozen=True)
class SceneSpec:
    name: str                         # the report row
    path: Path | None = None          # scene file (YAML or VPG .txt)
    vpg_meshes: Path | None = None    # block meshes of a VPG test case
    objects: str = ""                 # object set of random clutter
    count: int = 0                    # objects per random clutter
    group: str = ""                   # the named set it belongs to ("" = given one by one)
    packed: bool = False              # a packed arrangement of blocks, laid anew for every run

    @property
    def is_clutter(self) -> bool:
        return self.path is None and not self.packed

    def describe(self) -> str:
        if self.packed:
            return "packed arrangement of blocks"
        return str(self.path) if self.path is not None else f"{self.count} x {self.objects}"


def find_vpg_meshes(test_case: Path) -> Path | None:
    """VPG's block meshes for a test case: ``objects/blocks`` next to its ``test-cases`` folder, or one
    level up (VPG's repository keeps test cases in simulation/test-cases and meshes in objects/blocks)."""
    folder = test_case.resolve().parent
    for base in (folder.parent, folder.parent.parent):
        blocks = base / "objects" / "blocks"
        if blocks.is_dir():
            return blocks
    return None


def vpg_test_cases(vpg_dir: str | os.PathLike) -> list[Path]:
    """The test cases in a copy of VPG's files: DIR/test-cases, DIR/simulation/test-cases or DIR itself."""
    root = Path(vpg_dir)
    for folder in (root / "test-cases", root / "simulation" / "test-cases", root):
        cases = sorted(folder.glob("test-10-obj-*.txt"))
        if cases:
            return cases
    raise SceneSetError(f"--vpg {root}: no VPG test cases (test-10-obj-*.txt) in {root}/test-cases, "
                        f"{root}/simulation/test-cases or {root}")


def _scene_name(path: Path) -> str:
    return path.stem


def scene_from_argument(arg: str, vpg_meshes: str | os.PathLike | None = None, group: str = "") -> SceneSpec:
    """A scene file path or a preset name (``pile-20-a`` or ``pile-20-a.yaml``)."""
    from sim_cell.cell import PRESET_DIR

    path = Path(arg)
    if not path.exists():
        for candidate in (PRESET_DIR / arg, PRESET_DIR / f"{arg}.yaml"):
            if candidate.is_file():
                path = candidate
                break
        else:
            presets = ", ".join(p.stem for p in sorted(PRESET_DIR.glob("*.yaml")))
            raise SceneSetError(f"scene {arg}: file not found (and not a preset name; presets: {presets})")
    if not path.is_file():
        raise SceneSetError(f"scene {arg}: not a file")
    meshes = None
    if path.suffix == ".txt":
        meshes = Path(vpg_meshes) if vpg_meshes is not None else find_vpg_meshes(path)
        if meshes is None:
            raise SceneSetError(f"VPG test case {path}: block meshes not found in objects/blocks next to or "
                                "above its folder; pass --vpg-meshes DIR (VPG's objects/blocks)")
        if not meshes.is_dir():
            raise SceneSetError(f"--vpg-meshes {meshes}: not a directory")
    elif path.suffix not in (".yaml", ".yml"):
        raise SceneSetError(f"scene {path}: expected a .yaml scene file or a VPG test case .txt, "
                            f"got a {path.suffix or 'suffix-less'} file")
    return SceneSpec(name=_scene_name(path), path=path, vpg_meshes=meshes, group=group)


def clutter_scene(objects: str, count: int, name: str | None = None, group: str = "") -> SceneSpec:
    """Random clutter of ``count`` objects of the object set ``objects`` (checked now)."""
    from sim_cell.objects import resolve_object_set

    if not isinstance(count, int) or isinstance(count, bool) or not 1 <= count <= 60:
        raise SceneSetError(f"--count: got {count!r}, expected an integer 1..60")
    try:
        resolve_object_set(objects)
    except ValueError as exc:
        raise SceneSetError(f"--objects {objects!r}: {exc}") from None
    label = name or f"{_short(objects)} x{count}"
    return SceneSpec(name=label, objects=objects, count=count, group=group)


def _short(objects: str) -> str:
    text = re.sub(r"\s+", "", objects)
    return text if len(text) <= 28 else text[:25] + "..."


def named_set(name: str, vpg_dir: str | os.PathLike | None = None, count: int = CLUTTER_COUNT) -> list[SceneSpec]:
    """The scenes of a named set (see the module doc)."""
    if name == "vpg-hard":
        if vpg_dir is None:
            raise SceneSetError("--set vpg-hard needs --vpg DIR (a copy of VPG's test cases and block meshes)")
        return [scene_from_argument(str(p), group=name) for p in vpg_test_cases(vpg_dir)]
    if name == "presets":
        from sim_cell.cell import preset_scenes

        return [scene_from_argument(str(p), group=name) for p in preset_scenes()]
    if name == "novel-isolated":
        return [clutter_scene(obj, 1, name=f"{obj} alone", group=name) for obj in HELD_OUT_OBJECTS]
    if name == "novel-clutter":
        return [clutter_scene(",".join(HELD_OUT_OBJECTS), count, name=f"novel x{count}", group=name)]
    if name == "urdf-clutter":
        return [clutter_scene(TUNING_OBJECTS, count, name=f"random_urdfs x{count}", group=name)]
    if name == "packed":
        return [SceneSpec(name="packed blocks", objects="blocks", packed=True, group=name)]
    raise SceneSetError(f"--set: got {name!r}, expected one of {', '.join(SCENE_SETS)}")


def _urdf_file(name: str) -> Path:
    """Where the simulator looks for a scene's ``urdf:`` entry: an absolute path, else under
    pybullet_data, short names (``duck``) first translated -- the lookup of sim_cell.objects.spawn."""
    from sim_cell.objects import NAMED_NOVEL_OBJECTS, PYBULLET_DATA

    path = Path(name)
    return path if path.is_absolute() else PYBULLET_DATA / NAMED_NOVEL_OBJECTS.get(name, name)


# The simulator removes an object whose centre is below this height (workspace frame, m) as having
# fallen off the table (sim_cell.world's remove_outside: z > table - 0.05).
_LOWEST_Z = -0.05


def check_scene(spec: SceneSpec, workspace: WorkspaceConfig, config_source: str = "") -> int:
    """Parse a scene file without simulating it and return its object count; raises SceneSetError.

    Why: ``flgd eval`` promises that bad scene files are reported before anything is simulated.
    Besides the file's syntax this checks what would otherwise surface only mid-evaluation: every
    ``urdf:`` file exists, and every object's centre lies inside ``workspace`` (an object outside it
    would be removed as left_workspace at the first action, so the run could never complete and the
    policy would take the blame).
    """
    if spec.path is None:
        return spec.count
    from sim_cell.scenes import SceneError, load_scene

    try:
        scene = load_scene(spec.path, spec.vpg_meshes)
    except SceneError as exc:
        raise SceneSetError(str(exc)) from None
    if not scene.objects:
        why = (f"every entry is parked below the table or outside VPG's workspace ({scene.skipped} skipped)"
               if scene.skipped else "the objects list is empty")
        raise SceneSetError(f"scene {spec.path}: no objects ({why}); expected at least one")
    half_x = (workspace.x[1] - workspace.x[0]) / 2.0
    half_y = (workspace.y[1] - workspace.y[0]) / 2.0
    where = f" of {config_source}" if config_source else ""
    for i, obj in enumerate(scene.objects):
        label = f"scene {spec.path}: objects[{i}] ({obj.label})"
        if obj.urdf:
            urdf = _urdf_file(obj.urdf)
            if not urdf.is_file():
                raise SceneSetError(f"{label}: urdf {obj.urdf!r}: file {urdf} not found (expected an absolute "
                                    "path, a path under pybullet_data or a short name such as duck)")
        x, y, z = obj.position
        if not (-half_x <= x <= half_x and -half_y <= y <= half_y and z > _LOWEST_Z):
            raise SceneSetError(
                f"{label}: position [{x:g}, {y:g}, {z:g}] (m, workspace frame) is outside the workspace{where}: "
                f"expected x in [{-half_x:g}, {half_x:g}], y in [{-half_y:g}, {half_y:g}], z > {_LOWEST_Z:g} "
                f"(workspace x {list(workspace.x)}, y {list(workspace.y)} in the base frame); the simulator "
                "would remove it at the first action and the run could never complete")
    return len(scene.objects)
