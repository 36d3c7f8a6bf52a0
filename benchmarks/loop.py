"""``flgd bench loop``: does the cell act on noise and repeat what fails?  Variants side by side, frozen.

The shipped policy (or ``--policy``), frozen and greedy, cleans random clutter on several simulated cells at
several seeds, once per *variant* -- a named set of config changes -- through ``flgd eval``'s Evaluator (the
daemon's cycle, agent and metrics).  Every variant runs on the same cells, seeds and scenes, so the only
difference between two rows is the variant's settings.  Per variant and cell, pooled over seeds:

* grasp success (successful / attempted grasps) and picks per action (successful grasps / actions) side by side;
* completion, the longest failure streak, the failed actions in streaks of >= 5, runs ended stuck;
* objects lost (left the workspace other than in the gripper) and, of them, dropped from the gripper after a lift;

and per variant the mean over cells of each rate and loop number.  A variant is ``NAME:KEY=VALUE,KEY=VALUE`` with dotted config keys
(``rewards.min_object_area=36``, ``exploration.failure_memory=false``, ``camera.depth_fill=none``); the cells are
config files (default: the training cell and the two noisy cells in benchmarks/cells).  Results of each
(variant, cell, seed) are kept in ``--root`` as they finish: the bench run again skips what is done.

    flgd bench loop --variants base: area36:rewards.min_object_area=36 [--cells FILE ...] [--seeds 300 301 302]
                    [--objects blocks] [--count 20 | --scene-set vpg-hard] [--runs 3] [--root runs/loop]
                    [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from flgd.overrides import apply_overrides, parse_override

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CELLS = (REPO / "cell_config" / "sim.yaml", REPO / "benchmarks" / "cells" / "noisy-depth.yaml",
                 REPO / "benchmarks" / "cells" / "shifted-look.yaml")
DEFAULT_POLICY = REPO / "policies" / "flg-sim.safetensors"
METRICS = ("grasp_success", "picks_per_action", "completion", "longest_failure_streak", "streak_actions",
           "stuck_runs")


def parse_variant(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME:KEY=VALUE,...`` -> (NAME, {KEY: value}); values are read as YAML (numbers, true/false, text;
    ``flgd.overrides``)."""
    name, _, rest = text.partition(":")
    if not name or not name.replace("-", "").replace("_", "").isalnum():
        raise ValueError(f"--variants {text!r}: expected NAME:KEY=VALUE,... with a plain NAME")
    settings: dict[str, Any] = {}
    for item in filter(None, rest.split(",")):
        try:
            key, value = parse_override(item)
        except ValueError:
            raise ValueError(f"--variants {text!r}: {item!r} is not KEY=VALUE with a dotted KEY") from None
        settings[key] = value
    return name, settings


def variant_config(cell: Path, settings: dict[str, Any]):
    """The cell's config with the variant's settings (checked as any config is)."""
    from flgd.config import load_config

    return apply_overrides(load_config(cell), settings,
                           source=f"{cell} with {', '.join(f'{k}={v}' for k, v in settings.items())}")


def run_one(config: Any, policy: Path, scenes: list, runs: int, seed: int) -> list[dict]:
    """The run rows of one (variant, cell, seed), every scene's runs in order."""
    from flgd.evaluation.evaluator import EvalOptions, Evaluator
    from flgd.evaluation.report import _run_row
    from flgd.learning.policy_file import load_policy

    network = load_policy(policy).network
    with Evaluator(config, network, EvalOptions(runs=runs, seed=seed)) as ev:
        results = ev.evaluate(scenes)
    return [{"scene": spec.name, **_run_row(log, 10)} for spec, logs in results for log in logs]


def pooled(rows: list[dict]) -> dict[str, Any]:
    """The module doc's numbers over run rows."""
    counted = [r for r in rows if r["end"] not in ("unstable", "fault")]
    attempts = sum(r["grasp_attempts"] for r in counted)
    picks = sum(r["grasp_successes"] for r in counted)
    actions = sum(r["actions"] for r in counted)
    return {"runs": len(rows), "counted": len(counted), "grasp_attempts": attempts, "grasp_successes": picks,
            "actions": actions,
            "grasp_success": picks / attempts if attempts else None,
            "picks_per_action": picks / actions if actions else None,
            "completion": (sum(1 for r in counted if r["completed"]) / len(counted)) if counted else None,
            "longest_failure_streak": max((r["longest_failure_streak"] for r in counted), default=0),
            "streak_actions": sum(r["streak_actions"] for r in counted),
            "stuck_runs": sum(1 for r in counted if r["end"] == "stuck"),
            # why a cleared table was not a completed run: objects lost, and of them the ones dropped from the
            # gripper after a lift (None: rows kept from before the bench counted drops)
            "objects_lost": sum(r["objects_lost"] for r in counted),
            "objects_dropped": (sum(r["objects_dropped"] for r in counted)
                                if all("objects_dropped" in r for r in counted) else None)}


