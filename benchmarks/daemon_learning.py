"""``flgd bench daemon_learning``: what online learning costs or gains in the daemon's main job.

The main command (``flgd run --config cell_config/sim.yaml`` with the shipped policy) from a fresh state
directory, ``--actions`` actions (300), in three variants, ``--seeds`` (0 1 2) each:

* ``frozen`` -- learning off (``finetune.updates_per_action: 0``; the agent then acts greedily);
* ``gate``   -- the config as shipped: fine-tuning behind the champion/challenger gate;
* ``nogate`` -- the same fine-tuning with ``gate.enabled: false`` (learned weights act unvetted);
* ``gate-paced``, ``nogate-paced`` -- the same two with ``learning.wait_for_updates: true``: each cycle waits
  for the learner's scheduled updates, as a real cell's ~9 s cycle would let them run (on the simulated cell the
  cycle otherwise outruns the learner, which then drops most of its updates).

Each run is the daemon's own Controller (setup, run loop, background learner, gate) in its own process,
stopped after the given number of actions; its state directory under ``--root`` holds everything, and a run
cut short is continued by running the bench again (the daemon resumes from its state directory).  Reported
per variant, pooled over seeds: grasp success of every action the daemon took, per window of 100 grasps and
over the first 200 grasps; the same for greedy decisions only; promotions, drops and rollbacks; and one PNG.

    flgd bench daemon_learning [--root runs/daemon-learning] [--actions 300] [--seeds 0 1 2] [--jobs 2]
    flgd bench daemon_learning --report-only
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

from benchmarks._daemon_runs import action_rows, gate_counts, grasp_outcomes, run_controller, run_workers, steps_done

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "cell_config" / "sim.yaml"
VARIANTS = ("frozen", "gate", "nogate", "gate-paced", "nogate-paced")
WINDOW = 100
FIRST = 200


def variant_config(variant: str, seed: int, state_dir: Path):
    """cell_config/sim.yaml as the main command runs it, with the variant's one change and the seed."""
    from flgd.config import load_config

    cfg = load_config(CONFIG)
    cfg = dataclasses.replace(cfg, state_dir=str(state_dir),
                              sim=dataclasses.replace(cfg.sim, seed=seed),
                              learning=dataclasses.replace(cfg.learning, seed=seed, threads=1))
    if variant.endswith("-paced"):
        cfg = dataclasses.replace(cfg, learning=dataclasses.replace(cfg.learning, wait_for_updates=True))
        variant = variant[:-len("-paced")]
    if variant == "frozen":
        cfg = dataclasses.replace(cfg, finetune=dataclasses.replace(cfg.finetune, updates_per_action=0))
    elif variant == "nogate":
        cfg = dataclasses.replace(cfg, gate=dataclasses.replace(cfg.gate, enabled=False))
    elif variant != "gate":
        raise ValueError(f"variant: got {variant!r}, expected one of {', '.join(VARIANTS)}")
    return cfg


def worker(variant: str, seed: int, state_dir: Path, actions: int) -> int:
    """One run: the daemon's Controller on the variant's config until ``actions`` actions are in its log."""
    return run_controller(variant_config(variant, seed, state_dir), state_dir, actions)


def summarize(root: Path, seeds: list[int], actions: int) -> dict:
    out: dict = {"actions": actions, "seeds": seeds, "window": WINDOW, "variants": {}}
    for variant in VARIANTS:
        runs, missing = {}, []
        for seed in seeds:
            d = root / f"{variant}-s{seed}"
            done = steps_done(d)
            if done < actions:
                missing.append(f"{variant}-s{seed} ({done}/{actions} actions)")
                continue
            rows = action_rows(d, actions)
            runs[seed] = {"grasps": grasp_outcomes(rows), "greedy": grasp_outcomes(rows, True), "gate": gate_counts(d),
                          "moves": sum(1 for r in rows if r[1] not in (None, "grasp")),
                          "epsilon_actions": sum(1 for r in rows if r[3] == "epsilon")}
        v: dict = {"missing": missing, "per_seed": {}}
        if runs:
            n_windows = max(len(r["grasps"]) for r in runs.values()) // WINDOW + 1
            windows = []
            for k in range(n_windows):
                parts = [r["grasps"][k * WINDOW:(k + 1) * WINDOW] for r in runs.values()]
                n = sum(len(p) for p in parts)
                if n:
                    windows.append({"grasps": f"{k * WINDOW + 1}-{k * WINDOW + WINDOW}", "attempts": n,
                                    "success": sum(map(sum, parts)) / n})
            first = [r["grasps"][:FIRST] for r in runs.values()]
            greedy = [r["greedy"] for r in runs.values()]
            v.update({
                "windows": windows,
                "first_200": sum(map(sum, first)) / max(1, sum(map(len, first))),
                "all": sum(sum(r["grasps"]) for r in runs.values()) / max(1, sum(len(r["grasps"]) for r in runs.values())),
                "greedy_all": sum(map(sum, greedy)) / max(1, sum(map(len, greedy))),
                "gate": {k: sum(r["gate"][k] for r in runs.values()) for k in ("challenger", "promote", "drop",
                                                                              "rollback", "learner_updates")},
            })
            v["per_seed"] = {str(s): {"grasp_attempts": len(r["grasps"]),
                                      "success": sum(r["grasps"]) / max(1, len(r["grasps"])),
                                      "first_200": sum(r["grasps"][:FIRST]) / max(1, len(r["grasps"][:FIRST])),
                                      "moves": r["moves"], "epsilon_actions": r["epsilon_actions"], **r["gate"]}
                             for s, r in runs.items()}
        out["variants"][variant] = v
    frozen = out["variants"]["frozen"]
    for variant in VARIANTS[1:]:
        v = out["variants"][variant]
        if frozen.get("windows") and v.get("windows"):
            full = len(runs_of(v)) * WINDOW // 2  # a last window with under half its grasps is reported, not judged
            gaps = [w["success"] - f["success"] for w, f in zip(v["windows"], frozen["windows"])
                    if min(w["attempts"], f["attempts"]) >= full]
            v["worst_window_vs_frozen"] = min(gaps)
            v["first_200_vs_frozen"] = v["first_200"] - frozen["first_200"]
    return out


