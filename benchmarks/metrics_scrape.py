"""``flgd bench metrics-scrape``: what one Prometheus scrape of ``flgd run --metrics`` costs as the log grows.

A scrape reads the store (``compute_stats``, faults by kind, the phase histograms), so its cost grows with
the action log a cell accumulates over months.  This writes a synthetic action log of N cycles into a
fresh store (one bulk transaction; real cycles are written one by one), then times the daemon's collector
(``flgd.daemon.prometheus.CellCollector``) against it: the first scrape, which builds the phase
histograms over the whole log, and the following ones, which read only new rows.  The controller is a
stand-in exposing what the collector reads; the cost measured is the store's.

Reported per N: first scrape, median of ``--scrapes`` later scrapes (seconds), and the text size.
"""

from __future__ import annotations

import argparse
import json
import platform
import sqlite3
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

REPO = Path(__file__).resolve().parents[1]


def _fill(db_path: Path, cycles: int) -> None:
    from flgd.store import TIMING_PHASES

    cols = ["step", "time", "backend", "outcome", "primitive", "kind", "success", "duration",
            *(f"t_{p}" for p in TIMING_PHASES)]
    db = sqlite3.connect(db_path)
    with db:
        db.executemany(
            f"INSERT INTO actions({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})",
            ((i, 1.7e9 + 10 * i, "sim", "executed", "grasp" if i % 4 else "push", "grasp" if i % 4 else "push",
              int(i % 3 != 0), 8.0 + (i % 7), *(0.05 * (1 + (i + k) % 5) for k in range(len(TIMING_PHASES))))
             for i in range(cycles)))
        db.executemany("INSERT INTO events(time, kind, message) VALUES (?, 'fault', ?)",
                       ((1.7e9 + i, "cell fault: protective stop") for i in range(cycles // 1000)))
    db.close()


def _stand_in(store) -> SimpleNamespace:
    from flgd.config import CellConfig
    from flgd.daemon.state import State, StateMachine

    status = {"policy": "policy policies/flg-sim.safetensors", "last_checkpoint": "", "backend": "sim",
              "config": "cell_config/sim.yaml", "learner_updates": 0, "learner_backlog": 0, "learner_dropped": 0,
              "learner_running": True, "replay_size": 0}
    return SimpleNamespace(state=StateMachine(State.RUNNING), config=CellConfig(), store=store, learner=None,
                           status=lambda: status)


def measure(cycles: int, scrapes: int) -> dict:
    from prometheus_client import CollectorRegistry, generate_latest

    from flgd.daemon.prometheus import CellCollector
    from flgd.store import Store

    with tempfile.TemporaryDirectory(prefix="flgd-bench-metrics-") as d:
        store = Store(d)
        _fill(store.path, cycles)
        registry = CollectorRegistry()
        registry.register(CellCollector(_stand_in(store)))
        t = time.perf_counter()
        text = generate_latest(registry)
        first = time.perf_counter() - t
        later = []
        for _ in range(scrapes):
            t = time.perf_counter()
            generate_latest(registry)
            later.append(time.perf_counter() - t)
        store.close()
    return {"cycles": cycles, "first_scrape_s": round(first, 4), "scrape_median_s": round(statistics.median(later), 4),
            "bytes": len(text)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="flgd bench metrics-scrape", description=__doc__.splitlines()[0])
    p.add_argument("--cycles", type=int, nargs="+", default=[1000, 100_000, 1_000_000],
                   help="sizes of the synthetic action log")
    p.add_argument("--scrapes", type=int, default=5, help="later scrapes timed per size")
    p.add_argument("--out", help="write the results as JSON here")
    args = p.parse_args(argv)
    rows = [measure(n, args.scrapes) for n in args.cycles]
    for r in rows:
        print(f"{r['cycles']:>9} cycles: first scrape {r['first_scrape_s']:.3f} s, later scrapes "
              f"{r['scrape_median_s']:.3f} s (median of {args.scrapes}), {r['bytes']} bytes")
    if args.out:
        Path(args.out).write_text(json.dumps({"benchmark": "metrics-scrape", "machine": platform.node(),
                                              "python": sys.version.split()[0], "results": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
