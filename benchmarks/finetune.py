"""``flgd bench finetune``: what online learning gains on a cell that differs from the one the policy was trained in.

The paper's sim-to-real experiment on two simulated cells: the training cell (``cell_config/sim.yaml``) and a
second, different one (``--shifted``, default ``cell_config/sim-shifted.yaml``: another camera calibration, depth
noise, colours, light, object physics and objects).  Rows, each ``--seeds`` (0 1 2) runs of ``--actions`` (1,000):

* ``shifted-frozen``  -- the shipped policy on the second cell, learning off (greedy);
* ``shifted-gate``    -- the same, fine-tuning behind the champion/challenger gate (the daemon as shipped);
* ``shifted-nogate``  -- the same fine-tuning with ``gate.enabled: false`` (learned weights act unvetted);
* ``shifted-scratch`` -- no policy: a fresh network from the perception trunk learns on the second cell with the
  ``learning`` settings, its weights acting as they are handed over (the paper's from-scratch row; a fresh
  network has no level to protect, so no gate);
* ``train-frozen``, ``train-gate`` -- the shipped policy frozen and gated on the cell it was trained in.

A learning row brings its cell's frozen row along: every learning row is judged against it.

Every run is the daemon's own Controller (cycle, background learner, gate) in its own process and state
directory under ``--root``; a run cut short continues when the bench is run again.  Every run is paced
(``learning.wait_for_updates: true``): a cycle waits until the learner has run the previous actions' scheduled
updates, the time a real cell's ~9 s cycle gives it, so that the numbers measure the method and not the speed of
this machine.  ``--set KEY=VALUE`` changes a learner setting (``finetune.*``, ``learning.*``, ``gate.*``,
``exploration.*``) of the learning rows, and ``--tag NAME`` keeps such a candidate's runs and report apart; frozen
rows take no settings and are shared by every tag.

Reported per row, median over seeds: grasp success of every grasp the cell made per window of 100 grasps, over
the last 200 grasps, the worst window against the frozen row of the same cell (beside what that worst window
looks like by chance when learning changes nothing: with a few seeds it lies several points below zero), the
actions until the success over the last 100 grasps first reached 80 % and 90 %; promotions / drops / rollbacks
summed over the seeds; picks per action (successful grasps / actions), the longest failure streak, the failed
actions in streaks of >= 5 and the times the cell declared itself stuck and laid out a new scene; and one PNG of
the curves.  A run that is continued (cut short, then the bench run again)
draws new seeds for its continuation.

    flgd bench finetune [--root runs/finetune] [--actions 1000] [--seeds 0 1 2] [--rows ...] [--jobs 2]
                        [--engine ray|processes] [--address HOST:PORT]
                        [--shifted FILE] [--set KEY=VALUE ...] [--tag NAME] [--out FILE.json]
    flgd bench finetune --report-only ...
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks._daemon_runs import (REPO, action_rows, gate_counts, grasp_outcomes, grasp_steps, loop_counts,
                                     run_controller, run_workers, steps_done)

TRAIN_CONFIG = REPO / "cell_config" / "sim.yaml"
SHIFTED_CONFIG = REPO / "cell_config" / "sim-shifted.yaml"
ROWS = ("shifted-frozen", "shifted-gate", "shifted-nogate", "shifted-scratch", "train-frozen", "train-gate")
WINDOW = 100
LAST = 200
LEVELS = (0.8, 0.9)
SETTABLE = ("finetune.", "learning.", "gate.", "exploration.")


def parse_settings(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings (``flgd.overrides``: VALUE read as YAML) as a dict; ValueError naming the item that is
    not one."""
    from flgd.overrides import parse_override

    out: dict[str, Any] = {}
    for item in items:
        try:
            key, value = parse_override(item)
        except ValueError:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE, e.g. finetune.learning_rate=3e-5") from None
        if not key.startswith(SETTABLE):
            raise ValueError(f"--set {item!r}: only learner settings ({', '.join(k + '*' for k in SETTABLE)}) may "
                             "be set; the cell itself is chosen with --shifted")
        out[key] = value
    return out