def runs_of(v: dict) -> dict:
    return v.get("per_seed", {})


def _plot(summary: dict, path: Path) -> None:
    import cv2
    import numpy as np

    h, w = 360, 640
    img = np.full((h, w, 3), 255, np.uint8)
    colors = {"frozen": (90, 90, 90), "gate": (40, 140, 40), "nogate": (40, 40, 200), "gate-paced": (40, 200, 120),
              "nogate-paced": (200, 40, 160)}
    x0, x1, y0, y1 = 60, w - 20, h - 40, 20
    lo, hi = 0.6, 1.0
    for y in (0.6, 0.7, 0.8, 0.9, 1.0):
        py = int(y0 - (y - lo) / (hi - lo) * (y0 - y1))
        cv2.line(img, (x0, py), (x1, py), (225, 225, 225), 1)
        cv2.putText(img, f"{int(y * 100)}%", (10, py + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    n = max((len(v.get("windows", [])) for v in summary["variants"].values()), default=1)
    for k, (name, v) in enumerate(summary["variants"].items()):
        pts = []
        for i, win in enumerate(v.get("windows", [])):
            px = int(x0 + (i + 0.5) / max(1, n) * (x1 - x0))
            py = int(y0 - (min(hi, max(lo, win["success"])) - lo) / (hi - lo) * (y0 - y1))
            pts.append((px, py))
            cv2.circle(img, (px, py), 4, colors[name], -1)
        for a, b in zip(pts, pts[1:]):
            cv2.line(img, a, b, colors[name], 2)
        cv2.putText(img, name, (x0 + 10 + 110 * k, h - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colors[name], 1)
    cv2.putText(img, f"grasp success per window of {WINDOW} grasps, pooled over seeds {summary['seeds']}",
                (x0, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    cv2.imwrite(str(path), img)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="flgd bench daemon_learning", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", type=Path, default=Path("runs/daemon-learning"))
    p.add_argument("--actions", type=int, default=300)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--report-only", action="store_true")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "daemon-learning.json")
    p.add_argument("--worker", nargs=2, metavar=("VARIANT", "SEED"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.actions < 1 or args.jobs < 1:
        p.error("--actions and --jobs must be >= 1")
    if args.worker:
        variant, seed = args.worker[0], int(args.worker[1])
        return worker(variant, seed, args.root / f"{variant}-s{seed}", args.actions)
    if not args.report_only:
        todo = [(f"{v}-s{s}", ["bench", "daemon_learning", "--root", str(args.root), "--actions", str(args.actions),
                               "--worker", v, str(s)])
                for s in args.seeds for v in args.variants if steps_done(args.root / f"{v}-s{s}") < args.actions]
        run_workers(todo, args.root, args.jobs)
    summary = summarize(args.root, args.seeds, args.actions)
    summary["machine"] = f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}"
    summary["command"] = "flgd bench daemon_learning " + " ".join(argv)
    summary["date"] = time.strftime("%Y-%m-%d")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2) + "\n")
    _plot(summary, args.out.with_suffix(".png"))
    for name, v in summary["variants"].items():
        if v.get("windows"):
            wins = "  ".join(f"{w['grasps']}: {100 * w['success']:.1f}% ({w['attempts']})" for w in v["windows"])
            print(f"{name:7s} first 200 grasps {100 * v['first_200']:.1f}%  all {100 * v['all']:.1f}%  {wins}  "
                  f"gate {v['gate']}")
        if v["missing"]:
            print(f"{name:7s} missing: {', '.join(v['missing'])}")
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")
    return 0