def _mean(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return statistics.fmean(vals) if vals else None


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="flgd bench loop", description=__doc__.split("\n\n")[0])
    p.add_argument("--variants", nargs="+", required=True, metavar="NAME:KEY=VALUE,...")
    p.add_argument("--cells", nargs="+", type=Path, default=list(DEFAULT_CELLS))
    p.add_argument("--seeds", nargs="+", type=int, default=[300, 301, 302])
    p.add_argument("--policy", type=Path, default=DEFAULT_POLICY)
    p.add_argument("--objects", default="blocks")
    p.add_argument("--count", type=int, default=20)
    p.add_argument("--scene-set", metavar="NAME", help="a named scene set of flgd eval (e.g. vpg-hard) instead of "
                                                          "random clutter")
    p.add_argument("--vpg", type=Path, default=REPO.parent / "shared" / "external" / "vpg",
                   help="VPG's files for --scene-set vpg-hard")
    p.add_argument("--runs", type=int, default=3, help="runs per seed")
    p.add_argument("--root", type=Path, default=REPO / "runs" / "loop")
    p.add_argument("--out", type=Path, help="summary JSON")
    args = p.parse_args(argv)
    try:
        from flgd.evaluation.scene_sets import clutter_scene, named_set

        scenes = (named_set(args.scene_set, args.vpg) if args.scene_set
                  else [clutter_scene(args.objects, args.count)])
        variants = [parse_variant(v) for v in args.variants]
        configs = {(name, cell): variant_config(cell, settings) for name, settings in variants for cell in args.cells}
    except (ValueError, OSError) as exc:
        print(f"flgd bench loop: {exc}", file=sys.stderr)
        return 2
    import dataclasses

    import torch

    torch.set_num_threads(1)
    args.root.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"command": "flgd bench loop " + " ".join(argv), "policy": str(args.policy),
                               "objects": args.scene_set or args.objects, "count": args.count,
                               "runs_per_seed": args.runs,
                               "seeds": args.seeds, "cells": [str(c) for c in args.cells],
                               "machine": f"{platform.node()} ({platform.machine()}, {platform.python_version()})",
                               "date": time.strftime("%Y-%m-%d"), "variants": {}}
    for name, settings in variants:
        per_cell: dict[str, Any] = {}
        for cell in args.cells:
            rows: list[dict] = []
            for seed in args.seeds:
                scope = f"--{args.scene_set}" if args.scene_set else ""
                done = args.root / f"{name}--{cell.stem}{scope}--{seed}.json"
                if done.exists():
                    rows.extend(json.loads(done.read_text())["runs"])
                    continue
                cfg = dataclasses.replace(configs[(name, cell)], state_dir=str(args.root / "state"))
                t0 = time.perf_counter()
                got = run_one(cfg, args.policy, scenes, args.runs, seed)
                done.write_text(json.dumps({"variant": name, "settings": settings, "cell": str(cell), "seed": seed,
                                            "seconds": round(time.perf_counter() - t0, 1), "runs": got}))
                rows.extend(got)
                s = pooled(got)
                print(f"{name} {cell.stem} seed {seed}: grasp {s['grasp_successes']}/{s['grasp_attempts']}, "
                      f"picks/action {s['picks_per_action']:.2f}, longest streak {s['longest_failure_streak']}",
                      file=sys.stderr, flush=True)
            per_cell[cell.stem] = pooled(rows)
        summary["variants"][name] = {"settings": settings, "cells": per_cell,
                                     "mean": {m: _mean([c[m] for c in per_cell.values()]) for m in METRICS}}
    for name, v in summary["variants"].items():
        cells = "  ".join(f"{c}: {100 * (s['grasp_success'] or 0):.1f}% {s['picks_per_action'] or 0:.2f}/act "
                          f"streak {s['longest_failure_streak']} in>=5 {s['streak_actions']} stuck {s['stuck_runs']}"
                          for c, s in v["cells"].items())
        print(f"{name:>12}  mean {100 * (v['mean']['grasp_success'] or 0):.1f}% "
              f"{v['mean']['picks_per_action'] or 0:.3f}/act | {cells}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary, indent=2) + "\n")
    return 0
