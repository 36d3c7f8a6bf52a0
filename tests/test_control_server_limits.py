"""The control socket under abuse by authorised clients: slow and many connections, a second daemon on the
same path, numbers too long to read, files the caller may not read."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from flgd.ctl import call
from flgd.daemon.protocol import ProtocolError, Request
from flgd.daemon.server import (MAX_CONNECTIONS, MAX_CONNECTIONS_PER_UID, URGENT_WAITING, ConnectionSlots, ControlServer,
                               PeerPolicy, SocketInUse)

REPO = Path(__file__).resolve().parents[1]


def _read_lines(sock: socket.socket, n: int, timeout: float = 10.0) -> list[dict]:
    """Up to ``n`` reply lines: fewer if the server closed the connection first."""
    sock.settimeout(timeout)
    buf = b""
    while buf.count(b"\n") < n:
        chunk = sock.recv(65536)
        if not chunk:
            break
        buf += chunk
    return [json.loads(line) for line in buf.split(b"\n")[:n] if line]


def _read_line(sock: socket.socket, timeout: float = 10.0) -> dict | None:
    """One reply line, or None if the server closed the connection without one."""
    lines = _read_lines(sock, 1, timeout)
    return lines[0] if lines else None


class _Recorder:
    def __init__(self):
        self.seen: list[str] = []
        self.lock = threading.Lock()

    def __call__(self, req: Request) -> dict:
        with self.lock:
            self.seen.append(req.cmd)
        return {"served": req.cmd}


@pytest.fixture
def served(tmp_path):
    handler = _Recorder()
    srv = ControlServer(tmp_path / "ctl.sock", handler, lambda: "RUNNING", PeerPolicy(None),
                        request_timeout=1.0, urgent_timeout=1.0)
    srv.start()
    srv.handler_log = handler
    yield srv
    srv.stop()


def _connect(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX)
    s.connect(str(path))
    return s


def test_stop_and_pause_get_through_while_every_slot_is_held(served):
    """Connections held open fill every slot; the operator must still be able to pause and stop the cell."""
    holders = [_connect(served.path) for _ in range(MAX_CONNECTIONS + 8)]  # one uid, as an operator's script
    try:
        for cmd in ("pause", "stop"):
            reply = call(served.path, cmd, timeout=30)  # what flgctl does
            assert reply["ok"], reply
            assert reply["result"] == {"served": cmd}
        with _connect(served.path) as other:
            other.sendall(b'{"cmd": "status"}\n')
            reply = _read_line(other)
        # anything else waits for a free slot, and says what still works
        assert reply is not None and reply["error"]["code"] == "busy", reply
        assert "stop and pause are still served" in reply["error"]["message"]
        assert "status" not in served.handler_log.seen
    finally:
        for h in holders:
            h.close()


def test_connections_held_silent_in_the_urgent_lane_make_room_for_a_stop(tmp_path):
    """More silent connections than the lane holds, none of them ever timing out: the oldest make room, so the
    operator's stop is read and answered instead of ``busy`` until one of them gives up."""
    handler = _Recorder()
    srv = ControlServer(tmp_path / "ctl.sock", handler, lambda: "RUNNING", PeerPolicy(None), urgent_timeout=600.0)
    srv.start()
    holders = [_connect(srv.path) for _ in range(MAX_CONNECTIONS_PER_UID + URGENT_WAITING + 10)]
    try:
        reply = call(srv.path, "stop", timeout=5)
        assert reply["ok"] and reply["result"] == {"served": "stop"}, reply
        assert handler.seen == ["stop"]
    finally:
        for h in holders:
            h.close()
        srv.stop()


