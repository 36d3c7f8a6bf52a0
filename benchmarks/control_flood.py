"""``flgd bench control-flood``: how long ``flgctl stop`` takes while another client floods the control socket.

The flood is a same-user process whose threads open connections to the socket as fast as they can and hold
each one open without sending anything (each thread keeps its ``--hold`` newest and closes older ones, so the
flood's descriptors stay bounded).  For each mode (``idle``: the daemon connected and not acting;
``running``: cycling on the simulated cell) the benchmark starts ``flgd run`` on the small simulated config,
starts the flood, lets it fill every connection slot, times the answer to a ``pause`` sent by flgctl's client
library from this process (what the daemon controls: in IDLE the answer is a refusal, in RUNNING the pause),
then times the real ``flgctl stop`` command line from launch to exit (that adds a Python start-up, which a loaded
machine stretches).  Each trial is a fresh daemon (a stop ends it); reported per mode: every trial and the median.

``held_connection_flood`` is the flood alone, for tests.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Iterator

import yaml

REPO = Path(__file__).resolve().parents[1]


def _flood_forever(path: str, threads: int, hold: int) -> None:
    """The flood process: ``threads`` threads open and hold connections until killed."""
    opened = [0]

    def one() -> None:
        held: list[socket.socket] = []
        while True:
            s = socket.socket(socket.AF_UNIX)
            s.settimeout(1.0)
            try:
                s.connect(path)
            except OSError:
                s.close()
                continue
            held.append(s)
            opened[0] += 1
            if len(held) > hold:
                held.pop(0).close()

    for _ in range(threads):
        threading.Thread(target=one, daemon=True).start()
    while opened[0] < threads * hold:
        time.sleep(0.01)
    print("flooding", flush=True)
    while True:
        time.sleep(1.0)
        print(f"opened {opened[0]}", flush=True)


@contextlib.contextmanager
def held_connection_flood(path: str | os.PathLike, threads: int = 8, hold: int = 32) -> Iterator[None]:
    """A same-user process opening and holding connections to ``path`` from ``threads`` threads (at most
    ``hold`` open per thread), from when its first ``threads * hold`` are open until the block ends."""
    proc = subprocess.Popen([sys.executable, "-m", "benchmarks.control_flood", "--flood-only", str(path),
                             "--threads", str(threads), "--hold", str(hold)],
                            stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        line = proc.stdout.readline().strip()  # type: ignore[union-attr]
        if line != "flooding":
            raise RuntimeError(f"the flood did not start (said {line!r}, exit {proc.poll()})")
        yield
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()  # type: ignore[union-attr]


def _config(directory: Path) -> Path:
    """The shipped simulated cell's config with its state in ``directory`` (its relative paths made absolute)."""
    from flgd.config import load_config

    shipped = load_config(REPO / "cell_config" / "sim.yaml")
    data = yaml.safe_load((REPO / "cell_config" / "sim.yaml").read_text())
    data["state_dir"] = str(directory / "state")
    data["policy"] = str(shipped.policy)
    data["learning"]["init_trunk"] = str(shipped.learning.init_trunk)
    data["finetune"]["prior_sample"] = str(shipped.finetune.prior_sample)
    path = directory / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _cycles(sock: Path) -> int:
    from flgd.ctl import Client

    with Client(sock, timeout=30) as client:
        return int(client.call("status")["result"].get("cycles") or 0)


def _ctl(sock: Path, *argv: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flgd.ctl", "--socket", str(sock), *argv], capture_output=True,
                          text=True, timeout=timeout, cwd=REPO)


def trial(mode: str, threads: int, hold: int) -> dict:
    """One fresh daemon in ``mode``, flooded; seconds ``flgctl stop`` took and what it answered."""
    with tempfile.TemporaryDirectory(prefix="flgd-flood-") as d:
        directory = Path(d)
        sock = directory / "flgd.sock"
        args = ["--autostart"] if mode == "running" else []
        with open(directory / "daemon.log", "wb") as log:
            daemon = subprocess.Popen([sys.executable, "-m", "flgd.cli", "run", "--config", str(_config(directory)),
                                       "--socket", str(sock), "--no-status-line", *args],
                                      stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
            try:
                deadline = time.monotonic() + 300
                while _ctl(sock, "ping", timeout=30).returncode != 0:
                    if daemon.poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError("the daemon did not start:\n" + (directory / "daemon.log").read_text())
                    time.sleep(0.5)
                if mode == "running":
                    while _cycles(sock) < 1:
                        if time.monotonic() > deadline:
                            raise RuntimeError("no cycle logged after 300 s")
                        time.sleep(0.5)
                with held_connection_flood(sock, threads, hold):
                    time.sleep(1.0)  # the flood holds every slot and fills the urgent lane
                    from flgd.ctl import call

                    t0 = time.monotonic()
                    pause = call(sock, "pause", timeout=60)
                    answer_seconds = time.monotonic() - t0
                    t0 = time.monotonic()
                    stop = _ctl(sock, "stop")
                    seconds = time.monotonic() - t0
                code = daemon.wait(120)
            finally:
                if daemon.poll() is None:
                    daemon.send_signal(signal.SIGKILL)
                    daemon.wait()
    return {"mode": mode, "stop_seconds": round(seconds, 3), "pause_answer_seconds": round(answer_seconds, 3),
            "pause_answer": "ok" if pause.get("ok") else pause.get("error", {}).get("code"),
            "load_average_1min": round(os.getloadavg()[0], 2),
            "flgctl_exit": stop.returncode,
            "flgctl_output": (stop.stdout + stop.stderr).strip()[:200], "daemon_exit": code}


def _commit() -> str:
    proc = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO)
    return proc.stdout.strip()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="flgd bench control-flood", description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=5, help="fresh daemons per mode (default 5)")
    p.add_argument("--threads", type=int, default=8, help="flooding threads (default 8)")
    p.add_argument("--hold", type=int, default=32, help="connections each thread holds open (default 32)")
    p.add_argument("--modes", default="idle,running", help="comma-separated: idle, running")
    p.add_argument("--out", help="write the results as JSON here")
    p.add_argument("--flood-only", metavar="SOCKET", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.flood_only:
        _flood_forever(args.flood_only, args.threads, args.hold)
        return 0
    results: dict = {"benchmark": "control-flood", "date": time.strftime("%Y-%m-%d"), "commit": _commit(),
                     "machine": f"{platform.machine()}, {os.cpu_count()} cores", "threads": args.threads,
                     "hold_per_thread": args.hold, "modes": {}}
    for mode in args.modes.split(","):
        trials = [trial(mode, args.threads, args.hold) for _ in range(args.trials)]
        times = [t["stop_seconds"] for t in trials]
        answers = [t["pause_answer_seconds"] for t in trials]
        results["modes"][mode] = {"median_stop_seconds": round(statistics.median(times), 3),
                                  "max_stop_seconds": max(times),
                                  "median_pause_answer_seconds": round(statistics.median(answers), 3),
                                  "max_pause_answer_seconds": max(answers), "trials": trials}
        print(f"{mode}: flgctl stop {statistics.median(times):.2f} s median of {len(times)} (max {max(times):.2f} s; "
              f"exits {[t['flgctl_exit'] for t in trials]}); pause answered in {statistics.median(answers):.3f} s "
              f"median (max {max(answers):.3f} s; {[t['pause_answer'] for t in trials]})", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