def row_config(row: str, seed: int, state_dir: Path, shifted: Path, settings: dict[str, Any]):
    """The config a row's run uses: its cell's config, the seed, pacing, the row's one change and ``settings``."""
    from flgd.config import load_config
    from flgd.overrides import apply_overrides

    if row not in ROWS:
        raise ValueError(f"row: got {row!r}, expected one of {', '.join(ROWS)}")
    cell, variant = row.split("-", 1)
    path = shifted if cell == "shifted" else TRAIN_CONFIG
    cfg = load_config(path)
    if settings and variant != "frozen":
        cfg = apply_overrides(cfg, settings, source=f"{path} with --set {', '.join(settings)}", label="--set ")
    cfg = dataclasses.replace(
        cfg, state_dir=str(state_dir), sim=dataclasses.replace(cfg.sim, seed=seed),
        learning=dataclasses.replace(cfg.learning, seed=seed, threads=1, wait_for_updates=True))
    if variant == "frozen":
        cfg = dataclasses.replace(cfg, finetune=dataclasses.replace(cfg.finetune, updates_per_action=0))
    elif variant == "gate":
        cfg = dataclasses.replace(cfg, gate=dataclasses.replace(cfg.gate, enabled=True))
    elif variant == "nogate":
        cfg = dataclasses.replace(cfg, gate=dataclasses.replace(cfg.gate, enabled=False))
    elif variant == "scratch":
        cfg = dataclasses.replace(cfg, policy="", gate=dataclasses.replace(cfg.gate, enabled=False))
    return cfg


def with_references(rows: list[str]) -> list[str]:
    """``rows`` plus the frozen row of each of their cells (every learning row is judged against it), in ROWS order."""
    cells = {r.split("-")[0] for r in rows}
    return [r for r in ROWS if r in rows or (r.endswith("-frozen") and r.split("-")[0] in cells)]


def run_name(row: str, seed: int, tag: str) -> str:
    """A run's directory name; frozen rows are shared by every tag."""
    return f"{row}-s{seed}" if not tag or row.endswith("-frozen") else f"{tag}-{row}-s{seed}"


# ---------------------------------------------------------------------------- report

def actions_to_level(outcomes: list[int], steps: list[int], level: float) -> int | None:
    """The number of actions until the success over the last WINDOW grasps first reached ``level``; None if never."""
    total = 0
    for i, ok in enumerate(outcomes):
        total += ok
        if i >= WINDOW:
            total -= outcomes[i - WINDOW]
        if i >= WINDOW - 1 and total >= level * WINDOW - 1e-9:
            return steps[i] + 1
    return None


def _median_or_none(values: list[float | None]) -> float | None:
    """Median with None as 'never', ranked above every number (so None when half or more never got there)."""
    ranked = sorted(values, key=lambda v: float("inf") if v is None else v)
    mid = len(ranked) // 2
    if len(ranked) % 2:
        return ranked[mid]
    a, b = ranked[mid - 1], ranked[mid]
    return None if a is None or b is None else (a + b) / 2


