"""Scene making for the simulated cell: random drops (VPG-style), packed rows, scene files.

Each function lays out the objects of one cell's ``World`` (clearing it first); the random parts
come from the cell's ``Randomiser`` and its scene generator, drawn in a fixed order, so that a seed
gives the same scenes.  The functions return the scene's kind for the logs ("random 20", "packed 9",
"scene pile-20-a (20)").
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pybullet as p

from sim_cell import objects, packed, scenes
from sim_cell.randomisation import Randomiser
from sim_cell.stability import Unstable
from sim_cell.world import World

PRESET_DIR = Path(__file__).resolve().parent / "scenes"
DROP_MARGIN = 0.05          # m inside the workspace edge where random objects are dropped
# A dropped scene is stepped until every object is still (the camera and the first grasp must not
# meet a block still rolling or rocking; one at the edge rolled out during the first action, counted
# as "lost"), at most this long after the fixed 0.5 s settle.
MAX_EXTRA_SETTLE = 2.0      # s


def preset_scenes() -> list[Path]:
    """The highly cluttered scenes shipped in sim_cell/scenes/."""
    return sorted(PRESET_DIR.glob("*.yaml"))


def make_packed(world: World, randomiser: Randomiser, groups: int | None, fallback_count: int) -> str:
    """A packed arrangement (sim_cell.packed): rows of blocks laid flush; one that is unstable
    gives way to ``fallback_count`` dropped objects."""
    world.clear()
    randomiser.randomise_domain(world.table)
    ws = world.ws
    scene = packed.packed_scene(randomiser.rng, (ws.x[1] - ws.x[0]) / 2, (ws.y[1] - ws.y[0]) / 2,
                                DROP_MARGIN - 0.02, randomiser.block_spec, groups)
    origin = scenes.workspace_origin(ws)
    packed_ok = True
    try:
        for spec in scene.objects:
            world.add(spec.moved(np.asarray(spec.position) + origin, spec.orientation))
        world.settle(0.25)
    except Unstable:   # counted by settle; a dropped scene instead, as reset_scene would
        world.clear()
        drop_random_objects(world, randomiser, fallback_count)
        packed_ok = False
    world.remove_outside()
    world.stats["scenes"] += 1
    return f"packed {len(world.objects)}" if packed_ok else f"random {fallback_count}"


def make_clutter(world: World, randomiser: Randomiser, n: int, spread: float | None) -> str:
    """``n`` random objects dropped within +-``spread`` m of the workspace centre (None = anywhere)."""
    world.clear()
    randomiser.randomise_domain(world.table)
    drop_random_objects(world, randomiser, n, spread)
    world.stats["scenes"] += 1
    return f"random {n}"


def drop_random_objects(world: World, randomiser: Randomiser, n: int, spread: float | None = None) -> None:
    """Drop ``n`` objects one after another at random places, VPG-style, and let them settle."""
    rng, ws = randomiser.rng, world.ws
    centre = scenes.workspace_origin(ws)
    attempts = 0
    while len(world.objects) < n and attempts < 3:
        attempts += 1
        for _ in range(n - len(world.objects)):
            spec = randomiser.random_spec()
            if spread is None:
                x = rng.uniform(ws.x[0] + DROP_MARGIN, ws.x[1] - DROP_MARGIN)
                y = rng.uniform(ws.y[0] + DROP_MARGIN, ws.y[1] - DROP_MARGIN)
            else:
                x = centre[0] + rng.uniform(-spread, spread)
                y = centre[1] + rng.uniform(-spread, spread)
            top = max([ws.z[0]] + [objects.body_aabb(b, world.client)[1][2] for b in world.objects])
            z = top + 0.06
            q = p.getQuaternionFromEuler([float(v) for v in rng.uniform(-math.pi, math.pi, 3)])
            world.add(spec.moved((x, y, z), q))
            world.step(int(0.12 / world.dt))
        try:
            world.step(int(0.5 / world.dt))
            world.settle_until_still(MAX_EXTRA_SETTLE)
        except Unstable:
            world.stats["unstable_resets"] += 1
            world.clear()
            continue
        world.remove_outside()


def read_scene(scene: str | Path | scenes.Scene, vpg_meshes: str | Path | None) -> scenes.Scene:
    """A Scene, a scene YAML file, or a VPG test case .txt; relative names are looked up in sim_cell/scenes/ too."""
    if isinstance(scene, scenes.Scene):
        return scene
    path = Path(scene)
    if not path.exists() and (PRESET_DIR / path).exists():
        path = PRESET_DIR / path
    return scenes.load_scene(path, vpg_meshes)


def place_scene(world: World, scene: scenes.Scene) -> str:
    """The objects of ``scene`` at their poses; raises SceneError (and leaves no objects) when they do not fit."""
    world.clear()
    origin = scenes.workspace_origin(world.ws)
    try:
        for spec in scene.objects:
            placed = spec.moved(np.asarray(spec.position) + origin, spec.orientation)
            world.add(placed)
        world.settle(0.25)
    except (Unstable, ValueError) as exc:
        world.clear()
        raise scenes.SceneError(f"scene {scene.source or '<in memory>'}: {exc}") from None
    world.stats["scenes"] += 1
    return f"scene {Path(scene.source).stem if scene.source else '<in memory>'} ({len(world.objects)})"


def current_scene(world: World) -> scenes.Scene:
    """The world's objects and their poses as a scene (workspace frame)."""
    origin = scenes.workspace_origin(world.ws)
    out = []
    for obj in world.objects.values():
        pos, orn = p.getBasePositionAndOrientation(obj.body, physicsClientId=world.client)
        out.append(obj.spec.moved(np.asarray(pos) - origin, orn))
    return scenes.Scene(objects=tuple(out))
