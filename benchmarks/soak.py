"""``flgd bench soak``: does a daemon that runs for weeks stay the same size?

The real ``flgd run`` (a subprocess, sim cell, the shipped config: background learner, gate, metrics page on the
loopback) cycles until its store holds ``--cycles`` cycles.  Every ``--sample-every`` cycles the bench reads, from
/proc and the state directory: resident memory (RSS, and its peak), open descriptors, threads, the store's
database and write-ahead log, the whole state directory; and it scrapes the metrics page once (the page's server
must not grow either).

Resumable: the samples go to ``ROOT/samples.jsonl`` as they are taken; a bench started again on the same root
starts the daemon again on the same state directory (which resumes its learning) and goes on from the cycles the
store already holds.  Samples after a restart carry a new ``run`` number (a restart resets RSS).

The summary (``--out``, also ``ROOT/summary.json``): one row per 1,000 cycles, and after ``--warmup`` cycles the
growth per 1,000 cycles of RSS, descriptors, threads and store bytes (least squares over the samples of the last
run), against which the store's budget (``storage.max_bytes``) is the only growth allowed.

    flgd bench soak --root runs/soak --cycles 5000 --out benchmarks/results/soak-DATE.json
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
import urllib.request
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]


def _proc_status(pid: int) -> dict[str, int]:
    """VmRSS, VmHWM (bytes) and Threads of a process, from /proc."""
    out: dict[str, int] = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) * 1024
        elif key == "Threads":
            out[key] = int(value)
    return out


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def _tree_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _write_config(root: Path, source: Path) -> Path:
    """The shipped config with its state directory under ROOT and the metrics page on a free loopback port."""
    data = yaml.safe_load(source.read_text())
    data["state_dir"] = str(root / "state")
    data["metrics"] = "127.0.0.1:0"
    # paths in the config are relative to its own directory, not to the copy's
    if data.get("policy"):
        data["policy"] = str((source.parent / data["policy"]).resolve())
    for section, key in (("learning", "init_trunk"), ("finetune", "prior_sample"), ("sim", "scene")):
        value = (data.get(section) or {}).get(key)
        if value:
            data[section][key] = str((source.parent / value).resolve())
    path = root / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


class SoakDaemon:
    """``flgd run`` as a subprocess, with its log in ROOT; status over its control socket."""

    def __init__(self, root: Path, config: Path):
        self.root = root
        self.config = config
        self.socket = root / "run" / "flgd.sock"
        self.proc: subprocess.Popen | None = None
        self.log_path = root / "daemon.log"
        self.metrics_port: int | None = None

    def start(self) -> None:
        self.log_file = open(self.log_path, "ab")
        self._log_start = self.log_path.stat().st_size
        cmd = [sys.executable, "-m", "flgd.cli", "run", "--config", str(self.config), "--socket", str(self.socket),
               "--autostart", "--no-status-line"]
        self.proc = subprocess.Popen(cmd, stdout=self.log_file, stderr=subprocess.STDOUT, cwd=REPO)

    def status(self) -> dict | None:
        from flgd.ctl import Client, DaemonUnreachable

        try:
            with Client(self.socket, timeout=60.0) as c:
                reply = c.call("status")
        except (DaemonUnreachable, OSError):
            return None
        return reply.get("result") if reply.get("ok") else None

    def port(self) -> int | None:
        if self.metrics_port is None:
            import re

            with open(self.log_path, "rb") as f:
                f.seek(self._log_start)
                found = re.search(rb"metrics: serving http://127\.0\.0\.1:(\d+)/metrics", f.read())
            self.metrics_port = int(found.group(1)) if found else None
        return self.metrics_port

    def scrape(self) -> tuple[int, float]:
        """Bytes of one scrape of the metrics page and the seconds it took."""
        started = time.monotonic()
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port()}/metrics", timeout=30) as r:
            body = r.read()
        return len(body), time.monotonic() - started

    def stop(self) -> int:
        from flgd.ctl import Client, DaemonUnreachable

        assert self.proc is not None
        try:
            with Client(self.socket, timeout=60.0) as c:
                c.call("stop")
        except (DaemonUnreachable, OSError):
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(180)
        finally:
            self.log_file.close()


def _sample(daemon: SoakDaemon, status: dict, run: int, started: float) -> dict[str, Any]:
    assert daemon.proc is not None
    pid = daemon.proc.pid
    state = daemon.root / "state"
    proc = _proc_status(pid)
    scrape_bytes, scrape_seconds = daemon.scrape()
    return {
        "run": run, "cycles": int(status["cycles"]), "wall_s": round(time.monotonic() - started, 1),
        "rss_bytes": proc["VmRSS"], "rss_peak_bytes": proc["VmHWM"], "threads": proc["Threads"],
        "descriptors": len(os.listdir(f"/proc/{pid}/fd")),
        "store_bytes": _size(state / "flgd.sqlite"), "wal_bytes": _size(state / "flgd.sqlite-wal"),
        "state_dir_bytes": _tree_size(state), "replay_transitions": status.get("replay_size"),
        "learner_updates": status.get("learner_updates"), "state": status.get("state"),
        "scrape_bytes": scrape_bytes, "scrape_seconds": round(scrape_seconds, 4),
    }


def _slope(samples: list[dict], key: str) -> float | None:
    """Least-squares growth of ``key`` per 1,000 cycles."""
    if len(samples) < 3:
        return None
    xs = [s["cycles"] / 1000.0 for s in samples]
    ys = [float(s[key]) for s in samples]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    return None if sxx == 0 else sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx


def summarise(samples: list[dict], warmup: int) -> dict[str, Any]:
    last_run = max(s["run"] for s in samples)
    steady = [s for s in samples if s["run"] == last_run and s["cycles"] >= warmup]
    per_thousand = []
    for s in samples:
        if s["cycles"] // 1000 > (per_thousand[-1]["cycles"] // 1000 if per_thousand else -1):
            per_thousand.append(s)
    keys = ("rss_bytes", "descriptors", "threads", "store_bytes", "wal_bytes", "state_dir_bytes")
    return {
        "samples": len(samples), "runs": last_run + 1, "cycles": samples[-1]["cycles"], "warmup_cycles": warmup,
        "per_1000_cycles": per_thousand,
        "after_warmup": {
            "samples": len(steady),
            "growth_per_1000_cycles": {k: _slope(steady, k) for k in keys},
            "min": {k: min((s[k] for s in steady), default=None) for k in keys},
            "max": {k: max((s[k] for s in steady), default=None) for k in keys},
        },
        "rss_steady_median_bytes": sorted(s["rss_bytes"] for s in steady)[len(steady) // 2] if steady else None,
        "scrape_seconds_max": max(s["scrape_seconds"] for s in samples),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="flgd bench soak", description=__doc__.split("\n\n")[0])
    p.add_argument("--root", type=Path, required=True, help="run directory (resumable)")
    p.add_argument("--config", type=Path, default=REPO / "cell_config" / "sim.yaml")
    p.add_argument("--cycles", type=int, default=5000)
    p.add_argument("--sample-every", type=int, default=250)
    p.add_argument("--warmup", type=int, default=1000, help="cycles before growth is judged")
    p.add_argument("--out", type=Path, help="summary JSON (also written to ROOT/summary.json)")
    args = p.parse_args(argv)

    args.root = args.root.resolve()  # the config names its state directory absolutely
    args.root.mkdir(parents=True, exist_ok=True)
    samples_path = args.root / "samples.jsonl"
    samples = [json.loads(line) for line in samples_path.read_text().splitlines()] if samples_path.exists() else []
    run = samples[-1]["run"] + 1 if samples else 0
    config = args.root / "cell.yaml" if (args.root / "cell.yaml").exists() else _write_config(args.root, args.config)
    if samples and samples[-1]["cycles"] >= args.cycles:
        print(f"{args.root}: {samples[-1]['cycles']} cycles already; summarising")
    else:
        daemon = SoakDaemon(args.root, config)
        daemon.start()
        started = time.monotonic()
        next_mark = (samples[-1]["cycles"] // args.sample_every + 1) * args.sample_every if samples else 0
        try:
            while True:
                assert daemon.proc is not None
                if daemon.proc.poll() is not None:
                    raise SystemExit(f"flgd run exited with {daemon.proc.returncode}; see {daemon.log_path}")
                status = daemon.status()
                if status is not None and status.get("state") in ("FAULT", "PAUSED"):
                    print(f"daemon {status['state']}: {status.get('cause')}; resuming", flush=True)
                    from flgd.ctl import Client

                    with Client(daemon.socket, timeout=60.0) as c:
                        c.call("reset" if status["state"] == "FAULT" else "start")
                        if status["state"] == "FAULT":
                            c.call("start")
                if status is not None and daemon.port() and int(status["cycles"]) >= next_mark:
                    sample = _sample(daemon, status, run, started)
                    samples.append(sample)
                    with open(samples_path, "a") as f:
                        f.write(json.dumps(sample) + "\n")
                    print(f"{sample['cycles']:6d} cycles  RSS {sample['rss_bytes'] / 2**20:7.1f} MiB  "
                          f"fds {sample['descriptors']:4d}  threads {sample['threads']:3d}  "
                          f"store {sample['store_bytes'] / 2**20:7.1f} MiB  wal {sample['wal_bytes'] / 2**20:6.1f} "
                          f"MiB", flush=True)
                    next_mark = (sample["cycles"] // args.sample_every + 1) * args.sample_every
                    if sample["cycles"] >= args.cycles:
                        break
                time.sleep(2.0)
        finally:
            if daemon.proc is not None and daemon.proc.poll() is None:
                daemon.stop()
    summary = summarise(samples, args.warmup)
    summary.update({"command": "flgd bench soak " + " ".join(argv if argv is not None else sys.argv[1:]),
                    "config": str(args.config), "machine": f"{platform.node()} {os.cpu_count()} cores",
                    "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                             cwd=REPO).stdout.strip(),
                    "date": time.strftime("%Y-%m-%d")})
    text = json.dumps(summary, indent=2) + "\n"
    (args.root / "summary.json").write_text(text)
    if args.out:
        args.out.write_text(text)
    print(json.dumps(summary["after_warmup"], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
