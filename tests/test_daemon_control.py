"""The control surface of a real daemon (sim_cell, never started): fuzzing, peers, policy, backend, snapshot."""

from __future__ import annotations

import contextlib
import io
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flgd.ctl import main as ctl_main
from flgd.daemon.protocol import MAX_REQUEST_BYTES

from tests.fakes.daemon import REPO, DaemonProcess

pytestmark = pytest.mark.slow  # every test here starts a daemon


@pytest.fixture(scope="module")
def idle_daemon(tmp_path_factory):
    """One daemon for the whole module, IDLE throughout; its socket is reachable by other uids."""
    base = Path(tempfile.mkdtemp(prefix="flgd-ctl-", dir="/tmp"))
    os.chmod(base, 0o755)
    d = DaemonProcess(base).start().wait_ready()
    yield d
    d.cleanup()
    subprocess.run(["rm", "-rf", str(base)])


# --------------------------------------------------------------------------- fuzzing

_NAMES = ["start", "stop", "pause", "reset", "status", "stats", "ping", "policy_load", "policy_save", "backend",
          "snapshot", "dance", "", "STATUS", "start ", "\u00e9t\u00e9", "__class__"]
_SAFE_WITH_ANY_ARGS = {"pause", "status", "stats", "ping", "dance", "", "STATUS", "start ", "\u00e9t\u00e9",
                       "__class__"}
_json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
                            lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                                       max_size=4), max_leaves=10)


@st.composite
def _json_request(draw) -> bytes:
    """Requests that are JSON, some well-formed; never one that would legitimately move the arm."""
    cmd = draw(st.sampled_from(_NAMES) | st.integers() | st.none() | st.lists(st.text(max_size=3), max_size=2))
    obj: dict = {}
    if draw(st.booleans()):
        obj["cmd"] = cmd
    if isinstance(cmd, str) and cmd not in _SAFE_WITH_ANY_ARGS:
        # a real command: only with args it rejects (unknown key), so the request is invalid
        obj["args"] = {"bogus-" + draw(st.text(max_size=5)): draw(_json_values)}
    elif draw(st.booleans()):
        obj["args"] = draw(_json_values)
    if draw(st.booleans()):
        obj["id"] = draw(_json_values)
    if draw(st.booleans()):
        obj[draw(st.text(max_size=6))] = draw(_json_values)
    top = draw(st.sampled_from(["object", "object", "list", "scalar"]))
    if top == "list":
        return json.dumps([obj]).encode()
    if top == "scalar":
        return json.dumps(draw(_json_values)).encode()
    return json.dumps(obj, ensure_ascii=draw(st.booleans())).encode()


_payloads = st.one_of(
    st.binary(max_size=300),
    _json_request(),
    st.integers(MAX_REQUEST_BYTES - 2, 2 * MAX_REQUEST_BYTES).map(lambda n: b"{" + b"x" * n),
    st.tuples(_json_request(), _json_request()).map(lambda t: t[0] + b"\n" + t[1]),
    st.text(max_size=200).map(lambda s: s.encode("utf-8", "surrogatepass")),
)


def _exchange(path: Path, payload: bytes) -> list[dict]:
    data = payload + b"\n"
    expected = data.count(b"\n")
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(30)
        s.connect(str(path))
        s.sendall(data)
        buf = b""
        while buf.count(b"\n") < expected:
            chunk = s.recv(1 << 16)
            assert chunk, f"connection closed after {len(buf.splitlines())} of {expected} replies"
            buf += chunk
    return [json.loads(line) for line in buf.splitlines()]


def test_fuzzed_messages_all_answered_and_nothing_moves(idle_daemon):
    counter = {"messages": 0}

    @settings(max_examples=1000, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example])
    @given(_payloads)
    def one(payload: bytes) -> None:
        replies = _exchange(idle_daemon.socket, payload)
        counter["messages"] += 1
        for r in replies:
            assert set(r) >= {"ok", "state"}
            assert r["state"] == "IDLE"
            if not r["ok"]:
                assert r["error"]["code"] in ("bad_request", "too_long", "unknown_command", "wrong_state")
                assert r["error"]["message"]

    one()
    assert counter["messages"] >= 1000
    assert idle_daemon.proc.poll() is None
    st_ = idle_daemon.ok("status")
    assert st_["state"] == "IDLE" and st_["cycles"] == 0 and st_["step"] == 0  # the arm never moved


# --------------------------------------------------------------------------- wrong state, peers, ctl

def test_wrong_state_commands_are_refused(idle_daemon):
    for cmd in ("pause",):
        r = idle_daemon.call(cmd)
        assert not r["ok"] and r["error"]["code"] == "wrong_state" and "IDLE" in r["error"]["message"]
    p = idle_daemon.ctl("pause")
    assert p.returncode == 1 and "wrong_state" in p.stderr


