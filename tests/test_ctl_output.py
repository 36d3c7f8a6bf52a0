"""flgctl's output path: a reader that goes away (``| head -1``) or a full disk ends it quietly, like a Unix
tool, never with a traceback."""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import pytest

from flgd import ctl
from flgd.daemon.server import ControlServer, PeerPolicy
from tests.fakes.daemon import read_line

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


# --------------------------------------------------------------------------- flgctl: bad input is a clear error

@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf", "soon"])
def test_bad_timeout_is_a_usage_error(value, capsys):
    assert ctl.main(["--socket", "/nonexistent/flgd.sock", "--timeout", value, "status"]) == ctl.EXIT_USAGE
    assert "--timeout" in capsys.readouterr().err


class _OneReplyDaemon:
    """A control socket that answers every request line with ``reply`` (bytes, newline added)."""

    def __init__(self, reply: bytes):
        self.dir = Path(tempfile.mkdtemp(prefix="flgd-ctl-", dir="/tmp"))
        self.path = self.dir / "s.sock"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.bind(str(self.path))
        self.sock.listen(1)
        self.reply = reply
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.sock.accept()
        with conn:
            if b"\n" in read_line(conn):
                conn.sendall(self.reply + b"\n")

    def close(self) -> None:
        self.sock.close()
        self.thread.join(5)
        shutil.rmtree(self.dir, ignore_errors=True)


def test_json_output_reports_a_snapshot_that_cannot_be_written(tmp_path, capsys):
    png = base64.b64encode(b"\x89PNG fake").decode()
    daemon = _OneReplyDaemon(json.dumps({"ok": True, "state": "IDLE",
                                         "result": {"png_base64": png, "source": "last", "action": None}}).encode())
    try:
        code = ctl.main(["--socket", str(daemon.path), "--json", "snapshot", str(tmp_path / "no-dir" / "s.png")])
    finally:
        daemon.close()
    out = capsys.readouterr()
    assert code == ctl.EXIT_FAILED
    reply = json.loads(out.out)  # a script reading stdout must not see an empty output (or a success)
    assert reply["ok"] is False and "no-dir" in reply["error"]["message"]


def test_a_reply_that_is_not_utf8_is_exit_1_not_a_traceback(capsys):
    daemon = _OneReplyDaemon(b'{"ok": true, "result": "\xff"}')  # JSON-looking, not UTF-8
    try:
        code = ctl.main(["--socket", str(daemon.path), "status"])
    finally:
        daemon.close()
    assert code == ctl.EXIT_FAILED and "unreadable reply" in capsys.readouterr().err


# --------------------------------------------------------------------------- flgctl stop says what is known

def test_flgctl_stop_reports_a_request_not_a_finished_flush(capsys):
    daemon = _OneReplyDaemon(b'{"ok": true, "state": "STOPPING", "result": {"stopping": true}}')
    try:
        assert ctl.main(["--socket", str(daemon.path), "stop"]) == 0
    finally:
        daemon.close()
    out = capsys.readouterr().out
    assert out.startswith("stop requested") and "flushed" not in out and "halted" not in out


def test_flgctl_policy_save_permission_error_names_the_group(tmp_path, capsys, monkeypatch):
    saved = "/var/lib/flgd/policies/p.safetensors"
    daemon = _OneReplyDaemon(json.dumps({"ok": True, "state": "IDLE",
                                         "result": {"saved": saved, "learner_updates": 1}}).encode())

    def denied(src, dst):
        raise PermissionError(13, "Permission denied", src)

    monkeypatch.setattr(ctl.shutil, "copyfile", denied)
    try:
        assert ctl.main(["--socket", str(daemon.path), "policy", "save", str(tmp_path / "x.safetensors")]) == 1
    finally:
        daemon.close()
    err = capsys.readouterr().err
    assert saved in err and "Permission denied" in err and "group flgd" in err
