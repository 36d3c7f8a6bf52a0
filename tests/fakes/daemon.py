"""Shared helpers of the daemon tests (this module holds no tests).

``DaemonProcess`` runs the real ``flgd run`` as a subprocess against sim_cell in a
temporary state directory, with a small, fast config, and talks to it over
its real control socket.  ``tmpfs`` mounts a small or read-only filesystem for
the storage-fault tests (they need root, which the test machine has).
"""

from __future__ import annotations

import contextlib
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
import yaml

from flgd.config import load_config
from flgd.ctl import Client, DaemonUnreachable
from sim_cell.emulator.tcp_service import read_line  # noqa: F401 (the tests' one line reader)

REPO = Path(__file__).resolve().parents[2]


@contextlib.contextmanager
def tmpfs(path: Path, size: str = "4m") -> Iterator[Path]:
    """A fresh tmpfs of ``size`` at ``path`` (skips the test if mounting is not permitted)."""
    path.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(path)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {proc.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def write_config(directory: Path, state_dir: Path, **sections: Any) -> Path:
    """A sim config for tests: few objects, tiny learning batches, frequent checkpoints."""
    data = yaml.safe_load((REPO / "cell_config" / "sim.yaml").read_text())
    data["state_dir"] = str(state_dir)
    data["policy"] = ""
    # sim.yaml's relative paths are relative to cell_config/, not to the copy's directory
    shipped = load_config(REPO / "cell_config" / "sim.yaml")
    data["learning"]["init_trunk"] = str(shipped.learning.init_trunk)
    data["finetune"]["prior_sample"] = str(shipped.finetune.prior_sample)
    data.setdefault("sim", {}).update({"objects": 3, "seed": 1})
    data.setdefault("learning", {}).update({"batch_size": 1, "checkpoint_every": 2, "threads": 1,
                                            "device": "cpu", "replay_capacity": 1000})
    for name, values in sections.items():
        if isinstance(values, dict):
            data.setdefault(name, {}).update(values)
        else:
            data[name] = values
    path = directory / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


class DaemonProcess:
    """``flgd run`` as a real subprocess, with its log in a file."""

    def __init__(self, tmp_path: Path, config: Path | None = None, args: list[str] | None = None,
                 env: dict[str, str] | None = None, state_dir: Path | None = None,
                 max_descriptors: int | None = None, **sections: Any):
        self.dir = tmp_path
        self.state_dir = state_dir or tmp_path / "state"
        self.config = config or write_config(tmp_path, self.state_dir, **sections)
        self.socket = tmp_path / "run" / "flgd.sock"
        self.args = list(args or [])
        self.env = dict(os.environ, **(env or {}))
        self.env.pop("NOTIFY_SOCKET", None) if "NOTIFY_SOCKET" not in (env or {}) else None
        self.log_path = tmp_path / f"daemon-{time.monotonic_ns()}.log"
        self.max_descriptors = max_descriptors  # RLIMIT_NOFILE, soft and hard, of the daemon process
        self.proc: subprocess.Popen | None = None

    def start(self) -> "DaemonProcess":
        self.log_file = open(self.log_path, "wb")
        cmd = [sys.executable, "-m", "flgd.cli", "run", "--config", str(self.config), "--socket",
               str(self.socket), "--no-status-line", *self.args]
        limit = self.max_descriptors
        preexec = None if limit is None else (lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (limit, limit)))
        self.proc = subprocess.Popen(cmd, stdout=self.log_file, stderr=subprocess.STDOUT, env=self.env, cwd=REPO,
                                     preexec_fn=preexec)
        return self

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_ready(self, timeout: float = 180.0) -> "DaemonProcess":
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError(f"daemon exited with {self.proc.returncode}:\n{self.log()}")
            try:
                if self.call("ping")["ok"]:
                    return self
            except DaemonUnreachable:
                pass
            time.sleep(0.2)
        raise AssertionError(f"daemon not ready after {timeout} s:\n{self.log()}")

    def call(self, cmd: str, **args: Any) -> dict:
        with Client(self.socket, timeout=150.0) as c:
            return c.call(cmd, **args)

    def ok(self, cmd: str, **args: Any) -> dict:
        reply = self.call(cmd, **args)
        assert reply["ok"], (cmd, reply, self.log()[-3000:])
        return reply["result"]

    def ctl(self, *argv: str) -> subprocess.CompletedProcess:
        """The real flgctl command line, as a separate process."""
        return subprocess.run([sys.executable, "-m", "flgd.ctl", "--socket", str(self.socket), *argv],
                              capture_output=True, text=True, timeout=180, cwd=REPO)

    def wait_for(self, predicate, what: str, timeout: float = 240.0, poll: float = 0.3) -> dict:
        """Poll status until ``predicate(status)``; returns that status."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError(f"daemon exited with {self.proc.returncode} waiting for {what}:\n{self.log()}")
            st = self.ok("status")
            if predicate(st):
                return st
            time.sleep(poll)
        raise AssertionError(f"timed out waiting for {what}; last status {st}\n{self.log()[-4000:]}")

    def wait_exit(self, timeout: float = 120.0) -> int:
        try:
            return self.proc.wait(timeout)
        finally:
            self.log_file.close()

    def kill9(self) -> None:
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait()
        self.log_file.close()

    def cleanup(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self.log_file.closed:
            self.log_file.close()
