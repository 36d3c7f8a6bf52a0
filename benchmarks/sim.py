"""``flgd bench sim``: speed of the simulated cell and the grasp success of a scripted oracle.

1. Actions per second with 20 objects: capture a frame (rendering + depth noise),
   build the heightmap, plan a grasp or a push at a random object, check it and
   execute it (a successful grasp also runs the place plan).  Median over runs;
   the reference measured in the same run is the frame rate of capture alone.
   Besides wall-clock actions/s, actions per CPU-second of this process are
   reported: on a shared machine the wall clock also measures the neighbours'
   load (printed with the machine line), the CPU time only this cell's work.
2. Oracle grasp success on isolated blocks: one random block at a random pose,
   grasped at its footprint centre across its short axis through plan_grasp,
   check_plan, execute and grasp_reward -- shows gripper, friction and the
   width-based success signal work.

Targets (issue 3): >= 2 actions/s, oracle >= 95 %.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from flgd.clutter import grasp_reward
from flgd.config import load_config
from flgd.perception import base_to_pixel, frame_heightmaps
from flgd.plans import end_yaw, plan_grasp, plan_push, plan_release
from flgd.safety import PlanRefused, check_plan

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "cell_config" / "sim.yaml"


def short_axis_grasp(points: np.ndarray) -> tuple[float, float, float]:
    """(x, y, closing angle) at the centre of a footprint, across its narrowest horizontal width."""
    xy = points[:, :2]
    best = (math.inf, 0.0, 0.0, 0.0)
    for a in np.linspace(0.0, math.pi, 180, endpoint=False):
        u = np.array([math.cos(a), math.sin(a)])
        v = np.array([-u[1], u[0]])
        pu, pv = xy @ u, xy @ v
        width = pu.max() - pu.min()
        if width < best[0]:
            centre = u * (pu.max() + pu.min()) / 2 + v * (pv.max() + pv.min()) / 2
            best = (width, float(centre[0]), float(centre[1]), float(a))
    return best[1], best[2], best[3]


def actions_per_second(cfg, actions: int, seed: int) -> tuple[float, float, dict]:
    """(actions/s, captures/s, counters) for one run with ``cfg.sim.objects`` objects;
    ``counters["cpu_actions_per_s"]`` is the rate per CPU-second of this process."""
    from sim_cell.cell import SimCell

    rng = np.random.default_rng(seed)
    counts = {"grasp": 0, "grasp_ok": 0, "push": 0, "failed": 0, "resets": 0}
    with SimCell(cfg) as cell:
        busy = 0.0
        cpu = 0.0
        capture_time = 0.0
        for i in range(actions):
            if cell.object_count < cfg.sim.objects // 2:
                cell.reset_scene()
                counts["resets"] += 1
            t0 = time.perf_counter()
            c0 = time.process_time()
            frame = cell.capture()
            t1 = time.perf_counter()
            capture_time += t1 - t0
            hm = frame_heightmaps(frame, cfg.workspace, cfg.camera.depth_range)
            states = cell.object_states()
            target = states[int(rng.integers(len(states)))]
            angle = float(rng.uniform(0, 2 * math.pi))
            if i % 2 == 0:
                # the surface height under the grasp point, read from the heightmap as the agent would
                x, y, _ = short_axis_grasp(target.points)
                r, c = base_to_pixel(x, y, cfg.workspace)
                r = min(max(r, 0), hm.height.shape[0] - 1)
                c = min(max(c, 0), hm.height.shape[1] - 1)
                plan = plan_grasp(x, y, float(hm.height[r, c]), angle, cfg)
            else:
                back = 0.06
                plan = plan_push(target.position[0] - back * math.cos(angle),
                                 target.position[1] - back * math.sin(angle), angle, cfg)
            try:
                checked = check_plan(plan, cfg)
            except PlanRefused:
                counts["failed"] += 1
                busy += time.perf_counter() - t0
                cpu += time.process_time() - c0
                continue
            result = cell.execute(checked)
            if plan.primitive == "grasp":
                counts["grasp"] += 1
                held = bool(result.widths) and grasp_reward(result.widths[-1], cfg.gripper) > 0
                counts["grasp_ok"] += int(held)
                cell.execute(check_plan(plan_release(held, cfg, carry_yaw=end_yaw(plan, cfg)), cfg))
            else:
                counts["push"] += 1
            counts["failed"] += int(not result.completed)
            busy += time.perf_counter() - t0
            cpu += time.process_time() - c0
    counts["cpu_actions_per_s"] = round(actions / cpu, 2)
    return actions / busy, actions / capture_time, counts


def oracle_success(cfg, trials: int, seed: int) -> tuple[float, dict]:
    from sim_cell import shapes
    from sim_cell.cell import SimCell
    from sim_cell.objects import ObjectSpec
    import pybullet as p

    rng = np.random.default_rng(seed)
    per_shape: dict[str, list[int]] = {s: [] for s in shapes.SHAPES}
    base = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=0))
    with SimCell(base) as cell:
        for t in range(trials):
            shape = shapes.SHAPES[t % len(shapes.SHAPES)]
            dims = shapes.random_block_dims(shape, rng)
            geom = shapes.make_block(shape, dims)
            ws = cfg.workspace
            x = rng.uniform(ws.x[0] + 0.08, ws.x[1] - 0.08)
            y = rng.uniform(ws.y[0] + 0.08, ws.y[1] - 0.08)
            yaw = float(rng.uniform(-math.pi, math.pi))
            z = ws.z[0] + geom.extents[2] / 2 + 0.002
            cell.load_scene(_empty_scene())
            cell.add_object(ObjectSpec(shape=shape, size=dims, color=(0.8, 0.3, 0.2), position=(x, y, z),
                                       orientation=p.getQuaternionFromEuler([0, 0, yaw]),
                                       friction=float(rng.uniform(0.4, 0.9))), settle=0.3)
            state = cell.object_states()[0]
            gx, gy, angle = short_axis_grasp(state.points)
            plan = plan_grasp(gx, gy, state.top - ws.z[0], angle, cfg)
            result = cell.execute(check_plan(plan, cfg))
            ok = result.completed and bool(result.widths) and grasp_reward(result.widths[-1], cfg.gripper) > 0
            per_shape[shape].append(int(ok))
            cell.execute(check_plan(plan_release(ok, cfg, carry_yaw=end_yaw(plan, cfg)), cfg))
    rate = sum(sum(v) for v in per_shape.values()) / trials
    return rate, {k: f"{sum(v)}/{len(v)}" for k, v in per_shape.items() if v}


def _empty_scene():
    from sim_cell.scenes import Scene

    return Scene(objects=())


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="flgd bench sim", description="simulated cell speed and oracle success")
    ap.add_argument("--config", default=str(DEFAULT_CONFIG))
    ap.add_argument("--objects", type=int, default=20)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--actions", type=int, default=30, help="actions per run")
    ap.add_argument("--trials", type=int, default=100, help="oracle grasps on isolated blocks")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    cfg = load_config(args.config)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=args.objects, scene=""))
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, "
          f"python {platform.python_version()}, load average {load}; config {args.config}")
    rates, refs, cpu_rates = [], [], []
    for r in range(args.runs):
        cfg_r = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, seed=args.seed + r))
        aps, fps, counts = actions_per_second(cfg_r, args.actions, args.seed + r)
        rates.append(aps)
        refs.append(fps)
        cpu_rates.append(counts["cpu_actions_per_s"])
        print(f"run {r}: {aps:.2f} actions/s (capture alone {fps:.1f} frames/s) {counts}")
    med, ref = statistics.median(rates), statistics.median(refs)
    print(f"actions/s with {args.objects} objects: median {med:.2f} over {args.runs} runs "
          f"(reference: capture alone {ref:.1f} frames/s; ratio {med / ref:.3f}) -- target >= 2")
    print(f"actions per CPU-second: median {statistics.median(cpu_rates):.2f} "
          f"(load average now {' '.join(f'{v:.2f}' for v in os.getloadavg())})")
    rate, per_shape = oracle_success(cfg, args.trials, args.seed)
    print(f"oracle grasp success on isolated blocks: {rate * 100:.1f}% of {args.trials} -- target >= 95%")
    print(f"per shape: {per_shape}")
    return 0 if med >= 2.0 and rate >= 0.95 else 1