def seed_summary(state_dir: Path, actions: int) -> dict:
    rows = action_rows(state_dir, actions)
    grasps, steps = grasp_outcomes(rows), grasp_steps(rows)
    greedy = grasp_outcomes(rows, greedy_only=True)
    windows = [sum(grasps[k:k + WINDOW]) / len(grasps[k:k + WINDOW]) for k in range(0, len(grasps), WINDOW)]
    full = [len(grasps[k:k + WINDOW]) >= WINDOW // 2 for k in range(0, len(grasps), WINDOW)]
    last = grasps[-LAST:]
    return {"grasp_attempts": len(grasps), "success": sum(grasps) / max(1, len(grasps)),
            "greedy_success": sum(greedy) / max(1, len(greedy)),
            "last_200": sum(last) / max(1, len(last)),
            "windows": windows, "window_judged": full,
            **{f"actions_to_{int(100 * lv)}": actions_to_level(grasps, steps, lv) for lv in LEVELS},
            "moves": sum(1 for r in rows if r[1] not in (None, "grasp")),
            "epsilon_actions": sum(1 for r in rows if r[3] == "epsilon"), **gate_counts(state_dir),
            **loop_counts(state_dir, rows)}


def null_worst_window(frozen_runs: list[list[float]], seeds: int, windows: int, trials: int = 20000) -> dict:
    """What "the worst window against frozen" looks like when learning changes nothing.

    Both rows are drawn as ``seeds`` runs of ``windows`` windows, each window resampled from the frozen row's own
    judged windows of every seed (``frozen_runs``); per window the median over seeds, then the lowest difference.
    Why resampled and not binomial: the frozen runs' windows vary about twice as much as binomial noise at their
    rate would make them (the scenes differ), and that spread is what a learning row's windows carry too.  Windows
    are drawn independently: a run's scenes part ways from its seed's first scenes after its first different
    action, so no lasting per-seed level is assumed.  With a few seeds the minimum lies several points below zero
    by chance alone, so a learning row's worst window is read against this band, not against zero.
    """
    import numpy as np

    pool = np.asarray([w for run in frozen_runs for w in run], dtype=float)
    if pool.size == 0 or seeds <= 0 or windows <= 0:
        return {}
    rng = np.random.default_rng(0)
    a = rng.choice(pool, size=(trials, seeds, windows))
    b = rng.choice(pool, size=(trials, seeds, windows))
    worst = (np.median(a, axis=1) - np.median(b, axis=1)).min(axis=1)
    return {"median": float(np.median(worst)), "p05": float(np.quantile(worst, 0.05)),
            "p_at_least_minus_3": float(np.mean(worst >= -0.03 - 1e-9))}


def summarize(root: Path, rows: list[str], seeds: list[int], actions: int, tag: str) -> dict:
    out: dict = {"actions": actions, "seeds": seeds, "window": WINDOW, "tag": tag, "rows": {}}
    for row in rows:
        per_seed, missing = {}, []
        for seed in seeds:
            d = root / run_name(row, seed, tag)
            done = steps_done(d)
            if done < actions:
                missing.append(f"{run_name(row, seed, tag)} ({done}/{actions} actions)")
                continue
            per_seed[str(seed)] = seed_summary(d, actions)
        r: dict = {"missing": missing, "per_seed": per_seed}
        if per_seed:
            runs = list(per_seed.values())
            n = min(len(s["windows"]) for s in runs)
            r["windows"] = [statistics.median(s["windows"][k] for s in runs) for k in range(n)]
            r["window_judged"] = [all(s["window_judged"][k] for s in runs) for k in range(n)]
            r["last_200"] = statistics.median(s["last_200"] for s in runs)
            r["success"] = statistics.median(s["success"] for s in runs)
            r["greedy_success"] = statistics.median(s["greedy_success"] for s in runs)
            r["picks_per_action"] = statistics.median(s["picks_per_action"] or 0.0 for s in runs)
            r["longest_failure_streak"] = max(s["longest_failure_streak"] for s in runs)
            r["streak_actions"] = statistics.median(s["streak_actions"] for s in runs)
            r["stuck"] = sum(s["stuck"] for s in runs)
            for lv in LEVELS:
                key = f"actions_to_{int(100 * lv)}"
                r[key] = _median_or_none([s[key] for s in runs])
            r["gate"] = {k: sum(s[k] for s in runs) for k in ("challenger", "promote", "drop", "rollback",
                                                               "learner_updates")}
        out["rows"][row] = r
    for row, r in out["rows"].items():
        frozen = out["rows"].get(row.split("-")[0] + "-frozen")
        if row.endswith("-frozen") or not frozen or "windows" not in frozen or "windows" not in r:
            continue
        gaps = [a - b for a, b, ja, jb in zip(r["windows"], frozen["windows"], r["window_judged"],
                                              frozen["window_judged"]) if ja and jb]
        if gaps:
            r["worst_window_vs_frozen"] = min(gaps)
            frozen_runs = [[w for w, j in zip(run["windows"], run["window_judged"]) if j]
                           for run in frozen["per_seed"].values()]
            r["worst_window_if_learning_changed_nothing"] = null_worst_window(frozen_runs, len(r["per_seed"]),
                                                                              len(gaps))
        r["last_200_vs_frozen"] = r["last_200"] - frozen["last_200"]
    return out


COLOURS = {"shifted-frozen": (90, 90, 90), "shifted-gate": (40, 150, 40), "shifted-nogate": (40, 40, 210),
           "shifted-scratch": (0, 140, 230), "train-frozen": (170, 170, 170), "train-gate": (150, 210, 150)}


def plot(summary: dict, path: Path) -> None:
    """Median grasp success per window of 100 grasps, one line per row (hollow: a window not judged)."""
    import cv2
    import numpy as np

    h, w = 400, 720
    img = np.full((h, w, 3), 255, np.uint8)
    x0, x1, y0, y1 = 60, w - 20, h - 60, 30
    lo, hi = 0.0, 1.0
    for k in range(11):
        y = k / 10
        py = int(y0 - (y - lo) / (hi - lo) * (y0 - y1))
        cv2.line(img, (x0, py), (x1, py), (228, 228, 228), 1)
        cv2.putText(img, f"{int(y * 100)}%", (12, py + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    n = max((len(r.get("windows", [])) for r in summary["rows"].values()), default=1) or 1
    for i in range(n):
        px = int(x0 + (i + 0.5) / n * (x1 - x0))
        cv2.putText(img, f"{(i + 1) * WINDOW}", (px - 12, y0 + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    for k, (name, r) in enumerate(summary["rows"].items()):
        colour = COLOURS.get(name, (0, 0, 0))
        pts = [(int(x0 + (i + 0.5) / n * (x1 - x0)), int(y0 - (min(hi, max(lo, v)) - lo) / (hi - lo) * (y0 - y1)))
               for i, v in enumerate(r.get("windows", []))]
        judged = r.get("window_judged", [True] * len(pts))
        for pt, full in zip(pts, judged):   # a window with under half its grasps: hollow, not judged
            cv2.circle(img, pt, 4, colour, -1 if full else 1)
        for a, b in zip(pts, pts[1:]):
            cv2.line(img, a, b, colour, 2)
        cv2.putText(img, name, (x0 + 110 * (k % 6), h - 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, colour, 1)
    title = (f"grasp success per {WINDOW} grasps (median of seeds {summary['seeds']}), {summary['actions']} actions"
             + (f", {summary['tag']}" if summary.get("tag") else ""))
    cv2.putText(img, title, (x0, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    cv2.putText(img, "grasps", (x1 - 50, y0 + 32), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="flgd bench finetune", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", type=Path, default=Path("runs/finetune"))
    p.add_argument("--actions", type=int, default=1000)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--rows", nargs="+", choices=ROWS, default=list(ROWS))
    p.add_argument("--jobs", type=int, default=2, help="runs at once: Ray tasks of one CPU each (default 2)")
    p.add_argument("--engine", choices=("ray", "processes"), default="ray",
                   help="ray (default): the runs are tasks on a local Ray cluster or the one at --address; "
                        "processes: plain child processes on this machine")
    p.add_argument("--address", metavar="HOST:PORT",
                   help="join this Ray cluster (its nodes must see this repository and --root at the same paths)")
    p.add_argument("--shifted", type=Path, default=SHIFTED_CONFIG, help="the second cell's config")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="a learner setting of the learning rows (repeatable)")
    p.add_argument("--tag", default="", help="name of a candidate's runs and report (required with --set)")
    p.add_argument("--report-only", action="store_true")
    p.add_argument("--out", type=Path, default=None,
                   help="report JSON (default benchmarks/results/finetune[-TAG].json); the PNG goes beside it")
    p.add_argument("--worker", nargs=2, metavar=("ROW", "SEED"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.actions < 1 or args.jobs < 1:
        p.error("--actions and --jobs must be >= 1")
    if args.settings and not args.tag:
        p.error("--set needs --tag NAME, so that the candidate's runs do not mix with the default's")
    if args.tag and (not args.tag.replace("-", "").replace("_", "").isalnum()):
        p.error(f"--tag: got {args.tag!r}, expected letters, digits, '-' and '_'")
    try:
        settings = parse_settings(args.settings)
    except ValueError as exc:
        p.error(str(exc))
    shifted = args.shifted.resolve()
    args.rows = with_references(args.rows)
    if args.worker:
        row, seed = args.worker[0], int(args.worker[1])
        d = args.root / run_name(row, seed, args.tag)
        return run_controller(row_config(row, seed, d, shifted, settings), d, args.actions)
    # Every run's config is built (and so checked) before any run starts: a bad --set or --shifted is one line.
    from flgd.config import ConfigError

    try:
        for row in args.rows:
            row_config(row, args.seeds[0], args.root / "check", shifted, settings)
    except (ConfigError, OSError, ValueError) as exc:
        p.error(str(exc))
    failed: dict[str, int] = {}
    if not args.report_only:
        common = ["--root", str(args.root), "--actions", str(args.actions), "--shifted", str(shifted)]
        if args.tag:
            common += ["--tag", args.tag]
        for item in args.settings:
            common += ["--set", item]
        todo = [(run_name(r, s, args.tag), ["bench", "finetune", *common, "--worker", r, str(s)])
                for s in args.seeds for r in args.rows if steps_done(args.root / run_name(r, s, args.tag)) < args.actions]
        failed = {name: code for name, code in run_workers(todo, args.root, args.jobs, ray=args.engine == "ray",
                                                           address=args.address).items() if code != 0}
        if failed:
            print(f"flgd bench finetune: runs failed (see their logs in {args.root}): "
                  + ", ".join(f"{n} (exit {c})" for n, c in failed.items()), file=sys.stderr)
    summary = summarize(args.root, args.rows, args.seeds, args.actions, args.tag)
    summary.update(settings=settings, shifted=os.path.relpath(shifted, REPO),
                   machine=f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
                   command="flgd bench finetune " + " ".join(argv), date=time.strftime("%Y-%m-%d"), commit=_commit())
    out = args.out or REPO / "benchmarks" / "results" / (f"finetune-{args.tag}.json" if args.tag else "finetune.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(summary, indent=2) + "\n")
    plot(summary, out.with_suffix(".png"))
    for name, r in summary["rows"].items():
        if "windows" in r:
            wins = " ".join(_pct(v) for v in r["windows"])
            worst = r.get("worst_window_vs_frozen")
            null = r.get("worst_window_if_learning_changed_nothing") or {}
            band = f" (no change: {100 * null['median']:+.1f}, 5 % {100 * null['p05']:+.1f})" if null else ""
            print(f"{name:16s} last 200 {_pct(r['last_200'])}  to 80% {r['actions_to_80']}  to 90% "
                  f"{r['actions_to_90']}  worst vs frozen "
                  f"{'-' if worst is None else f'{100 * worst:+.1f}'}{band}  gate {r['gate']}  windows {wins}")
            print(f"{'':16s} all grasps {_pct(r['success'])}, picks/action {r['picks_per_action']:.2f}, longest "
                  f"failure streak {r['longest_failure_streak']}, in streaks >= 5 {r['streak_actions']:g} "
                  f"(median), stuck {r['stuck']}")
        if r["missing"]:
            print(f"{name:16s} missing: {', '.join(r['missing'])}")
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 1 if not args.report_only and failed else 0
