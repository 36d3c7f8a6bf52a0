"""``flgd bench memory``: what returning freed memory to the system (``flgd.memory``) saves and costs.

Each run is a fresh process (the C library's settings hold from the process start): the daemon's cycle on
sim_cell with the agent, the store and the replay, and after each cycle one learner update run in line (not on
the learner thread, so that its time is measured without a second thread competing).  Reported per variant:
resident memory at the end and its peak, and the medians of the decision time, the learner update time and
the controller's time per cycle.  The variants alternate run by run, so a busy machine slows both alike; the
ratios are against ``default`` from the same invocation.

    flgd bench memory --cycles 150 --runs 3 --out benchmarks/results/memory-DATE.json
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
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VARIANTS = ("default", "return-freed", "trim-each-cycle")


def _rss() -> tuple[int, int]:
    values = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(value.split()[0]) * 1024
    return values["VmRSS"], values["VmHWM"]


def worker(variant: str, config: str, cycles: int) -> dict:
    if variant == "return-freed":
        from flgd.memory import return_freed_memory

        if not return_freed_memory():
            raise SystemExit("mallopt is not available here")
    import torch

    from flgd.cell import make_cell
    from flgd.config import load_sim_config
    from flgd.cycle import CycleRunner
    from flgd.learning.agent import Agent
    from flgd.learning.learner import Learner
    from flgd.learning.policy_file import load_policy
    from flgd.learning.replay import PrioritizedReplay
    from flgd.store import Store

    torch.set_num_threads(1)
    cfg = load_sim_config(config, "the benchmark runs on sim_cell")
    with tempfile.TemporaryDirectory(prefix="flgd-bench-memory-") as state:
        cfg = dataclasses.replace(cfg, state_dir=state)
        store = Store(state)
        if cfg.policy:  # the shipped policy: the decisions and the objects cleared are those of the daemon
            net = load_policy(cfg.policy, expected_variant=cfg.learning.network).network
        else:
            from flgd.learning.networks import build_network

            net = build_network(cfg.learning.network, rotations=cfg.learning.rotations, seed=cfg.learning.seed)
        agent = Agent(cfg, net, seed=cfg.learning.seed)
        replay = PrioritizedReplay.from_config(cfg.learning)
        learner = Learner(cfg, net, replay, mailbox=agent.mailbox)
        cell = make_cell(cfg, "sim")
        decide, update, controller, trim = [], [], [], []
        if variant == "trim-each-cycle":
            from flgd.memory import trim_heap
        try:
            runner = CycleRunner(cfg, cell, agent, store=store, replay=replay, learner=None)
            done = 0
            while done < cycles:
                rec = runner.run_once()
                if rec.outcome == "empty":
                    continue
                decide.append(rec.timings.get("decide", 0.0))
                controller.append(rec.duration - rec.timings.get("execute", 0.0))
                t0 = time.perf_counter()
                learner.update()
                update.append(time.perf_counter() - t0)
                if variant == "trim-each-cycle":
                    t0 = time.perf_counter()
                    trim_heap()
                    trim.append(time.perf_counter() - t0)
                done += 1
        finally:
            cell.close()
            store.close()
        rss, peak = _rss()
    return {"variant": variant, "cycles": cycles, "rss_bytes": rss, "rss_peak_bytes": peak,
            "decide_s": statistics.median(decide), "update_s": statistics.median(update),
            "controller_s": statistics.median(controller), "trim_s": statistics.median(trim) if trim else 0.0}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="flgd bench memory", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(REPO / "cell_config" / "sim.yaml"))
    p.add_argument("--cycles", type=int, default=150)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--out", type=Path)
    p.add_argument("--worker", choices=VARIANTS, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.config, args.cycles)))
        return 0
    runs: list[dict] = []
    for i in range(args.runs):
        for variant in VARIANTS:
            out = subprocess.run([sys.executable, "-m", "flgd.cli", "bench", "memory", "--worker", variant,
                                  "--config", args.config, "--cycles", str(args.cycles)],
                                 capture_output=True, text=True, cwd=REPO, env=dict(os.environ, OMP_NUM_THREADS="1"))
            if out.returncode != 0:
                print(out.stderr[-3000:], file=sys.stderr)
                return 1
            row = json.loads(out.stdout.strip().splitlines()[-1])
            runs.append(row)
            print(f"run {i} {variant:13s} RSS {row['rss_bytes'] / 2**20:7.1f} MiB (peak "
                  f"{row['rss_peak_bytes'] / 2**20:7.1f})  decide {row['decide_s'] * 1000:6.1f} ms  update "
                  f"{row['update_s'] * 1000:6.1f} ms  controller {row['controller_s'] * 1000:6.1f} ms  trim "
                  f"{row['trim_s'] * 1000:5.1f} ms", flush=True)
    summary: dict = {"runs": runs, "medians": {}}
    for variant in VARIANTS:
        rows = [r for r in runs if r["variant"] == variant]
        summary["medians"][variant] = {k: statistics.median(r[k] for r in rows)
                                       for k in ("rss_bytes", "rss_peak_bytes", "decide_s", "update_s",
                                                 "controller_s")}
    base = summary["medians"]["default"]
    summary["ratio_to_default"] = {v: {k: summary["medians"][v][k] / base[k] for k in base} for v in VARIANTS[1:]}
    summary.update({"command": "flgd bench memory " + " ".join(argv if argv is not None else sys.argv[1:]),
                    "machine": f"{platform.node()} {os.cpu_count()} cores", "date": time.strftime("%Y-%m-%d"),
                    "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                             text=True, cwd=REPO).stdout.strip()})
    print(json.dumps(summary["ratio_to_default"], indent=2))
    if args.out:
        args.out.write_text(json.dumps(summary, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
