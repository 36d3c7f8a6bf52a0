"""The systemd side: the unit file verifies, and the stdlib notify sender speaks systemd's datagram protocol."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flgd.daemon.notify import Notifier

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "flgd.service"


def _unit_with_real_binary(tmp_path: Path) -> Path:
    """The shipped unit with ExecStart pointing at this checkout's flgd (the real one, so verify can check it)."""
    flgd = Path(sys.executable).parent / "flgd"
    assert flgd.exists(), f"{flgd} missing: is flgd installed in this venv?"
    text = UNIT.read_text()
    assert "ExecStart=/opt/flgd/.venv/bin/flgd run " in text
    out = tmp_path / "flgd.service"
    out.write_text(text.replace("ExecStart=/opt/flgd/.venv/bin/flgd", f"ExecStart={flgd}"))
    return out


def test_unit_file_verifies(tmp_path):
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed")
    unit = _unit_with_real_binary(tmp_path)
    proc = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stderr.strip() == "", proc.stderr


def test_unit_file_settings():
    keys: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        m = re.match(r"^(\w+)=(.*)$", line)
        if m:
            keys.setdefault(m.group(1), []).append(m.group(2))
    one = {k: v[-1] for k, v in keys.items()}
    assert one["Type"] == "notify" and one["Restart"] == "on-failure"
    assert one["User"] == "flgd" and one["StateDirectory"] == "flgd" and one["RuntimeDirectory"] == "flgd"
    assert one["ProtectSystem"] == "strict" and one["NoNewPrivileges"] == "yes"
    assert "PrivateDevices" not in one  # it would hide the camera
    assert "char-usb_device rw" in keys["DeviceAllow"]
    assert "plugdev" in one["SupplementaryGroups"]
    assert int(one["WatchdogSec"]) > 0
    # the stop timeout must leave room for the motion in flight plus checkpoint and flush
    assert int(one["TimeoutStopSec"]) >= 60


def test_sysusers_snippet_parses(tmp_path):
    if shutil.which("systemd-sysusers") is None:
        pytest.skip("systemd-sysusers is not installed")
    proc = subprocess.run(["systemd-sysusers", "--dry-run", str(REPO / "systemd" / "flgd.sysusers")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "Failed" not in proc.stderr and "ignoring" not in proc.stderr, proc.stderr


def _receiver(tmp_path: Path) -> tuple[socket.socket, str]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify.sock")
    sock.bind(path)
    sock.settimeout(5)
    return sock, path


def test_notifier_sends_systemd_datagrams(tmp_path):
    sock, path = _receiver(tmp_path)
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())})
    assert n.enabled and n.watchdog_interval == 2.0
    n.ready("IDLE | cycles 0")
    msg = sock.recv(4096).decode().split("\n")
    assert msg[0] == "READY=1" and "STATUS=IDLE | cycles 0" in msg and f"MAINPID={os.getpid()}" in msg
    n.status("RUNNING")
    n.status("RUNNING")  # unchanged status: not sent again
    n.watchdog()
    n.watchdog()  # rate-limited to a quarter of the interval
    n.stopping("bye")
    got = [sock.recv(4096).decode() for _ in range(3)]
    assert got == ["STATUS=RUNNING", "WATCHDOG=1", "STOPPING=1\nSTATUS=bye"]
    sock.settimeout(0.2)
    with pytest.raises(socket.timeout):
        sock.recv(4096)


def test_notifier_abstract_socket_and_disabled_cases(tmp_path):
    name = f"flgd-test-{os.getpid()}-{time.monotonic_ns()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(5)
    Notifier({"NOTIFY_SOCKET": "@" + name}).send("STATUS=abstract")
    assert sock.recv(100) == b"STATUS=abstract"
    sock.close()
    off = Notifier({})
    assert not off.enabled and off.send("READY=1") is False
    # a watchdog meant for another process is not ours to ping
    assert Notifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}).watchdog_interval is None
