"""``flgd bench learning``: learning efficiency of FLG against its ablations (paper IV-A), and Table II.

1. Curves: FLG, DPEN (no masks) and rho-FCN (VPG head, x16 upsampling, no
   skip) -- all on the fast trunk, see flgd.learning.networks -- trained from
   scratch with ``--objects`` (10) objects, ``--seeds`` (0 1 2) each, by
   ``flgd train`` in the same harness.  Reported per variant: the steps
   (actions) until the rolling grasp success over the last 200 grasp attempts
   (the paper's figure) first reaches 80 % and 90 %, and the same for a window
   of 50; median and min..max over seeds, plus every seed's value, and one PNG
   of all curves.
2. Table II: Grasping-only against Grasping-Moving on the preset highly
   cluttered piles (sim_cell/scenes): an FLG run trained with
   ``exploration.grasp_only`` (``<root>/flg-grasponly-s<seed>``) and the
   grasp-and-move FLG run of part 1, each evaluated frozen (greedy) by
   ``flgd eval`` on every preset, ``--eval-runs`` runs per scene; completion
   rate and grasp success.

Every run is a ``flgd train`` run directory under ``--root``, so a run that is
cut short (Ctrl-C, a session that ends) is continued by running the bench
again; finished runs are skipped.  Runs go in parallel processes
(``--jobs``, one torch thread each).  ``--report-only`` only reads whatever
runs exist and marks the unfinished ones.  A Table II evaluation file that
cannot be read (cut off while being written by an older version) counts as
missing: the report says so and the next bench run redoes it.  A run whose
run.json is damaged stops the bench (exit 2) with the file named.

    flgd bench learning [--root runs/learning] [--steps 1000] [--seeds 0 1 2] [--jobs 2]
    flgd bench learning --report-only
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from flgd.atomic_file import write_atomically
from flgd.training.actions_csv import read_rows
from flgd.training.curve import (grasp_series, plot_curves, rolling_success, spread, steps_to_threshold,
                                success_by_rule)
from flgd.training.run import RunFileError, read_run_info

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "cell_config" / "sim.yaml"
VARIANTS = ("flg", "dpen", "rho-fcn")
THRESHOLDS = (0.8, 0.9)
WINDOWS = (200, 50)
RULE_SPLIT_STEPS = 200  # the greedy-vs-random split is reported over this many final steps


@dataclass(frozen=True)
class RunSpec:
    name: str
    variant: str
    seed: int
    grasp_only: bool = False

    def args(self, config: Path, objects: int, steps: int, out: Path, workers: int = 0) -> list[str]:
        cmd = [sys.executable, "-m", "flgd.cli", "train", "--config", str(config), "--variant", self.variant,
               "--objects", str(objects), "--steps", str(steps), "--seed", str(self.seed), "--threads", "1",
               "--out", str(out)]
        if workers:
            cmd += ["--workers", str(workers)]
        return cmd + (["--grasp-only"] if self.grasp_only else [])


@dataclass
class RunResult:
    spec: RunSpec
    directory: Path
    rows: list[dict]
    step: int
    target: int
    status: str

    @property
    def complete(self) -> bool:
        return self.status == "finished" and self.step >= self.target


def run_specs(variants: list[str], seeds: list[int], table2: bool) -> list[RunSpec]:
    specs = [RunSpec(f"{v}-s{s}", v, s) for s in seeds for v in variants]
    if table2 and "flg" in variants:  # Table II compares two FLG runs
        specs += [RunSpec(f"flg-grasponly-s{s}", "flg", s, grasp_only=True) for s in seeds]
    return specs


def read_run(directory: Path, spec: RunSpec, steps: int) -> RunResult | None:
    """The run in ``directory`` (None: not started); a damaged run.json raises ``RunFileError``."""
    info = read_run_info(directory)
    if info is None:
        return None
    rows = read_rows(directory / "actions.csv")
    step = max((int(r["step"]) for r in rows if r.get("step")), default=-1) + 1
    return RunResult(spec, directory, rows, step, steps, str(info.get("status", "unknown")))


# ---------------------------------------------------------------------- running

def train_all(specs: list[RunSpec], root: Path, config: Path, objects: int, steps: int, jobs: int,
              workers: int = 0) -> bool:
    """Start or continue every unfinished run, ``jobs`` at a time; Ctrl-C stops them cleanly.

    Returns False when interrupted (the runs resume on the next call)."""
    todo = []
    for spec in specs:
        res = read_run(root / spec.name, spec, steps)
        if res is not None and res.complete:
            print(f"  {spec.name}: finished ({res.step} steps), skipped")
            continue
        todo.append(spec)
    running: dict[str, subprocess.Popen] = {}
    stopping = False

    def on_signal(signum, _frame) -> None:
        nonlocal stopping
        stopping = True
        for proc in running.values():
            proc.send_signal(signal.SIGINT)

    old = signal.signal(signal.SIGINT, on_signal)
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    try:
        while (todo and not stopping) or running:
            while todo and not stopping and len(running) < jobs:
                spec = todo.pop(0)
                out = root / spec.name
                out.mkdir(parents=True, exist_ok=True)
                log = (root / f"{spec.name}.out").open("a")
                print(f"  {spec.name}: training to {steps} steps (log {log.name})")
                # own session: a terminal's Ctrl-C reaches only the bench, which forwards exactly one
                # SIGINT (a second one would make a run exit without its final checkpoint)
                running[spec.name] = subprocess.Popen(spec.args(config, objects, steps, out, workers), stdout=log,
                                                      stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                                      env=env, cwd=REPO, start_new_session=True)
            for name, proc in list(running.items()):
                if proc.poll() is not None:
                    print(f"  {name}: exit code {proc.returncode}")
                    del running[name]
            time.sleep(2.0)
    finally:
        signal.signal(signal.SIGINT, old)
    return not stopping


def read_table2(path: Path) -> tuple[dict | None, str]:
    """(overall metrics, '') of a Table II evaluation file, or (None, what is wrong with it).

    An unreadable file must count as missing, not stop every later report: a bench cut off while
    ``flgd eval`` wrote it would otherwise never redo the evaluation."""
    try:
        rep = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        return None, f"{type(exc).__name__}: {exc}"
    overall = rep.get("overall") if isinstance(rep, dict) else None
    if not isinstance(overall, dict):
        return None, "no 'overall' object (not a flgd eval report)"
    return overall, ""


def evaluate_table2(results: dict[str, RunResult], root: Path, eval_runs: int, seeds: list[int]) -> None:
    """``flgd eval`` of the newest checkpoint of each Table II run on the presets (cached per checkpoint)."""
    from sim_cell.cell import preset_scenes

    scenes = [str(p) for p in preset_scenes()]
    for seed in seeds:
        for name, grasp_only in ((f"flg-s{seed}", False), (f"flg-grasponly-s{seed}", True)):
            res = results.get(name)
            if res is None or not res.complete:
                continue
            ckpts = sorted((res.directory / "checkpoints").glob("checkpoint-*.safetensors"))
            if not ckpts:
                continue
            out = res.directory / f"table2-{ckpts[-1].stem}-r{eval_runs}.json"
            if out.exists():
                overall, problem = read_table2(out)
                if overall is not None:
                    continue
                print(f"  {out.name}: unreadable ({problem}), evaluating again")
            # flgd eval writes its report in place; it goes to a hidden file (not matched by the
            # table2-* glob) and is moved to ``out`` atomically only once whole and readable
            partial = out.with_name(f".{out.name}.partial")
            cmd = [sys.executable, "-m", "flgd.cli", "eval", "--config", str(res.directory / "config.yaml"),
                   "--policy", str(ckpts[-1]), "--scenes", *scenes, "--runs", str(eval_runs), "--seed", str(seed),
                   "--json", str(partial), "--png", str(out.with_suffix(".png")), "--quiet"] + \
                (["--grasp-only"] if grasp_only else [])
            print(f"  evaluating {name} ({ckpts[-1].name}) on {len(scenes)} presets x {eval_runs} runs")
            try:
                proc = subprocess.run(cmd, cwd=REPO, check=False, env=dict(os.environ, OMP_NUM_THREADS="1"))
                if proc.returncode == 0 and read_table2(partial)[0] is not None:
                    write_atomically(out, partial.read_bytes(), mode=0o644)
                else:
                    print(f"  {name}: evaluation failed (exit code {proc.returncode}); it is redone by the "
                          "next run of the bench")
            finally:
                partial.unlink(missing_ok=True)


# ---------------------------------------------------------------------- report

def _fmt(v: int | None, res: RunResult) -> str:
    if v is not None:
        return str(v)
    return f"> {res.step}" if res.complete else f"not yet (at {res.step})*"


def _learner_settings(directory: Path) -> str:
    """What a run's learning started from and how it learned, from its config.yaml (so that tables
    made with different settings are never mistaken for one another)."""
    import yaml

    try:
        lc = (yaml.safe_load((directory / "config.yaml").read_text()) or {}).get("learning", {})
    except (OSError, yaml.YAMLError) as exc:
        return f"config.yaml unreadable ({exc})"
    start = f"trunk {lc['init_trunk']}" if lc.get("init_trunk") else "random initial weights"
    return (f"start {start}; lr {lc.get('learning_rate')}, {lc.get('updates_per_action')} updates/action, "
            f"batch {lc.get('batch_size')}")


def report(results: dict[str, RunResult], variants: list[str], seeds: list[int], root: Path,
           steps: int, objects: int, eval_runs: int) -> dict:
    lines = [f"# flgd bench learning ({objects} objects, target {steps} steps per run)", "",
             f"machine: {platform.node()}, {os.cpu_count()} CPUs, {platform.processor() or platform.machine()}; "
             f"runs in {root}", "",
             "Steps (actions) until the rolling grasp success over the last W grasp attempts first reaches the "
             "threshold; median [min..max] over seeds (a run that never reached it ranks last).  "
             "`*` = run not finished yet.", ""]
    settings: dict[str, list[str]] = {}
    for name, res in sorted(results.items()):
        settings.setdefault(_learner_settings(res.directory), []).append(name)
    for text, names in settings.items():
        lines.append(f"learner settings ({', '.join(names)}): {text}")
    lines.append("")
    out: dict = {"objects": objects, "steps": steps, "variants": {}, "settings": settings}
    header = "| variant | W | 80 % | 90 % | per seed (80 % / 90 %) | final rolling success |"
    lines += [header, "|---|---|---|---|---|---|"]
    for v in variants:
        runs = [results[f"{v}-s{s}"] for s in seeds if f"{v}-s{s}" in results]
        entry: dict = {"runs": {r.spec.name: {"step": r.step, "status": r.status, "complete": r.complete}
                                for r in runs}}
        for w in WINDOWS:
            per_seed = {}
            for r in runs:
                series = grasp_series(r.rows)
                per_seed[r.spec.name] = {t: steps_to_threshold(series, t, w) for t in THRESHOLDS}
                _, rate = rolling_success(series, w)
                per_seed[r.spec.name]["final"] = float(rate[-1]) if len(rate) else None
            spreads = {t: spread([per_seed[n][t] for n in per_seed]) for t in THRESHOLDS}
            entry[f"window_{w}"] = {
                "per_seed": {n: {str(k): val for k, val in d.items()} for n, d in per_seed.items()},
                **{f"steps_to_{int(100 * t)}": vars(spreads[t]) for t in THRESHOLDS}}
            seeds_txt = "; ".join(
                f"s{r.spec.seed}: {_fmt(per_seed[r.spec.name][0.8], r)} / {_fmt(per_seed[r.spec.name][0.9], r)}"
                for r in runs)
            finals = ", ".join("-" if per_seed[r.spec.name]["final"] is None
                               else f"{100 * per_seed[r.spec.name]['final']:.0f}%" for r in runs)
            lines.append(f"| {v} | {w} | {spreads[0.8].text() if runs else '-'} | "
                         f"{spreads[0.9].text() if runs else '-'} | {seeds_txt or 'no runs'} | {finals} |")
        out["variants"][v] = entry
    rule_lines = []
    for v in variants:
        for s in seeds:
            r = results.get(f"{v}-s{s}")
            if r is None or not r.rows:
                continue
            split = success_by_rule(r.rows, last_steps=RULE_SPLIT_STEPS)
            cells = []
            for rule in ("greedy", "epsilon"):
                done, tried = split.get(rule, (0, 0))
                cells.append(f"{100 * done / tried:.0f} % ({done}/{tried})" if tried else "-")
            rule_lines.append(f"| {r.spec.name} | {cells[0]} | {cells[1]} |")
            out["variants"][v]["runs"][r.spec.name]["grasps_by_rule_last_steps"] = {
                k: {"successes": a, "attempts": b} for k, (a, b) in split.items()}
    if rule_lines:
        lines += ["", f"Grasp success by decision rule over each run's last {RULE_SPLIT_STEPS} steps (greedy = the "
                  "policy's own choice; epsilon = a random point inside the mask):", "",
                  "| run | greedy | epsilon |", "|---|---|---|", *rule_lines]
    curves = {}
    groups = {}
    for v in variants:
        for s in seeds:
            r = results.get(f"{v}-s{s}")
            if r is not None and r.rows:
                label = f"{v} s{s}" + ("" if r.complete else " (unfinished)")
                curves[label], groups[label] = r.rows, v
    if curves:
        plot_curves(root / "curves.png", curves, windows=(200,), groups=groups,
                    title=f"rolling grasp success (last 200 grasps), {objects} objects")
        lines += ["", f"curves: {root / 'curves.png'}"]

    table2 = []
    for s in seeds:
        for name, mode in ((f"flg-s{s}", "Grasping-Moving"), (f"flg-grasponly-s{s}", "Grasping-only")):
            res = results.get(name)
            evals = sorted(res.directory.glob(f"table2-*-r{eval_runs}.json")) if res else []
            if not evals:
                table2.append((mode, s, None, res, ""))
                continue
            overall, problem = read_table2(evals[-1])
            table2.append((mode, s, overall, res,
                           f"{evals[-1].name} unreadable ({problem}), will be redone" if problem else ""))
    if any(t[2] is not None or t[3] is not None for t in table2):
        lines += ["", "## Table II: preset cluttered piles, frozen greedy policy", "",
                  "| mode | seed | completion | grasp success | grasps | runs |", "|---|---|---|---|---|---|"]
        out["table2"] = []
        for mode, s, ov, res, problem in table2:
            if ov is None:
                state = problem or ("no run" if res is None else ("not evaluated" if res.complete else
                                                                  f"training not finished (at {res.step})*"))
                lines.append(f"| {mode} | {s} | {state} | | | |")
                continue
            comp, gs = ov.get("completion"), ov.get("grasp_success")
            lines.append(f"| {mode} | {s} | {'-' if comp is None else f'{100 * comp:.0f}%'} | "
                         f"{'-' if gs is None else f'{100 * gs:.1f}%'} | "
                         f"{ov.get('grasp_successes', '-')}/{ov.get('grasp_attempts', '-')} | {ov.get('runs', '-')} |")
            out["table2"].append({"mode": mode, "seed": s, **{k: ov.get(k) for k in (
                "completion", "grasp_success", "grasp_successes", "grasp_attempts", "runs")}})
    text = "\n".join(lines) + "\n"
    write_atomically(root / "report.md", text.encode(), mode=0o644)
    write_atomically(root / "report.json", (json.dumps(out, indent=2) + "\n").encode(), mode=0o644)
    print(text)
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="flgd bench learning", description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(DEFAULT_CONFIG))
    ap.add_argument("--root", default=str(REPO / "runs" / "learning"), help="directory of the run directories")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--objects", type=int, default=10)
    ap.add_argument("--steps", type=int, default=1000, help="training steps per run")
    ap.add_argument("--jobs", type=int, default=2, help="parallel training processes (one torch thread each)")
    ap.add_argument("--workers", type=int, default=0,
                    help="each run is `flgd train --workers N` (N Ray workers and its learner; default 0: one process)")
    ap.add_argument("--no-table2", action="store_true", help="skip the grasp-only vs grasp-and-move part")
    ap.add_argument("--eval-runs", type=int, default=2, help="Table II: runs per preset scene")
    ap.add_argument("--report-only", action="store_true", help="no training: report on the runs that exist")
    args = ap.parse_args(argv)
    if args.jobs < 1 or args.steps < 1 or args.eval_runs < 1 or not 1 <= args.objects <= 60:
        print("flgd bench learning: --jobs, --steps and --eval-runs must be >= 1, --objects 1..60", file=sys.stderr)
        return 2
    root = Path(args.root).resolve()
    root.mkdir(parents=True, exist_ok=True)
    specs = run_specs(args.variants, args.seeds, not args.no_table2)
    interrupted = False
    try:
        if not args.report_only:
            interrupted = not train_all(specs, root, Path(args.config).resolve(), args.objects, args.steps,
                                        args.jobs, max(0, args.workers))
            if interrupted:
                print("flgd bench learning: interrupted; run the same command again to resume (no Table II "
                      "evaluation started)", file=sys.stderr)
        results = {}
        for spec in specs:
            res = read_run(root / spec.name, spec, args.steps)
            if res is not None:
                results[spec.name] = res
    except RunFileError as exc:  # found before any training starts: train_all reads every run first
        print(f"flgd bench learning: {exc}", file=sys.stderr)
        return 2
    if not args.report_only and not args.no_table2 and not interrupted:
        evaluate_table2(results, root, args.eval_runs, args.seeds)
    report(results, args.variants, args.seeds, root, args.steps, args.objects, args.eval_runs)
    return 130 if interrupted else 0
