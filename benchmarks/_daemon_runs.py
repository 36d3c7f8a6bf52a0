"""Runs of the daemon's own Controller for benchmarks: one config per run in its own process and state directory,
resumable (a run continues from its state directory), and what its store says afterwards.

``flgd bench daemon_learning`` and ``flgd bench finetune`` both use it, so that every row they compare runs the
same cycle, background learner and gate as ``flgd run``.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def steps_done(state_dir: Path) -> int:
    """Actions in a run's log (0 for a run not started or a store that cannot be read)."""
    db_path = state_dir / "flgd.sqlite"
    if not db_path.exists():
        return 0
    db = sqlite3.connect(db_path)
    try:
        return int(db.execute("SELECT COALESCE(MAX(step) + 1, 0) FROM actions").fetchone()[0])
    except sqlite3.Error:
        return 0
    finally:
        db.close()


def run_controller(cfg: Any, state_dir: Path, actions: int) -> int:
    """One run: the daemon's Controller on ``cfg`` until ``actions`` actions are in its log (a run already begun
    continues: the Controller draws the seeds of its continuation, ``flgd.wiring.continuing_config``)."""
    import logging

    from flgd.config import dump_config
    from flgd.daemon.controller import Controller
    from flgd.wiring import continuing_config

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(message)s")
    done = steps_done(state_dir)
    state_dir.mkdir(parents=True, exist_ok=True)
    # the record of a continuation shows the seeds it runs with
    (state_dir / ("config.yaml" if done == 0 else f"config-from-{done}.yaml")).write_text(
        dump_config(continuing_config(cfg, done)))
    ctl = Controller(cfg, autostart=True)
    ctl.setup()
    prior = ctl.learner.prior
    if prior is not None:  # the record that the setting acted
        print(f"prior sample {prior.path}: {len(prior)} transitions, share {ctl.learner.prior_share}", flush=True)
    try:
        ctl.run_loop(stop_requested=lambda: ctl.runner.step >= actions)
    finally:
        ctl.shutdown()
        if prior is not None:
            print(f"prior transitions drawn: {ctl.learner.prior_drawn} in {ctl.learner.updates} updates", flush=True)
    return 0


def run_workers(jobs: list[tuple[str, list[str]]], root: Path, parallel: int, *, ray: bool = False,
                address: str | None = None) -> dict[str, int]:
    """Run ``(name, argv)`` worker commands (``python -m flgd.cli`` + argv), ``parallel`` at a time, one core each,
    logging to ``root/NAME.log``; returns each name's exit code.  With ``ray`` each command is a Ray task of one
    CPU (``run_on_ray``)."""
    if ray:
        return run_on_ray(jobs, root, parallel, address)
    todo = list(jobs)
    running: list[tuple[subprocess.Popen, str]] = []
    codes: dict[str, int] = {}
    env = dict(os.environ, OMP_NUM_THREADS="1")
    root.mkdir(parents=True, exist_ok=True)
    while todo or running:
        while todo and len(running) < parallel:
            name, argv = todo.pop(0)
            log = root / f"{name}.log"
            with open(log, "ab") as out:
                proc = subprocess.Popen([sys.executable, "-m", "flgd.cli", *argv], stdout=out,
                                        stderr=subprocess.STDOUT, env=env, cwd=REPO)
            running.append((proc, name))
            print(f"started {name} (log {log})", flush=True)
        time.sleep(0.5)
        for proc, name in list(running):
            if proc.poll() is not None:
                running.remove((proc, name))
                codes[name] = proc.returncode
                print(f"{name} finished with {proc.returncode}", flush=True)
    return codes


