"""flgctl's output path: a reader that goes away (``| head -1``) or a full disk ends it quietly, like a Unix
tool, never with a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from flgd.daemon.server import ControlServer, PeerPolicy

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def daemon_socket(tmp_path):
    srv = ControlServer(tmp_path / "ctl.sock", lambda r: {"pong": True, "pid": 1, "note": "x" * 200},
                        lambda: "IDLE", PeerPolicy(None))
    srv.start()
    yield srv.path
    srv.stop()


def _flgctl(socket_path: Path, *argv: str, stdout) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flgd.ctl", "--socket", str(socket_path), *argv], stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=60, cwd=REPO)


@pytest.mark.parametrize("argv", [("ping",), ("--json", "ping")])
def test_a_closed_pipe_ends_flgctl_quietly(daemon_socket, argv):
    r, w = os.pipe()
    os.close(r)  # the reader is gone before flgctl writes a byte: its write must meet EPIPE
    try:
        p = _flgctl(daemon_socket, *argv, stdout=w)
    finally:
        os.close(w)
    assert p.stderr == "", p.stderr
    assert p.returncode == 1


def test_a_closed_pipe_is_quiet_when_the_daemon_is_not_running_either(tmp_path):
    r, w = os.pipe()
    os.close(r)
    try:
        p = _flgctl(tmp_path / "none.sock", "--json", "status", stdout=w)
    finally:
        os.close(w)
    assert p.stderr == "" and p.returncode == 1


@pytest.mark.parametrize("argv", [("ping",), ("--json", "ping")])
def test_a_full_disk_is_one_line_on_stderr(daemon_socket, argv):
    with open("/dev/full", "w") as full:
        p = _flgctl(daemon_socket, *argv, stdout=full)
    assert p.returncode == 1
    assert p.stderr == "flgctl: cannot write the output: No space left on device\n", p.stderr


def test_output_still_arrives_whole(daemon_socket):
    p = _flgctl(daemon_socket, "ping", stdout=subprocess.PIPE)
    assert p.returncode == 0 and p.stdout == "flgd answers (pid 1, IDLE)\n"