@pytest.mark.parametrize("cmd", ["stop", "pause"])
def test_stop_and_pause_are_answered_within_two_seconds_while_eight_threads_open_and_hold_connections(tmp_path, cmd):
    """A same-user process whose 8 threads keep opening connections and holding them (32 each at most) takes
    every slot and keeps the urgent lane full; the operator's stop and pause must still be answered at once.
    The 2 s bound is the promise (docs/daemon.md), not a measurement."""
    from benchmarks.control_flood import held_connection_flood

    handler = _Recorder()
    srv = ControlServer(tmp_path / "ctl.sock", handler, lambda: "RUNNING", PeerPolicy(None))  # default timeouts
    srv.start()
    try:
        with held_connection_flood(srv.path, threads=8, hold=32):
            t0 = time.monotonic()
            reply = call(srv.path, cmd, timeout=30)  # what flgctl does, retries included
            seconds = time.monotonic() - t0
        assert reply["ok"], reply
        assert reply["result"] == {"served": cmd}
        assert seconds <= 2.0, f"{cmd} took {seconds:.1f} s under the flood"
    finally:
        srv.stop()


def test_a_request_trickled_a_byte_at_a_time_is_cut_off_at_its_deadline(served):
    with _connect(served.path) as s:
        reply = None
        for ch in b'{"cmd": "status"':  # never the newline
            try:
                s.sendall(bytes([ch]))
            except OSError:
                break
            time.sleep(0.1)
        reply = _read_line(s)
    assert reply is not None, "closed without saying why"
    assert reply["error"]["code"] == "bad_request" and "not complete within 1 s" in reply["error"]["message"]
    assert served.handler_log.seen == []


def test_a_connection_idle_between_whole_requests_is_not_cut_off_by_the_request_deadline(served):
    with _connect(served.path) as s:
        for _ in range(3):
            s.sendall(b'{"cmd": "ping"}\n')
            assert _read_line(s)["ok"]
            time.sleep(0.5)  # 1.5 s in all on one connection: more than the 1 s request deadline
    assert served.handler_log.seen == ["ping"] * 3


def test_connection_slots_cap_each_uid_and_the_total():
    slots = ConnectionSlots(total=3, per_uid=2)
    assert slots.acquire(1) and slots.acquire(1)
    assert not slots.acquire(1)  # uid 1 has its share
    assert slots.acquire(2)
    assert not slots.acquire(3)  # all taken
    slots.release(1)
    assert slots.acquire(3) and slots.held() == 3 and slots.held(1) == 1


def test_a_second_server_on_a_live_socket_leaves_it_alone(served):
    """``flgd run`` of a second daemon on the same socket: refused, and its cleanup must not unlink the
    first one's socket (which would leave the first moving the arm with no way to reach it)."""
    second = ControlServer(served.path, lambda r: {}, lambda: "IDLE", PeerPolicy(None))
    with pytest.raises(SocketInUse):
        second.start()
    second.stop()  # what the second daemon's shutdown does
    assert served.path.exists()
    with _connect(served.path) as s:
        s.sendall(b'{"cmd": "ping"}\n')
        assert _read_line(s)["result"] == {"served": "ping"}


def test_a_socket_file_replaced_under_a_server_is_not_removed_by_it(tmp_path):
    path = tmp_path / "ctl.sock"
    srv = ControlServer(path, lambda r: {}, lambda: "IDLE", PeerPolicy(None))
    srv.start()
    path.unlink()
    other = socket.socket(socket.AF_UNIX)
    other.bind(str(path))  # someone else's socket now has the path
    try:
        srv.stop()
        assert path.exists()
    finally:
        other.close()


