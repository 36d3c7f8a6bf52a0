"""Out of file descriptors: the operator can still stop the cell, and the log says so once.

The daemon test is the issue's: ``flgd run --metrics`` under a limit of 1,024
descriptors (systemd's default), 1,022 half-sent ``GET /metrics`` requests held
open, then ``flgctl stop``.  The server test exhausts a process's descriptors
by other means (a leak), so the control socket's spare descriptor is what
answers.
"""

from __future__ import annotations

import re
import resource
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from flgd.ctl import Client
from tests.fakes.daemon import REPO

pytestmark = pytest.mark.slow  # every test here starts a daemon

DAEMON_LIMIT = 1024
SLOW_SCRAPES = 1022


def _raise_own_limit(needed: int) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < needed:
        if hard != resource.RLIM_INFINITY and hard < needed:
            pytest.skip(f"this process may open only {hard} descriptors; the test needs {needed}")
        resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))


def _half_sent_scrapes(port: int, n: int) -> list[socket.socket]:
    """``n`` connections to the metrics port, each with a request line and no end of headers.

    One after the other, as fast as the server accepts them; once a connect has to wait (the server
    accepts no more), the rest are only started, not waited for, so the test never stalls.
    """
    conns = []
    waiting = False
    for _ in range(n):
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if waiting:
            s.setblocking(False)
            s.connect_ex(("127.0.0.1", port))
        else:
            s.settimeout(3.0)
            try:
                s.connect(("127.0.0.1", port))
            except OSError:
                waiting = True
            s.setblocking(False)
        conns.append(s)
    for s in conns:
        try:
            s.send(b"GET /metrics HTTP/1.1\r\nHost: cell\r\n")
        except OSError:
            pass  # not accepted: it waits in the listen queue, which costs the daemon nothing
    return conns


def test_stop_is_answered_while_a_thousand_slow_scrapes_are_held(daemon_factory):
    _raise_own_limit(SLOW_SCRAPES + 256)
    d = daemon_factory(args=["--metrics", "127.0.0.1:0"], max_descriptors=DAEMON_LIMIT).start().wait_ready()
    d.ok("status")  # set up: the cell and the policy hold their descriptors already
    port = int(re.search(r"metrics: serving http://127\.0\.0\.1:(\d+)/metrics", d.log()).group(1))
    held = _half_sent_scrapes(port, SLOW_SCRAPES)
    try:
        time.sleep(3.0)  # the daemon has had time to take (or refuse) what it would
        started = time.monotonic()
        with Client(d.socket, timeout=30.0) as c:
            reply = c.call("stop")
        answered_after = time.monotonic() - started
        assert reply["ok"], reply
        assert answered_after < 2.0, f"stop answered only after {answered_after:.1f} s"
        assert d.wait_exit(60) == 0
    finally:
        for s in held:
            s.close()
    lines = d.log().splitlines()
    assert len(lines) < 100, f"{len(lines)} log lines:\n" + "\n".join(lines[:40])


_EXHAUSTED_SERVER = textwrap.dedent("""
    import os, sys, time
    from flgd.daemon.server import ControlServer, PeerPolicy
    answered = []
    def handler(request):
        answered.append(request.cmd)
        return {"cmd": request.cmd}
    server = ControlServer(sys.argv[1], handler, lambda: "RUNNING", PeerPolicy(None))
    server.start()
    time.sleep(0.5)  # the accept loop has taken its spare descriptor
    leaked = []
    try:
        while True:
            leaked.append(os.open(os.devnull, os.O_RDONLY))
    except OSError:
        pass
    print("exhausted", len(leaked), flush=True)
    while len(answered) < int(sys.argv[2]):
        time.sleep(0.05)
    print("answered", len(answered), flush=True)
    server.stop()
""")


def test_a_process_out_of_descriptors_still_answers_one_connection_at_a_time(tmp_path: Path):
    sock_path = tmp_path / "flgd.sock"
    calls = 5

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))

    proc = subprocess.Popen([sys.executable, "-c", _EXHAUSTED_SERVER, str(sock_path), str(calls)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=limit)
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert first.startswith("exhausted"), first + proc.stderr.read() if proc.poll() is not None else first
        for i in range(calls):  # one after the other: each gets the spare descriptor back when it closes
            with Client(sock_path, timeout=10.0) as c:
                reply = c.call("stop" if i % 2 else "status")
            assert reply["ok"], reply
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert f"answered {calls}" in out
    log_lines = [line for line in err.splitlines() if line.strip()]
    # one episode, one line: a connection that takes the descriptor the last one gave back is no recovery
    assert len(log_lines) == 1 and "out of file descriptors" in log_lines[0], err[-3000:]
