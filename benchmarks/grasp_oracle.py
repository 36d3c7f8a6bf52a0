"""``flgd bench grasp_oracle``: the physics ceiling of grasping in sim_cell, per block shape.

A scripted oracle that knows every pose (``SimCell.object_states``) grasps one
block of each shape at the centre of its footprint, closing across its
narrowest extent (among the 8 distinct rotations of the action space; along
the extrusion axis for prisms lying on a side, across the free part of the long
arm for an L-block), through the same path as the policy: heightmap from a
rendered frame, ``plan_action``, ``check_plan``, ``execute``, the width test,
then ``plan_release``.  A grasp counts when the width test says held and the
block was carried out of the workspace.  What fails here is the simulated
physics (or the action space), not a policy: the numbers bound what any policy
can reach.

Modes: ``rest`` -- the block alone, lying on its designed face, random yaw;
``drop`` -- alone, dropped with a random 3-D orientation as in random clutter;
``clutter`` -- dropped onto a light pile of 5 random blocks; the oracle ignores
the neighbours, so grasps whose descent is stopped by a neighbour are reported
apart (placement, not physics).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import pybullet as p

from flgd.actions import Action
from flgd.clutter import grasp_reward
from flgd.config import CellConfig, load_config
from flgd.perception import base_to_pixel, frame_heightmaps
from flgd.plans import end_yaw, plan_action, plan_release
from flgd.safety import check_plan
from sim_cell import objects, shapes
from sim_cell.cell import SimCell

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "cell_config" / "sim.yaml"
MODES = ("rest", "drop", "clutter")
PRISMS_ON_A_SIDE = ("triangular_prism", "arch", "half_cylinder")  # flat parallel ends along body y


def random_block(shape: str, rng: np.random.Generator) -> tuple[objects.ObjectSpec, shapes.BlockGeometry]:
    """A block as SimCell's random clutter makes it (size, density, friction)."""
    dims = shapes.random_block_dims(shape, rng)
    geom = shapes.make_block(shape, dims)
    mass = max(float(np.prod(geom.extents)) * 0.7 * float(rng.uniform(400, 900)), 0.02)
    spec = objects.ObjectSpec(shape=shape, size=dims, color=(0.8, 0.3, 0.3), mass=mass,
                              friction=float(rng.uniform(0.4, 0.9)))
    return spec, geom


