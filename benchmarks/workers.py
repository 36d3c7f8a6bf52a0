"""``flgd bench workers``: actions per wall-second of ``flgd train`` in one process and with ``--workers N``.

Each configuration trains a fresh run directory for ``--steps`` steps from the same config and seed; the
configurations are interleaved in ``--rounds`` rounds (one process, then each N, then again), so a shared,
noisy machine slows them alike, and the median over rounds is reported with its ratio to ``--workers 1`` of
the same rounds.  Two rates: over the whole command (start-up included: Ray, the workers' simulators) and in
the steady state (from the first ``--warmup`` actions on, read off the actions' times in ``actions.csv``).

Where the CPU goes, per configuration (medians): the training process (the learner; in one process also the
cell), the workers (their own reports), and the rest of the machine's busy time during the run (Ray's own
processes, start-up of the command -- and any other load, so measure on an otherwise idle machine), all in CPU
seconds per action.

Target (issue 38): ``--workers N`` >= 0.8 x N x ``--workers 1`` for every N with N + 1 <= cores, and
``--workers 1`` >= the one-process rate.

    flgd bench workers [--workers 1 2] [--steps 60] [--rounds 3] [--config cell_config/sim.yaml]
                       [--root runs/bench-workers] [--out benchmarks/results/workers.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _machine_cpu() -> float:
    """CPU seconds the whole machine spent busy so far (/proc/stat): Ray's processes are not children that the
    command waits for, so its rusage would miss them.  Other load on the machine counts too (say so)."""
    fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    ticks = [int(v) for v in fields]
    busy = sum(ticks) - ticks[3] - (ticks[4] if len(ticks) > 4 else 0)  # less idle and iowait
    return busy / os.sysconf("SC_CLK_TCK")


def _run(config: Path, out: Path, steps: int, seed: int, workers: int, warmup: int) -> dict:
    """One training run from scratch; its rates and CPU split."""
    from flgd.training.actions_csv import read_rows

    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "flgd.cli", "train", "--config", str(config), "--steps", str(steps), "--seed",
           str(seed), "--threads", "1", "--out", str(out)]
    if workers:
        cmd += ["--workers", str(workers)]
    cpu0, t0 = _machine_cpu(), time.monotonic()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True,
                          env=dict(os.environ, OMP_NUM_THREADS="1"))
    wall, cpu = time.monotonic() - t0, _machine_cpu() - cpu0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    info = json.loads((out / "run.json").read_text())
    rows = read_rows(out / "actions.csv")
    times = sorted(float(r["time"]) for r in rows if r.get("time"))
    steady = (len(times) - 1 - warmup) / (times[-1] - times[warmup]) if len(times) > warmup + 1 else None
    driver = float(info["segments"][-1].get("process_cpu_seconds", 0.0))
    worker_cpu = [float(w["cpu_seconds"]) for w in info["segments"][-1].get("worker_stats", [])]
    learner = sum(float(r["t_update"] or 0) for r in rows)
    n = len(rows)
    return {"workers": workers, "steps": n, "wall_s": round(wall, 1), "actions_per_s": n / wall,
            "steady_actions_per_s": steady, "updates": info["updates"],
            "cpu_per_action": {"total": cpu / n, "training_process": driver / n, "learner_updates": learner / n,
                               "workers": sum(worker_cpu) / n,
                               "ray_and_other": max(0.0, cpu - driver - sum(worker_cpu)) / n}}


def _median(values: list[float | None]) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="flgd bench workers", description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=REPO / "cell_config" / "sim.yaml")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="the N of --workers N to measure")
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--warmup", type=int, default=5, help="actions left out of the steady-state rate")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--root", type=Path, default=REPO / "runs" / "bench-workers")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "workers.json")
    args = p.parse_args(argv)
    if args.steps <= args.warmup + 1 or args.rounds < 1 or any(n < 1 for n in args.workers):
        p.error("--steps must exceed --warmup + 1, --rounds >= 1, every --workers N >= 1")
    configs = [0] + sorted(set(args.workers) | {1})
    runs: dict[int, list[dict]] = {n: [] for n in configs}
    for r in range(args.rounds):
        for n in configs:
            res = _run(args.config.resolve(), args.root / f"w{n}-r{r}", args.steps, args.seed, n, args.warmup)
            runs[n].append(res)
            label = "one process" if n == 0 else f"--workers {n}"
            print(f"round {r + 1}: {label:12s} {res['actions_per_s']:.3f} actions/s overall, "
                  f"{res['steady_actions_per_s'] or 0:.3f} steady; CPU s/action {res['cpu_per_action']}", flush=True)
    summary: dict = {"command": "flgd bench workers " + " ".join(argv), "date": time.strftime("%Y-%m-%d"),
                     "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
                     "commit": _commit(), "config": os.path.relpath(args.config.resolve(), REPO),
                     "steps": args.steps, "rounds": args.rounds, "configurations": {}}
    ref = [x["steady_actions_per_s"] for x in runs[1]]
    for n in configs:
        rates = [x["actions_per_s"] for x in runs[n]]
        steady = [x["steady_actions_per_s"] for x in runs[n]]
        ratio = _median([a / b for a, b in zip(steady, ref) if a and b])
        cpu = {k: _median([x["cpu_per_action"][k] for x in runs[n]]) for k in runs[n][0]["cpu_per_action"]}
        summary["configurations"]["one process" if n == 0 else f"workers {n}"] = {
            "actions_per_s": _median(rates), "steady_actions_per_s": _median(steady),
            "steady_ratio_to_workers_1": ratio, "target_ratio": None if n == 0 else 0.8 * n,
            "cpu_seconds_per_action": cpu, "runs": runs[n]}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2) + "\n")
    for name, c in summary["configurations"].items():
        print(f"{name:12s} median {c['actions_per_s']:.3f} actions/s overall, {c['steady_actions_per_s']:.3f} "
              f"steady, x{c['steady_ratio_to_workers_1']:.2f} of --workers 1; CPU s/action "
              + ", ".join(f"{k} {v:.2f}" for k, v in c["cpu_seconds_per_action"].items()))
    print(f"wrote {args.out}")
    return 0


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
