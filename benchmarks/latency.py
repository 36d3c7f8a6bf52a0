"""``flgd bench latency``: time of a full FLG decision and of one learner update, per network variant.

A decision is what the daemon pays between capture and plan: 16 rotations x 2
maps x 224 x 224 through the network (rotate, forward, rotate back), the grasp
and move masks, the masked argmax and the exploration rules
(``Agent.decide``).  The default ("fast") network and the paper-faithful
DenseNet-121 variant are measured in the same run and their ratio reported,
so a shared, noisy machine still compares with itself.  One learner update
(batch of 4 non-terminal transitions: all 16 rotations of each s' through the
online network, one through the target network, the executed rotation(s)
forward and backward) is timed for the default network, once with the exact
double-DQN target and once with every a' and target value cached
(``learning.next_argmax_max_age`` > 0 after a first update that fills the
cache; in training about 3 of 4 targets are served that way).

A third timing repeats the decision while the learner thread trains in the
same process, the daemon's steady state.  Threads: on a 2-core machine that
other work shares, one torch thread (``--threads 1``, config
``learning.threads: 1``) gives stable latencies; two threads are faster on an
idle machine but collapse when a core is taken (OpenMP workers wait for a
descheduled peer): 0.57 s instead of 0.09 s per decision in one measurement.

``--learning`` adds the comparison used to choose the fast network's width:
a synthetic grasping task on 64 x 64 maps -- one 3 cm bar per scene, at a
random multiple of 22.5 deg and a random position; a grasp succeeds only on
the bar's middle part with the fingers closing across it -- trained with the
real Learner (prioritized replay, Huber, Adam) from a fixed set of labelled
transitions, and scored by the greedy masked grasp on 32 held-out scenes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import time

import cv2
import numpy as np
import torch

from flgd.actions import Action
from flgd.config import CellConfig
from flgd.learning.agent import Agent, masked_maps
from flgd.learning.learner import Learner
from flgd.learning.networks import build_network, q_maps
from flgd.learning.replay import PrioritizedReplay, Transition
from flgd.perception import Heightmaps

TARGET_DECISION_S = 0.25


def clutter_scene(seed: int, n: int = 224, blocks: int = 15) -> Heightmaps:
    """A cluttered table: textured background, ``blocks`` coloured boxes 2-6 cm high."""
    rng = np.random.default_rng(seed)
    height = np.zeros((n, n), np.float32)
    color = np.clip(rng.normal(120, 8, (n, n, 3)), 0, 255).astype(np.uint8)
    for _ in range(blocks):
        centre = tuple(float(v) for v in rng.uniform(20, n - 20, 2))
        size = tuple(float(v) for v in rng.uniform(10, 30, 2))
        box = np.round(cv2.boxPoints((centre, size, float(rng.uniform(0, 180))))).astype(np.int32)
        cv2.fillPoly(height, [box], float(rng.uniform(0.02, 0.06)))
        cv2.fillPoly(color, [box], tuple(int(v) for v in rng.integers(0, 255, 3)))
    return Heightmaps(color, height)


def _median_s(fn, runs: int) -> tuple[float, list[float]]:
    fn()  # warm-up: allocations, grid cache
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def decision_latency(variant: str, runs: int, cfg: CellConfig, **arch) -> tuple[float, list[float]]:
    agent = Agent(cfg, build_network(variant, cfg.learning.rotations, seed=0, **arch), seed=0)
    scenes = [clutter_scene(s) for s in range(3)]
    state = {"i": 0}

    def one() -> None:
        state["i"] += 1
        decision = agent.decide(scenes[state["i"] % 3], step=10_000)
        assert decision is not None

    return _median_s(one, runs)


def update_latency(variant: str, runs: int, cfg: CellConfig, cached: bool = False,
                   **arch) -> tuple[float, list[float]]:
    import dataclasses

    age = 10 * (runs + 1) if cached else 0
    cfg = dataclasses.replace(cfg, learning=dataclasses.replace(
        cfg.learning, next_argmax_max_age=age, target_update_every=max(cfg.learning.target_update_every, runs + 2)))
    replay = PrioritizedReplay.from_config(cfg.learning)
    scenes = [clutter_scene(s) for s in range(cfg.learning.batch_size + 1)]
    for i in range(cfg.learning.batch_size):
        replay.add(Transition(scenes[i], Action("grasp", 100, 100, i), 0.0, scenes[i + 1], False))
    learner = Learner(cfg, build_network(variant, cfg.learning.rotations, seed=0, **arch), replay, device="cpu")
    if cached:
        for _ in range(3):  # stratified sampling of 4 slots: a few updates visit (and cache) all of them
            learner.update()
    return _median_s(learner.update, runs)


def decision_while_training(runs: int, cfg: CellConfig) -> tuple[float, list[float]]:
    """Decisions of the default network while the learner thread trains in the same process (the daemon's
    steady state): the two compete for the cores."""
    agent = Agent(cfg, build_network(cfg.learning.network, cfg.learning.rotations, seed=0), seed=0)
    replay = PrioritizedReplay.from_config(cfg.learning)
    scenes = [clutter_scene(s) for s in range(cfg.learning.batch_size + 1)]
    for i in range(cfg.learning.batch_size):
        replay.add(Transition(scenes[i], Action("grasp", 100, 100, i), 0.0, scenes[i + 1], False))
    learner = Learner(cfg, agent.network, replay, device="cpu", mailbox=agent.mailbox)
    learner.start()
    try:
        for _ in range(runs + 2):
            learner.notify_new_transition()
        return _median_s(lambda: agent.decide(scenes[0], step=10_000), runs)
    finally:
        learner.stop(timeout=120)


# --------------------------------------------------------------------------- learning-speed task

def bar_task(seed: int, n: int = 64) -> tuple[Heightmaps, np.ndarray, int]:
    """One bar at a random multiple of 22.5 deg; returns heightmaps, the 'good grasp' pixel mask and the
    rotation index (mod R/2) that closes across the bar."""
    rng = np.random.default_rng(seed)
    k = int(rng.integers(8))
    angle = 22.5 * k  # long axis direction, degrees from +col towards +row
    centre = tuple(float(v) for v in rng.uniform(18, n - 18, 2))
    height = np.zeros((n, n), np.float32)
    box = np.round(cv2.boxPoints((centre, (28.0, 8.0), angle))).astype(np.int32)
    cv2.fillPoly(height, [box], float(rng.uniform(0.02, 0.05)))
    color = np.clip(rng.normal(110, 6, (n, n, 3)), 0, 255).astype(np.uint8)
    color[height > 0] = rng.integers(60, 255, 3)
    good = np.zeros((n, n), np.uint8)
    middle = np.round(cv2.boxPoints((centre, (12.0, 6.0), angle))).astype(np.int32)
    cv2.fillPoly(good, [middle], 1)
    good &= (height > 0).astype(np.uint8)
    return Heightmaps(color, height), good, (k + 4) % 8  # closing direction is perpendicular


def task_transitions(scenes: int, per_scene: int, seed: int) -> list[Transition]:
    rng = np.random.default_rng(seed)
    out = []
    for s in range(scenes):
        hm, good, rot = bar_task(seed * 100_000 + s)
        on_bar = np.argwhere(hm.height > 0)
        good_px = np.argwhere(good > 0)
        for j in range(per_scene):
            if j < per_scene // 3:  # a success: good pixel, right rotation (or its twin)
                r, c = good_px[rng.integers(len(good_px))]
                i = rot + 8 * int(rng.integers(2))
            else:  # a random grasp on the bar
                r, c = on_bar[rng.integers(len(on_bar))]
                i = int(rng.integers(16))
            reward = 1.0 if good[r, c] and i % 8 == rot else 0.0
            out.append(Transition(hm, Action("grasp", int(r), int(c), i), reward, None, True))
    return out


def task_accuracy(net, cfg: CellConfig, scenes: int = 32) -> float:
    # every grasp rotation allowed: the bar task's 64 px maps are barely wider than the open gripper
    agent = Agent(dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, grasp_in_view=False)), net)
    hits = 0
    net.eval()
    for s in range(scenes):
        hm, good, rot = bar_task(999_000 + s)
        with torch.no_grad():
            q = q_maps(net, hm).numpy()
        gmask, mmask = agent.masks(hm.height)
        masked = masked_maps(q, gmask, mmask)[:, 0]
        i, r, c = np.unravel_index(int(np.argmax(masked)), masked.shape)
        hits += int(good[r, c] and i % 8 == rot)
    return hits / scenes


def learning_speed(variant: str, updates: int, checkpoints: int, seed: int, **arch) -> dict:
    cfg = CellConfig()
    cfg = dataclasses.replace(cfg, learning=dataclasses.replace(cfg.learning, learning_rate=5e-4,
                                                                device="cpu", seed=seed))
    replay = PrioritizedReplay.from_config(cfg.learning)
    replay.extend((t, None) for t in task_transitions(64, 12, seed))
    learner = Learner(cfg, build_network(variant, 16, seed=seed, **arch), replay, device="cpu")
    curve, train_s = [], 0.0
    every = max(1, updates // checkpoints)
    for u in range(1, updates + 1):
        t0 = time.perf_counter()
        learner.update()
        train_s += time.perf_counter() - t0
        if u % every == 0:
            curve.append((u, task_accuracy(learner.snapshot(), cfg)))
    return {"variant": variant, **arch, "curve": curve, "train_seconds": round(train_s, 1),
            "seconds_per_update": round(train_s / updates, 4)}


# --------------------------------------------------------------------------- main

def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="flgd bench latency", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=7, help="timed decisions of the default network")
    parser.add_argument("--reference-runs", type=int, default=3,
                        help="timed decisions of densenet121 (0 skips it)")
    parser.add_argument("--update-runs", type=int, default=5, help="timed learner updates")
    parser.add_argument("--reference-update-runs", type=int, default=0,
                        help="timed learner updates of densenet121 (exact target; default 0 skips them)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    parser.add_argument("--widths", type=str, default="", help="also time these fast widths, e.g. 8,16,24")
    parser.add_argument("--learning", action="store_true", help="run the learning-speed comparison too")
    parser.add_argument("--learning-updates", type=int, default=300)
    parser.add_argument("--learning-seeds", type=int, default=2)
    parser.add_argument("--candidates", default="fast:8,fast:12,fast:16,fast:24",
                        help="networks compared by --learning: VARIANT or fast:WIDTH, comma-separated")
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = parser.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    cfg = CellConfig()
    default = cfg.learning.network
    machine = f"{platform.machine()} {os.cpu_count()} cpus, torch {torch.__version__} " \
              f"({torch.get_num_threads()} threads), python {platform.python_version()}"
    result: dict = {"benchmark": "latency", "machine": machine, "heightmap": list(cfg.workspace.shape),
                    "rotations": cfg.learning.rotations}
    print(f"machine: {machine}; heightmap {cfg.workspace.shape}, {cfg.learning.rotations} rotations")

    fast_s, fast_runs = decision_latency(default, args.runs, cfg)
    ok = "ok" if fast_s <= TARGET_DECISION_S else "MISSED"
    print(f"decision, {default}: median {fast_s:.3f} s over {args.runs} runs "
          f"({', '.join(f'{t:.3f}' for t in fast_runs)}); target <= {TARGET_DECISION_S} s: {ok}")
    result["decision"] = {default: {"median_s": round(fast_s, 4), "runs_s": [round(t, 4) for t in fast_runs]},
                          "target_s": TARGET_DECISION_S}
    if args.reference_runs > 0:
        dense_s, dense_runs = decision_latency("densenet121", args.reference_runs, cfg)
        print(f"decision, densenet121: median {dense_s:.3f} s over {args.reference_runs} runs "
              f"({', '.join(f'{t:.3f}' for t in dense_runs)}); densenet121 / {default} = {dense_s / fast_s:.1f}x")
        result["decision"]["densenet121"] = {"median_s": round(dense_s, 4),
                                             "runs_s": [round(t, 4) for t in dense_runs]}
        result["decision"]["ratio_densenet121_to_default"] = round(dense_s / fast_s, 2)
    for w in [int(v) for v in args.widths.split(",") if v.strip()]:
        s, runs = decision_latency("fast", args.runs, cfg, width=w)
        print(f"decision, fast width {w}: median {s:.3f} s ({s / fast_s:.2f}x default)")
        result["decision"][f"fast-w{w}"] = {"median_s": round(s, 4), "runs_s": [round(t, 4) for t in runs]}

    upd_s, upd_runs = update_latency(default, args.update_runs, cfg)
    print(f"learner update, {default}, batch {cfg.learning.batch_size} (non-terminal): median {upd_s:.3f} s "
          f"over {args.update_runs} runs ({', '.join(f'{t:.3f}' for t in upd_runs)})")
    result["update"] = {default: {"median_s": round(upd_s, 4), "runs_s": [round(t, 4) for t in upd_runs],
                                  "batch_size": cfg.learning.batch_size}}
    cached_s, cached_runs = update_latency(default, args.update_runs, cfg, cached=True)
    print(f"learner update, {default}, a' and target values cached: median {cached_s:.3f} s "
          f"({', '.join(f'{t:.3f}' for t in cached_runs)}); {cached_s / upd_s:.2f}x the exact update")
    result["update"][f"{default}-cached"] = {"median_s": round(cached_s, 4),
                                             "runs_s": [round(t, 4) for t in cached_runs],
                                             "ratio_to_exact": round(cached_s / upd_s, 3)}
    if args.reference_update_runs > 0:
        dense_u, dense_u_runs = update_latency("densenet121", args.reference_update_runs, cfg)
        print(f"learner update, densenet121, batch {cfg.learning.batch_size} (non-terminal): median {dense_u:.3f} s "
              f"over {args.reference_update_runs} runs ({', '.join(f'{t:.3f}' for t in dense_u_runs)}); "
              f"densenet121 / {default} = {dense_u / upd_s:.1f}x")
        result["update"]["densenet121"] = {"median_s": round(dense_u, 4), "runs_s": [round(t, 4) for t in dense_u_runs],
                                           "batch_size": cfg.learning.batch_size,
                                           "ratio_to_default": round(dense_u / upd_s, 2)}
    busy_s, busy_runs = decision_while_training(args.runs, cfg)
    print(f"decision, {default}, while the learner thread trains: median {busy_s:.3f} s "
          f"({', '.join(f'{t:.3f}' for t in busy_runs)}); {busy_s / fast_s:.2f}x the idle decision")
    result["decision"][f"{default}-while-training"] = {"median_s": round(busy_s, 4),
                                                       "runs_s": [round(t, 4) for t in busy_runs]}

    if args.learning:
        candidates = []
        for item in (v.strip() for v in args.candidates.split(",") if v.strip()):
            variant, _, width = item.partition(":")
            candidates.append((variant, {"width": int(width)} if width else {}))
        rows = []
        for variant, arch in candidates:
            per_seed = [learning_speed(variant, args.learning_updates, 3, seed, **arch)
                        for seed in range(args.learning_seeds)]
            final = statistics.mean(r["curve"][-1][1] for r in per_seed)
            mid = statistics.mean(r["curve"][0][1] for r in per_seed)
            spu = statistics.median(r["seconds_per_update"] for r in per_seed)
            dec, _ = decision_latency(variant, 3, cfg, **arch)
            rows.append({"variant": variant, **arch, "per_seed": per_seed, "accuracy_first_checkpoint": mid,
                         "accuracy_final": final, "seconds_per_update_64px": spu, "decision_s_224": dec})
            label = variant + (f" w{arch['width']}" if arch else "")
            print(f"learning {label:>12}: accuracy {mid:.2f} @ {per_seed[0]['curve'][0][0]} updates, "
                  f"{final:.2f} @ {args.learning_updates}; {spu * 1000:.0f} ms/update (64 px); "
                  f"decision {dec:.3f} s (224 px)")
        result["learning"] = rows
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return 0 if fast_s <= TARGET_DECISION_S else 1
