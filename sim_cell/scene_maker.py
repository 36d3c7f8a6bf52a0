"""Scene making for the simulated cell: random drops (VPG-style), packed rows, scene files.

Each function lays out the objects of one ``SimCell``, under its lock, through the cell's own world
operations (clear, add, step, settle, remove what left the workspace), which stay with the cell because
plan execution uses them too.  The random parts come from the cell's ``Randomiser`` and its scene
generator, drawn in a fixed order, so that a seed gives the same scenes.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pybullet as p

from sim_cell import objects, packed, scenes
from sim_cell.stability import Unstable

if TYPE_CHECKING:
    from sim_cell.cell import SimCell

PRESET_DIR = Path(__file__).resolve().parent / "scenes"
DROP_MARGIN = 0.05          # m inside the workspace edge where random objects are dropped
# A dropped scene is stepped until every object is still (the camera and the first grasp must not
# meet a block still rolling or rocking; one at the edge rolled out during the first action, counted
# as "lost"), at most this long after the fixed 0.5 s settle.
MAX_EXTRA_SETTLE = 2.0      # s


def preset_scenes() -> list[Path]:
    """The highly cluttered scenes shipped in sim_cell/scenes/."""
    return sorted(PRESET_DIR.glob("*.yaml"))


def make_packed(cell: SimCell, groups: int | None) -> int:
    """Replace ``cell``'s objects by a packed arrangement (see ``SimCell.make_packed``); returns the count."""
    cell._clear_objects()
    _randomise_domain(cell)
    ws = cell._ws
    scene = packed.packed_scene(cell._randomiser.rng, (ws.x[1] - ws.x[0]) / 2, (ws.y[1] - ws.y[0]) / 2,
                                DROP_MARGIN - 0.02, cell._randomiser.block_spec, groups)
    origin = scenes.workspace_origin(ws)
    packed_ok = True
    try:
        for spec in scene.objects:
            cell._add(spec.moved(np.asarray(spec.position) + origin, spec.orientation))
        cell._settle(0.25)
    except Unstable:   # counted by _settle; a dropped scene instead, as reset_scene would
        cell._clear_objects()
        drop_random_objects(cell, cell._object_count)
        packed_ok = False
    cell._remove_outside()
    cell.stats["scenes"] += 1
    cell.scene_kind = f"packed {len(cell._objects)}" if packed_ok else f"random {cell._object_count}"
    return len(cell._objects)


def make_clutter(cell: SimCell, n: int, spread: float | None) -> int:
    """Replace ``cell``'s objects by ``n`` dropped ones (see ``SimCell.make_clutter``); returns the count."""
    cell._clear_objects()
    _randomise_domain(cell)
    drop_random_objects(cell, n, spread)
    cell.stats["scenes"] += 1
    cell.scene_kind = f"random {n}"
    return len(cell._objects)


def _randomise_domain(cell: SimCell) -> None:
    cell._light = cell._randomiser.randomise_domain(cell._table, cell._light)


def drop_random_objects(cell: SimCell, n: int, spread: float | None = None) -> None:
    """Drop ``n`` objects one after another at random places, VPG-style, and let them settle."""
    rng, ws = cell._randomiser.rng, cell._ws
    centre = scenes.workspace_origin(ws)
    attempts = 0
    while len(cell._objects) < n and attempts < 3:
        attempts += 1
        for _ in range(n - len(cell._objects)):
            spec = cell._randomiser.random_spec()
            if spread is None:
                x = rng.uniform(ws.x[0] + DROP_MARGIN, ws.x[1] - DROP_MARGIN)
                y = rng.uniform(ws.y[0] + DROP_MARGIN, ws.y[1] - DROP_MARGIN)
            else:
                x = centre[0] + rng.uniform(-spread, spread)
                y = centre[1] + rng.uniform(-spread, spread)
            top = max([ws.z[0]] + [objects.body_aabb(b, cell._client)[1][2] for b in cell._objects])
            z = top + 0.06
            q = p.getQuaternionFromEuler([float(v) for v in rng.uniform(-math.pi, math.pi, 3)])
            cell._add(spec.moved((x, y, z), q))
            cell._step(int(0.12 / cell._dt))
        try:
            cell._step(int(0.5 / cell._dt))
            cell._settle_until_still(MAX_EXTRA_SETTLE)
        except Unstable:
            cell.stats["unstable_resets"] += 1
            cell._clear_objects()
            continue
        cell._remove_outside()


def load_scene(cell: SimCell, scene: str | Path | scenes.Scene, vpg_meshes: str | Path | None) -> int:
    """Replace ``cell``'s objects by a scene (see ``SimCell.load_scene``); returns the number placed."""
    if not isinstance(scene, scenes.Scene):
        path = Path(scene)
        if not path.exists() and (PRESET_DIR / path).exists():
            path = PRESET_DIR / path
        scene = scenes.load_scene(path, vpg_meshes)
    cell._clear_objects()
    origin = scenes.workspace_origin(cell._ws)
    try:
        for spec in scene.objects:
            placed = spec.moved(np.asarray(spec.position) + origin, spec.orientation)
            cell._add(placed)
        cell._settle(0.25)
    except (Unstable, ValueError) as exc:
        cell._clear_objects()
        cell.scene_kind = "none"
        raise scenes.SceneError(f"scene {scene.source or '<in memory>'}: {exc}") from None
    cell.stats["scenes"] += 1
    cell.scene_kind = f"scene {Path(scene.source).stem if scene.source else '<in memory>'} ({len(cell._objects)})"
    return len(cell._objects)


def current_scene(cell: SimCell) -> scenes.Scene:
    """``cell``'s objects and their poses as a scene (workspace frame)."""
    origin = scenes.workspace_origin(cell._ws)
    out = []
    for obj in cell._objects.values():
        pos, orn = p.getBasePositionAndOrientation(obj.body, physicsClientId=cell._client)
        out.append(obj.spec.moved(np.asarray(pos) - origin, orn))
    return scenes.Scene(objects=tuple(out))