def test_other_uid_is_refused(idle_daemon):
    if os.getuid() != 0:
        pytest.skip("needs root to switch to another uid")
    os.chmod(idle_daemon.socket.parent, 0o755)
    os.chmod(idle_daemon.socket, 0o666)  # file mode lets it connect; the daemon's peer check must refuse
    # The interpreter lives under /root (unreadable for uid 65534), so the child runs flgctl's main()
    # in the already-loaded interpreter after dropping its uid, instead of exec'ing it; what it imports
    # lazily is imported here first.
    import grp  # noqa: F401  (argparse/shutil import it lazily)

    from flgd.ctl import _parser
    _parser().parse_args(["--socket", "x", "--json", "start"])
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            out, err = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                rc = ctl_main(["--socket", str(idle_daemon.socket), "--json", "start"])
            os.write(w, json.dumps({"rc": rc, "out": out.getvalue(), "err": err.getvalue()}).encode())
        except BaseException as exc:
            os.write(w, json.dumps({"rc": None, "out": "", "err": repr(exc)}).encode())
        finally:
            os._exit(0)
    os.close(w)
    with os.fdopen(r) as f:
        got = json.loads(f.read())
    os.waitpid(pid, 0)
    assert got["rc"] == 4, got
    assert json.loads(got["out"])["error"]["code"] == "forbidden"
    assert idle_daemon.ok("status")["state"] == "IDLE"  # the refused start did nothing


def test_ctl_reports_a_daemon_that_is_not_running(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "flgd.ctl", "--socket", str(tmp_path / "none.sock"), "status"],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 3 and "flgd is not running" in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "flgd.ctl", "--json", "--socket", str(tmp_path / "none.sock"),
                           "stats"], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 3 and json.loads(proc.stdout)["error"]["code"] == "not_running"
    assert subprocess.run([sys.executable, "-m", "flgd.ctl", "frobnicate"], capture_output=True,
                          cwd=REPO).returncode == 2


# --------------------------------------------------------------------------- policy, backend, snapshot

def test_policy_save_then_load_and_a_bad_policy_keeps_the_running_one(idle_daemon, tmp_path):
    saved = tmp_path / "p.safetensors"
    p = idle_daemon.ctl("policy", "save", str(saved))
    assert p.returncode == 0, p.stderr
    assert saved.stat().st_size > 0
    before = idle_daemon.ok("status")["policy"]

    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x80\x04not a policy at all" * 10)
    p = idle_daemon.ctl("policy", "load", str(bad))
    assert p.returncode == 1 and "running policy stays" in p.stderr and str(bad) in p.stderr
    assert idle_daemon.ok("status")["policy"] == before

    truncated = tmp_path / "truncated.safetensors"
    truncated.write_bytes(saved.read_bytes()[: saved.stat().st_size // 2])
    assert idle_daemon.ctl("policy", "load", str(truncated)).returncode == 1
    assert idle_daemon.ok("status")["policy"] == before

    p = idle_daemon.ctl("--json", "policy", "load", str(saved))
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["result"]["loaded"] == str(saved)
    assert str(saved) in idle_daemon.ok("status")["policy"]

    default = idle_daemon.ok("policy_save")
    assert Path(default["saved"]).parent == idle_daemon.state_dir / "policies"
    assert Path(default["saved"]).exists()
    r = idle_daemon.call("policy_load", path="relative.safetensors")
    assert r["error"]["code"] == "bad_request"
    # the daemon never writes outside its state directory, even when asked directly
    for outside in (str(tmp_path / "evil.safetensors"), str(idle_daemon.state_dir / ".." / "escape.safetensors")):
        r = idle_daemon.call("policy_save", path=outside)
        assert r["error"]["code"] == "bad_request" and "outside the state directory" in r["error"]["message"]
        assert not Path(outside).exists()
    inside = idle_daemon.state_dir / "mine.safetensors"
    assert idle_daemon.ok("policy_save", path=str(inside))["saved"] == str(inside) and inside.exists()


def test_backend_swap_failure_keeps_the_old_cell(idle_daemon):
    p = idle_daemon.ctl("backend", "no-such-cell")
    assert p.returncode == 1 and "still on 'sim'" in p.stderr
    assert idle_daemon.ok("status")["backend"] == "sim"
    p = idle_daemon.ctl("backend", "sim")  # a fresh simulated cell, connected between cycles
    assert p.returncode == 0, p.stderr
    assert "sim -> sim" in p.stdout
    assert idle_daemon.ok("status")["state"] == "IDLE"


def test_a_backend_swap_while_running_pauses(tmp_path):
    """A newly connected arm never starts moving on its own: the operator looks at it, then starts it."""
    d = DaemonProcess(tmp_path).start().wait_ready()
    try:
        assert d.ctl("start").returncode == 0
        d.wait_for(lambda s: s["cycles"] >= 1, "a cycle")
        p = d.ctl("backend", "sim")
        assert p.returncode == 0, p.stderr
        status = d.wait_for(lambda s: not s["cycle_in_flight"], "the cycle in flight to finish")
        assert status["state"] == "PAUSED" and "backend swapped" in status["cause"], status
        cycles = status["cycles"]
        time.sleep(1.0)
        assert d.ok("status")["cycles"] == cycles
    finally:
        d.cleanup()


def test_snapshot_in_idle_is_a_real_picture(idle_daemon, tmp_path):
    out = tmp_path / "snap.png"
    p = idle_daemon.ctl("snapshot", str(out))
    assert p.returncode == 0, p.stderr
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] > 400 and img.shape[1] > 2 * img.shape[0] - 100
    # not blank: the heat maps and the heightmap put many distinct colours on it
    assert img.std() > 20 and len(np.unique(img.reshape(-1, 3), axis=0)) > 500
    assert idle_daemon.ok("status")["cycles"] == 0  # a snapshot never acts
