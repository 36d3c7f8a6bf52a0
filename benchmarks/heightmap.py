"""``flgd bench heightmap``: time to turn a 640x480 RGB-D frame into 224x224 heightmaps.

Measured on one core (numpy is single-threaded here; the process is pinned to
one CPU when the OS allows it).  Reported as the median over repeated runs and
as a ratio against a reference measured in the same run -- a plain float
conversion of the same depth frame -- so that a noisy machine can still be
compared with itself.

Also measured in the same runs: what filling the cells without a reading
(``camera.depth_fill``: lowest, inpaint) adds to the projection, and what the
grasp and move masks cost with and without the object filter
(``rewards.min_object_area``) -- the two together are the price of not acting on
noise (target: <= 5 ms together).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import numpy as np

from flgd.clutter import action_masks
from flgd.config import RewardConfig, WorkspaceConfig
from flgd.geometry import pose_matrix, rpy_to_matrix
from flgd.perception import make_heightmaps


def _frame(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A cluttered-table-like frame: table at 0.70 m with random 2-10 cm blocks and 2% holes."""
    rng = np.random.default_rng(seed)
    depth = np.full((480, 640), 700.0)
    for _ in range(20):
        r, c = rng.integers(40, 440), rng.integers(100, 540)
        hr, hc = rng.integers(15, 60, size=2)
        depth[r:r + hr, c:c + hc] = 700.0 - rng.uniform(20, 100)
    depth += rng.normal(0, 1.0, depth.shape)
    depth[rng.random(depth.shape) < 0.02] = 0
    color = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    k = np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]])
    pose = pose_matrix((-0.5, 0.0, 0.70), rpy_to_matrix(np.pi, 0, 0))
    return color, depth.astype(np.uint16), k, pose


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="flgd bench heightmap", description=__doc__)
    parser.add_argument("--repeats", type=int, default=50, help="timed calls per run")
    parser.add_argument("--runs", type=int, default=5, help="independent runs; the median of medians is reported")
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = parser.parse_args(argv)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    ws = WorkspaceConfig()
    color, depth, k, pose = _frame(0)
    make_heightmaps(color, depth, k, 0.001, pose, ws)  # warm the ray cache, as in the daemon

    heightmap_runs, reference_runs = [], []
    fills: dict[str, list[float]] = {"none": [], "lowest": [], "inpaint": []}
    masks: dict[str, list[float]] = {"unfiltered": [], "filtered": []}
    height = make_heightmaps(color, depth, k, 0.001, pose, ws, (0.2, 1.5), "none").height
    unfiltered, filtered = RewardConfig(min_object_area=0.0), RewardConfig()
    for _ in range(args.runs):
        heightmap_runs.append(_median_ms(lambda: make_heightmaps(color, depth, k, 0.001, pose, ws,
                                                                 (0.2, 1.5)), args.repeats))
        reference_runs.append(_median_ms(lambda: depth.astype(np.float32) * np.float32(0.001), args.repeats))
        for method in fills:
            fills[method].append(_median_ms(lambda: make_heightmaps(color, depth, k, 0.001, pose, ws, (0.2, 1.5),
                                                                    method), args.repeats))
        masks["unfiltered"].append(_median_ms(lambda: action_masks(height, unfiltered), args.repeats))
        masks["filtered"].append(_median_ms(lambda: action_masks(height, filtered), args.repeats))
    hm = statistics.median(heightmap_runs)
    ref = statistics.median(reference_runs)
    fill_ms = {m: statistics.median(v) for m, v in fills.items()}
    mask_ms = {m: statistics.median(v) for m, v in masks.items()}
    added = {m: fill_ms[m] - fill_ms["none"] + mask_ms["filtered"] - mask_ms["unfiltered"]
             for m in ("lowest", "inpaint")}
    result = {
        "benchmark": "heightmap", "frame": "640x480", "heightmap": list(ws.shape),
        "median_ms": round(hm, 3), "runs_ms": [round(t, 3) for t in heightmap_runs],
        "reference_median_ms": round(ref, 3), "ratio_to_reference": round(hm / ref, 1),
        "target_ms": 15.0, "machine": f"{platform.machine()} {os.cpu_count()} cpus, {platform.python_version()}",
        "fill_median_ms": {m: round(v, 3) for m, v in fill_ms.items()},
        "masks_median_ms": {m: round(v, 3) for m, v in mask_ms.items()},
        "fill_and_filter_added_ms": {m: round(v, 3) for m, v in added.items()}, "added_target_ms": 5.0,
    }
    print(f"heightmap 640x480 -> {ws.shape[0]}x{ws.shape[1]}: median {hm:.2f} ms over {args.runs} runs "
          f"(runs: {', '.join(f'{t:.2f}' for t in heightmap_runs)}); target <= 15 ms")
    print(f"reference (depth uint16 -> float32 metres): {ref:.3f} ms; ratio {hm / ref:.1f}x")
    print("heightmap by fill: " + ", ".join(f"{m} {v:.2f} ms" for m, v in fill_ms.items())
          + f"; masks unfiltered {mask_ms['unfiltered']:.3f} ms, filtered {mask_ms['filtered']:.3f} ms")
    print("fill + object filter add: " + ", ".join(f"{m} {v:.2f} ms" for m, v in added.items()) + "; target <= 5 ms")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return 0