def oracle_grasp(cell: SimCell, body: int, spec: objects.ObjectSpec,
                 geom: shapes.BlockGeometry) -> tuple[float, float, float]:
    """(x, y, closing angle) of the oracle's grasp from the block's true pose."""
    pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cell._client)
    r = np.asarray(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
    if spec.shape == "l_block" and abs(r[2, 2]) > 0.9:
        a, b, w, _ = spec.size     # arm A is the rectangle (0, 0)-(a, w) of the polygon; frame at the bbox centre
        centre = np.asarray(pos) + r @ (np.array([(a + w) / 2, w / 2, 0.0]) - np.array([a / 2, b / 2, 0.0]))
        axis = r @ np.array([0.0, 1.0, 0.0])
        return float(centre[0]), float(centre[1]), math.atan2(axis[1], axis[0])
    xy = (geom.mesh_vertices @ r.T + np.asarray(pos))[:, :2]
    centre = (xy.max(axis=0) + xy.min(axis=0)) / 2

    def extent(angle: float) -> float:
        d = xy @ np.array([math.cos(angle), math.sin(angle)])
        return float(d.max() - d.min())

    angle = min((2 * math.pi * k / 16 for k in range(8)), key=extent)
    if spec.shape in PRISMS_ON_A_SIDE:
        axis = r @ np.array([0.0, 1.0, 0.0])
        along = math.atan2(axis[1], axis[0])
        if abs(axis[2]) < 0.5 and extent(along) < 0.075:
            angle = along
    return float(centre[0]), float(centre[1]), angle


def trial(cell: SimCell, cfg: CellConfig, shape: str, mode: str, rng: np.random.Generator) -> str:
    """One oracle grasp; returns 'held', 'blocked' (clutter: descent stopped above the planned
    depth by a neighbour) or what went wrong."""
    ws = cfg.workspace
    spec, geom = random_block(shape, rng)
    cx, cy = (ws.x[0] + ws.x[1]) / 2, (ws.y[0] + ws.y[1]) / 2
    if mode == "clutter":
        cell.make_clutter(5, spread=0.07)
        x, y = cx + rng.uniform(-0.05, 0.05), cy + rng.uniform(-0.05, 0.05)
        z = max([ws.z[0]] + [s.top for s in cell.object_states()]) + geom.extents[2] / 2 + 0.005
        q = p.getQuaternionFromEuler([0.0, 0.0, float(rng.uniform(-math.pi, math.pi))])
    else:
        cell.make_clutter(0)
        x, y = rng.uniform(ws.x[0] + 0.08, ws.x[1] - 0.08), rng.uniform(ws.y[0] + 0.08, ws.y[1] - 0.08)
        if mode == "rest":
            z = ws.z[0] + geom.extents[2] / 2 + 0.002
            q = p.getQuaternionFromEuler([0.0, 0.0, float(rng.uniform(-math.pi, math.pi))])
        else:
            z = ws.z[0] + 0.08
            q = p.getQuaternionFromEuler([float(v) for v in rng.uniform(-math.pi, math.pi, 3)])
    body = cell.add_object(spec.moved((x, y, z), q), settle=0.6)
    gx, gy, angle = oracle_grasp(cell, body, spec, geom)
    hm = frame_heightmaps(cell.capture(), ws, cfg.camera.depth_range)
    row, col = base_to_pixel(gx, gy, ws)
    plan = plan_action(Action("grasp", row, col, int(round(angle / (2 * math.pi / 16))) % 16), hm.height, cfg)
    lowest = [math.inf]
    run_line = cell._arm.run_line

    def watched_line(traj, stop_force=0.0, **kwargs):
        stopped = run_line(traj, stop_force, **kwargs)
        lowest[0] = min(lowest[0], float(cell._tcp()[2, 3]))
        return stopped

    cell._arm.run_line = watched_line
    try:
        before = dict(cell.stats)
        result = cell.execute(check_plan(plan, cfg))
    finally:
        del cell._arm.run_line
    width = result.widths[-1] if result.widths else math.nan
    held = grasp_reward(width, cfg.gripper) > 0
    cell.execute(check_plan(plan_release(held, cfg, carry_yaw=end_yaw(plan, cfg),
                                         width=width if math.isfinite(width) else None), cfg))
    target_out = body not in {s.body for s in cell.object_states()}
    if held and target_out and cell.stats["left_workspace"] == before["left_workspace"]:
        return "held"
    if mode == "clutter" and lowest[0] > plan.target[2] + 0.003:
        return "blocked"
    if not result.completed:
        return "plan failed: " + result.failure.split(";")[0][:60]
    return "dropped or missed" if not held else "held another block / lost"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="flgd bench grasp_oracle", description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(DEFAULT_CONFIG))
    ap.add_argument("--modes", default="rest,drop", help=f"comma list of {', '.join(MODES)}")
    ap.add_argument("--shapes", default=",".join(shapes.SHAPES))
    ap.add_argument("--trials", type=int, default=20, help="grasps per shape and mode")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    modes = [m for m in args.modes.split(",") if m]
    bad_modes = [m for m in modes if m not in MODES]
    bad_shapes = [s for s in args.shapes.split(",") if s not in shapes.SHAPES]
    if bad_modes or not modes:
        print(f"flgd bench grasp_oracle: --modes: got {args.modes!r}, expected a comma list of {', '.join(MODES)}")
        return 1
    if bad_shapes:
        print(f"flgd bench grasp_oracle: --shapes: unknown {', '.join(bad_shapes)}; expected some of "
              f"{', '.join(shapes.SHAPES)}")
        return 1
    if args.trials < 1:
        print(f"flgd bench grasp_oracle: --trials: got {args.trials}, expected at least 1")
        return 1
    cfg = load_config(args.config)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=0, scene="", seed=args.seed))
    cell = SimCell(cfg)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    try:
        for mode in modes:
            held_all = counted_all = 0
            for shape in args.shapes.split(","):
                outcomes = [trial(cell, cfg, shape, mode, rng) for _ in range(args.trials)]
                counted = [o for o in outcomes if o != "blocked"]
                held = counted.count("held")
                held_all, counted_all = held_all + held, counted_all + len(counted)
                fails = sorted({o for o in counted if o != "held"})
                blocked = len(outcomes) - len(counted)
                print(f"{mode:8s} {shape:18s} {held:3d}/{len(counted):<3d} "
                      f"({100.0 * held / max(len(counted), 1):5.1f} %)"
                      + (f"  blocked by a neighbour: {blocked}" if blocked else "")
                      + (f"  failures: {'; '.join(fails)}" if fails else ""), flush=True)
            print(f"{mode:8s} {'all shapes':18s} {held_all:3d}/{counted_all:<3d} "
                  f"({100.0 * held_all / max(counted_all, 1):5.1f} %)  [{time.perf_counter() - t0:.0f} s]", flush=True)
    finally:
        cell.close()
    return 0