def test_the_socket_of_a_killed_daemon_is_replaced(tmp_path):
    """kill -9 leaves the socket file; the kernel drops the path lock, so the next daemon takes over."""
    path = tmp_path / "ctl.sock"
    code = ("import sys, time; from flgd.daemon.server import ControlServer, PeerPolicy; "
            "s = ControlServer(sys.argv[1], lambda r: {}, lambda: 'IDLE', PeerPolicy(None)); s.start(); "
            "print('ready', flush=True); time.sleep(600)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        assert proc.stdout.readline().strip() == "ready"
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()
    assert path.exists()
    second = ControlServer(path, lambda r: {"n": 2}, lambda: "IDLE", PeerPolicy(None))
    second.start()
    try:
        with _connect(path) as s:
            s.sendall(b'{"cmd": "ping"}\n')
            assert _read_line(s)["result"] == {"n": 2}
    finally:
        second.stop()
    assert not path.exists()


def test_an_integer_too_long_to_read_gets_an_error_reply_and_the_connection_goes_on(served):
    with _connect(served.path) as s:
        s.sendall(b'{"cmd": "status", "id": ' + b"9" * 5000 + b"}\n" + b'{"cmd": "ping"}\n')
        replies = _read_lines(s, 2)
    assert replies, "connection dropped without a reply"
    first, second = replies
    assert first["error"]["code"] == "bad_request" and "number too long" in first["error"]["message"]
    assert second["ok"]


# --------------------------------------------------------------------------- files the caller may not read

def _as_uid(uid: int, gid: int, path: str, request: dict) -> dict:
    """Fork a child that becomes ``uid``/``gid`` and sends one request; return its reply."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(gid)
            os.setuid(uid)
            with socket.socket(socket.AF_UNIX) as s:
                s.connect(path)
                s.sendall(json.dumps(request).encode() + b"\n")
                data = b""
                s.settimeout(20)
                while b"\n" not in data:
                    chunk = s.recv(65536)
                    if not chunk:
                        break
                    data += chunk
            os.write(w, data or b'{"closed": true}\n')
        except BaseException as exc:
            os.write(w, json.dumps({"child_error": repr(exc)}).encode() + b"\n")
        finally:
            os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        out = f.read()
    os.waitpid(pid, 0)
    return json.loads(out.splitlines()[0])


def test_policy_load_of_a_file_the_member_may_not_read_names_the_problem_not_the_content():
    """A control-group member asks the (root) daemon to load a root-only file: the reply must not hold its
    size or first bytes; a file the member may read is loaded (and refused for its content) as before."""
    if os.getuid() != 0:
        pytest.skip("needs root to switch to another uid")
    from flgd.learning.policy_file import PolicyFileError, load_policy

    def handler(req: Request) -> dict:
        try:
            load_policy(req.args["path"])
        except PolicyFileError as exc:
            raise ProtocolError("failed", str(exc)) from None
        return {"loaded": True}

    nobody, nogroup = 65534, 65534
    with tempfile.TemporaryDirectory(prefix="flgd-access-", dir="/tmp") as d:
        os.chmod(d, 0o755)
        secret = Path(d) / "secret"
        secret.write_bytes(b"root:$6$saltsalt$" + b"x" * 1000)
        os.chmod(secret, 0o600)
        public = Path(d) / "public"
        public.write_bytes(b"not a policy, but anyone may read it")
        os.chmod(public, 0o644)
        hidden_dir = Path(d) / "private"
        hidden_dir.mkdir(mode=0o700)
        (hidden_dir / "p.safetensors").write_bytes(b"x" * 64)
        os.chmod(hidden_dir / "p.safetensors", 0o644)
        srv = ControlServer(Path(d) / "ctl.sock", handler, lambda: "IDLE", PeerPolicy("nogroup"))
        srv.start()
        try:
            for target in (secret, hidden_dir / "p.safetensors"):
                reply = _as_uid(nobody, nogroup, str(srv.path), {"cmd": "policy_load", "args": {"path": str(target)}})
                err = reply.get("error", {})
                assert err.get("code") == "forbidden", reply
                assert "permission denied" in err["message"] and str(target) in err["message"]
                assert "1017" not in err["message"] and "header length" not in err["message"]  # size, bytes
            reply = _as_uid(nobody, nogroup, str(srv.path), {"cmd": "policy_load", "args": {"path": str(public)}})
            assert reply["error"]["code"] == "failed" and "header length" in reply["error"]["message"], reply
        finally:
            srv.stop()