def _interruptible_child() -> None:
    """In the command's process before it starts: SIGINT unblocked (a Ray worker blocks it, and its children
    inherit that) and sent when the Ray worker dies, so a stopped bench stops its runs cleanly (a checkpoint)."""
    import ctypes
    import signal

    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGINT))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _run_command(argv: list[str], log: str) -> int:
    """One worker command, where Ray placed it (the repository and ``root`` at the same paths on every node)."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    with open(log, "ab") as out:
        return subprocess.run([sys.executable, "-m", "flgd.cli", *argv], stdout=out, stderr=subprocess.STDOUT,
                              env=env, cwd=REPO, preexec_fn=_interruptible_child).returncode


def run_on_ray(jobs: list[tuple[str, list[str]]], root: Path, parallel: int, address: str | None = None,
               retries: int = 1) -> dict[str, int]:
    """``run_workers`` on Ray: each command a task of one CPU on a local cluster of ``parallel`` CPUs (or the one at
    ``address``).  A task whose Ray worker died (a node lost) runs again ``retries`` times: every run resumes
    from its state directory, so nothing is done twice."""
    from flgd.training.ray_engine import start_engine, worker_lost_errors

    root.mkdir(parents=True, exist_ok=True)
    if not jobs:
        return {}
    engine = start_engine(address, parallel)
    ray = engine.ray
    lost = worker_lost_errors(ray)
    task = ray.remote(num_cpus=1, max_retries=0)(_run_command)
    codes: dict[str, int] = {}
    tries: dict[str, int] = {}
    try:
        todo = list(jobs)
        running: dict[Any, tuple[str, list[str]]] = {}
        while todo or running:
            while todo and len(running) < parallel:
                name, argv = todo.pop(0)
                log = root.resolve() / f"{name}.log"
                running[task.remote(argv, str(log))] = (name, argv)
                print(f"started {name} on Ray (log {log})", flush=True)
            ready, _ = ray.wait(list(running), num_returns=1, timeout=1.0)  # Ctrl-C gets a turn
            if not ready:
                continue
            name, argv = running.pop(ready[0])
            try:
                codes[name] = int(ray.get(ready[0]))
            except ray.exceptions.RayTaskError as exc:  # starting the command failed (no Python, no log dir)
                print(f"{name}: {str(exc).strip().splitlines()[-1]}", flush=True)
                codes[name] = -1
            except lost as exc:
                tries[name] = tries.get(name, 0) + 1
                print(f"{name}: its Ray worker was lost ({str(exc).splitlines()[0]})", flush=True)
                if tries[name] <= retries:
                    todo.append((name, argv))
                    continue
                codes[name] = -1
            print(f"{name} finished with {codes[name]}", flush=True)
    finally:
        engine.stop()
    return codes


def action_rows(state_dir: Path, actions: int) -> list[tuple]:
    """(step, primitive, success, rule, policy, outcome) of the first ``actions`` actions."""
    db = sqlite3.connect(state_dir / "flgd.sqlite")
    try:
        return db.execute("SELECT step, primitive, success, rule, policy, outcome FROM actions "
                          "WHERE step < ? ORDER BY step", (actions,)).fetchall()
    finally:
        db.close()


def gate_counts(state_dir: Path) -> dict:
    """Challengers, promotions, drops, rollbacks and learner updates of a run."""
    db = sqlite3.connect(state_dir / "flgd.sqlite")
    try:
        kinds = dict(db.execute("SELECT kind, COUNT(*) FROM gate_events GROUP BY kind").fetchall())
        updates = db.execute("SELECT value FROM counters WHERE name='learner_updates'").fetchone()
    finally:
        db.close()
    out = {k: int(kinds.get(k, 0)) for k in ("challenger", "promote", "drop", "rollback")}
    out["learner_updates"] = int(updates[0]) if updates else 0
    return out


def loop_counts(state_dir: Path, rows: list[tuple]) -> dict:
    """Picks per action, the longest failure streak, actions in streaks of >= 5 and the times the cell declared
    itself stuck (re-laying its scene) in a run: the loops a rate per grasp hides."""
    from flgd.evaluation.metrics import LONG_STREAK

    decided = [r for r in rows if r[5] in ("executed", "refused")]
    db = sqlite3.connect(state_dir / "flgd.sqlite")
    try:
        succeeded = {int(step) for step, in db.execute("SELECT step FROM actions WHERE reward > 0")}
        stuck = db.execute("SELECT COUNT(*) FROM events WHERE kind='stuck'").fetchone()[0]
    finally:
        db.close()
    picks = sum(1 for r in decided if r[1] == "grasp" and r[2] == 1)
    longest = streak = in_long = 0
    for r in decided:
        if r[0] in succeeded:
            in_long += streak if streak >= LONG_STREAK else 0
            streak = 0
        else:
            streak += 1
            longest = max(longest, streak)
    in_long += streak if streak >= LONG_STREAK else 0
    return {"picks_per_action": picks / len(decided) if decided else None, "longest_failure_streak": longest,
            "streak_actions": in_long, "stuck": int(stuck)}


def grasp_outcomes(rows: list[tuple], greedy_only: bool = False) -> list[int]:
    """1/0 per grasp the cell made, in order (ε-random ones left out with ``greedy_only``)."""
    return [int(s == 1) for _, prim, s, rule, _, outcome in rows
            if prim == "grasp" and outcome in ("executed", "refused") and (not greedy_only or rule != "epsilon")]


def grasp_steps(rows: list[tuple]) -> list[int]:
    """The action index of each grasp ``grasp_outcomes`` counts, in the same order."""
    return [step for step, prim, _, _, _, outcome in rows if prim == "grasp" and outcome in ("executed", "refused")]
