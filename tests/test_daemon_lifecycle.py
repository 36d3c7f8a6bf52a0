"""The daemon as a real process against sim_cell: states, stats vs the action log, restarts, kill -9, notify."""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest

from flgd.store import Store

from tests.fakes.daemon import REPO, DaemonProcess, tmpfs, write_config

pytestmark = pytest.mark.slow  # every test here starts a daemon


def _db_counts(state_dir: Path) -> dict:
    """The action log read directly with sqlite3 (not through flgd), as stats must agree with it."""
    db = sqlite3.connect(f"file:{state_dir / 'flgd.sqlite'}?mode=ro", uri=True)
    q = lambda sql: db.execute(sql).fetchone()[0]  # noqa: E731
    out = {
        "cycles": q("SELECT COUNT(*) FROM actions"),
        "attempts": q("SELECT COUNT(*) FROM actions WHERE outcome='executed' AND primitive='grasp'"),
        "successes": q("SELECT COUNT(*) FROM actions WHERE outcome='executed' AND primitive='grasp' AND success=1"),
        "push": q("SELECT COUNT(*) FROM actions WHERE outcome='executed' AND kind='push'"),
        "shift": q("SELECT COUNT(*) FROM actions WHERE outcome='executed' AND kind='shift'"),
        "refused": q("SELECT COUNT(*) FROM actions WHERE outcome='refused'"),
        "executed": q("SELECT COUNT(*) FROM actions WHERE outcome='executed'"),
        "transitions": q("SELECT COUNT(*) FROM transitions"),
    }
    db.close()
    return out


def test_start_pause_reset_start_stop_and_stats_match_the_log(daemon_factory, tmp_path):
    d = daemon_factory().start().wait_ready()
    assert d.ok("status")["state"] == "IDLE"
    p = d.ctl("start")
    assert p.returncode == 0 and "RUNNING" in p.stdout, p.stderr
    d.wait_for(lambda s: s["cycles"] >= 4, "4 cycles")
    p = d.ctl("pause")
    assert p.returncode == 0, p.stderr
    st = d.wait_for(lambda s: not s["cycle_in_flight"], "the cycle in flight to finish")
    p = d.ctl("status")
    assert p.returncode == 0 and p.stdout.startswith("state         PAUSED"), p.stdout
    assert d.ctl("pause").returncode == 1  # wrong state now

    snap = tmp_path / "snap.png"
    p = d.ctl("snapshot", str(snap))
    assert p.returncode == 0 and "last decision" in p.stdout, p.stderr
    assert cv2.imread(str(snap)) is not None

    p = d.ctl("reset")
    assert p.returncode == 0 and "IDLE" in p.stdout, p.stderr
    assert d.ctl("start").returncode == 0
    d.wait_for(lambda s: s["cycles"] >= st["cycles"] + 3, "3 more cycles")
    assert d.ctl("pause").returncode == 0
    d.wait_for(lambda s: not s["cycle_in_flight"] and s["state"] == "PAUSED", "paused")

    p = d.ctl("--json", "stats")
    assert p.returncode == 0, p.stderr
    stats = json.loads(p.stdout)["result"]
    db = _db_counts(d.state_dir)
    assert stats["cycles"] == db["cycles"] >= 7
    assert stats["grasp_attempts"] == db["attempts"]
    assert stats["grasp_successes"] == db["successes"]
    assert stats["moves"] == {"push": db["push"], "shift": db["shift"]}
    assert stats["plans_refused"] == db["refused"]
    assert stats["actions_executed"] == db["executed"]
    if db["executed"]:
        assert stats["action_efficiency"] == pytest.approx(db["successes"] / db["executed"])
    for phase in ("capture", "perceive", "decide", "execute", "judge", "store"):
        assert stats["timing_median"][phase] is not None and stats["timing_median"][phase] >= 0
    human = d.ctl("stats")
    assert human.returncode == 0 and f"cycles               {db['cycles']}" in human.stdout
    status = d.ok("status")
    assert status["stored_transitions"] == db["transitions"] == status["replay_size"]
    assert isinstance(status["learner_backlog"], int) and status["learner_backlog"] >= 0
    assert "dropped), replay" in d.ctl("status").stdout

    p = d.ctl("stop")
    assert p.returncode == 0
    assert d.wait_exit() == 0
    log = d.log()
    for change in ("IDLE -> RUNNING: start by operator", "RUNNING -> PAUSED: pause by operator",
                   "PAUSED -> IDLE: reset by operator", "-> STOPPING: stop by operator"):
        assert change in log, change
    store = Store(d.state_dir)
    assert store.integrity_check() == "ok"
    kinds = [e["message"] for e in store.events("state")]
    assert any("PAUSED -> IDLE" in k for k in kinds)
    assert not d.socket.exists()  # removed on a clean stop
    store.close()

    # a restart after a clean stop resumes the final checkpoint with its target network and Adam moments
    again = daemon_factory(config=d.config, state_dir=d.state_dir).start().wait_ready()
    st = again.ok("status")
    assert st["resumed_from_updates"] >= status["learner_updates"] > 0  # the learner ran on until the stop
    assert st["trainer_state"] == f"restored at update {st['resumed_from_updates']}"
    assert "restored at update" in again.log()
    assert f"optimizer restored at update {st['resumed_from_updates']}" in again.ctl("status").stdout

    # a trainer state that cannot be read is reported and skipped: the daemon starts and runs on its checkpoint
    assert again.ctl("stop").returncode == 0 and again.wait_exit() == 0
    (d.state_dir / "trainer-state.safetensors").write_bytes(b"cut off")
    third = daemon_factory(config=d.config, state_dir=d.state_dir, args=["--autostart"]).start().wait_ready()
    st = third.ok("status")
    assert st["trainer_state"].startswith("fresh (") and "not a readable trainer state" in st["trainer_state"]
    third.wait_for(lambda s: s["cycles"] >= st["cycles"] + 1, "a cycle after a bad trainer state")


def _checkpoint_and_state(state_dir: Path) -> tuple[int, int | None] | None:
    """(newest checkpoint's update count, trainer state's update count or None), read from the files."""
    from safetensors import safe_open

    ckpts = sorted((state_dir / "checkpoints").glob("checkpoint-*.safetensors"))
    if not ckpts:
        return None
    newest = int(ckpts[-1].stem.split("-")[1])
    path = state_dir / "trainer-state.safetensors"
    if not path.exists():
        return newest, None
    with safe_open(str(path), framework="pt") as f:
        return newest, int((f.metadata() or {})["updates"])


def test_kill_9_at_random_points_then_resume(daemon_factory, tmp_path):
    """Five runs killed at random instants (one just after a checkpoint): nothing corrupt, learning resumes."""
    rng = random.Random(11)
    state_dir = tmp_path / "state"
    config = write_config(tmp_path, state_dir)
    last_updates = 0
    restored = 0
    on_disk: tuple[int, int | None] | None = None
    for run in range(5):
        d = daemon_factory(config=config, state_dir=state_dir, args=["--autostart"]).start().wait_ready()
        st = d.ok("status")
        stored = Store(state_dir)
        assert stored.integrity_check() == "ok"
        assert st["replay_size"] == st["stored_transitions"] == stored.transition_count()
        assert st["step"] == stored.next_step()
        if run > 0:
            assert on_disk is not None, "a checkpoint must exist after the first runs"
            newest, state_updates = on_disk
            assert st["resumed_from_updates"] == newest and "checkpoint" in st["learner_from"]
            assert newest >= last_updates  # never goes back
            last_updates = newest
            # restored exactly when the kill left the trainer state of that very checkpoint on disk
            ts = st["trainer_state"]
            if state_updates == newest:
                assert ts == f"restored at update {newest}", ts
                restored += 1
            else:
                assert "is of update" in ts or "not found" in ts, ts
        stored.close()
        # let some cycles and updates happen, then kill at a random moment (maybe mid-cycle, mid-checkpoint)
        target = st["cycles"] + rng.randint(1, 4)
        d.wait_for(lambda s: s["cycles"] >= target, f"run {run}: {target} cycles", poll=0.1)
        if run == 0:  # the resume checks below need one checkpoint; a loaded machine may be slow to learn
            d.wait_for(lambda s: any((state_dir / "checkpoints").glob("checkpoint-*.safetensors")),
                       "a first checkpoint", poll=0.1)
        if run == 2:  # one kill just after a checkpoint and its trainer state are both written
            d.wait_for(lambda s: (lambda p: p is not None and p[0] == p[1])(_checkpoint_and_state(state_dir)),
                       "a checkpoint with its trainer state", poll=0.02)
        else:
            time.sleep(rng.uniform(0.0, 1.5))
        d.kill9()
        on_disk = _checkpoint_and_state(state_dir)
    store = Store(state_dir)
    assert store.integrity_check() == "ok"
    assert store.transition_count() == store.query("SELECT COUNT(*) FROM actions WHERE transition_id IS NOT NULL")[0][0]
    assert last_updates > 0
    assert restored >= 1, "no resumed run got its trainer state back"


def test_notify_messages_and_sigterm(daemon_factory, tmp_path):
    recv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify.sock"
    recv.bind(str(path))
    recv.settimeout(120)
    d = daemon_factory(env={"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "2000000"}, args=["--autostart"])
    d.start()
    got: list[str] = []

    def until(pred, what: str) -> None:
        while not any(pred(m) for m in got):
            try:
                got.append(recv.recv(65536).decode())
            except socket.timeout:
                raise AssertionError(f"no {what} notification; got {got}\n{d.log()}") from None

    until(lambda m: "READY=1" in m, "READY")
    ready = next(m for m in got if "READY=1" in m)
    assert f"MAINPID={d.proc.pid}" in ready
    # READY comes only once the cell and the policy are up: the socket already answers then
    assert d.ok("status")["backend"] == "sim"
    until(lambda m: m == "WATCHDOG=1", "WATCHDOG")
    until(lambda m: m.startswith("STATUS=RUNNING"), "STATUS RUNNING")
    d.wait_for(lambda s: s["cycles"] >= 2, "2 cycles")
    d.proc.send_signal(signal.SIGTERM)
    until(lambda m: "STOPPING=1" in m, "STOPPING")
    assert d.wait_exit() == 0
    assert "signal SIGTERM" in d.log()
    assert sorted((d.state_dir / "checkpoints").glob("*.safetensors")), "final checkpoint written"
    recv.close()


def test_bad_config_and_bad_policy_exit_nonzero_with_a_clear_message(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("backend: sim\nrobot:\n  speed: -1\n")
    p = subprocess.run([sys.executable, "-m", "flgd.cli", "run", "--config", str(cfg)], capture_output=True,
                       text=True, cwd=REPO, timeout=120)
    assert p.returncode == 1 and "robot.speed" in p.stderr and str(cfg) in p.stderr
    good = write_config(tmp_path, tmp_path / "state")
    bad_policy = tmp_path / "nope.safetensors"
    bad_policy.write_bytes(b"garbage")
    p = subprocess.run([sys.executable, "-m", "flgd.cli", "run", "--config", str(good), "--policy", str(bad_policy),
                        "--socket", str(tmp_path / "s.sock")], capture_output=True, text=True, cwd=REPO,
                       timeout=120)
    assert p.returncode == 1 and str(bad_policy) in p.stderr, p.stderr
    assert not (tmp_path / "s.sock").exists()


def test_full_disk_gives_a_fault_not_a_crash(daemon_factory, tmp_path):
    with tmpfs(tmp_path / "small", size="3m") as state_dir:
        # no free-space floor: the writes themselves meet the full disk (the floor: tests/test_disk_budget.py)
        d = daemon_factory(state_dir=state_dir, args=["--autostart"],
                           storage={"min_free_bytes": 0}).start().wait_ready()
        st = d.wait_for(lambda s: s["state"] == "FAULT", "a FAULT from the full disk", timeout=400)
        assert "disk is full" in st["cause"], st["cause"]
        assert d.proc.poll() is None  # still running and answering
        p = d.ctl("status")
        assert p.returncode == 0 and "FAULT" in p.stdout and "disk is full" in p.stdout
        assert d.ctl("start").returncode == 1  # no motion until a reset succeeds
        # A reset may succeed while a small write still fits; the next write (a cycle, or the learner's
        # next checkpoint) then faults again, cleanly.
        p = d.ctl("reset")
        if p.returncode == 0:
            d.ctl("start")  # may already be refused because the learner's checkpoint faulted first
        else:
            assert p.returncode == 1 and "disk is full" in p.stderr, p.stderr
        st = d.wait_for(lambda s: s["state"] == "FAULT", "the FAULT to come back", timeout=400)
        assert st["state"] == "FAULT" and "disk is full" in st["cause"]
        assert d.proc.poll() is None
        d.ctl("stop")
        assert d.wait_exit() == 0


def test_read_only_state_dir_gives_a_fault_at_startup(daemon_factory, tmp_path):
    with tmpfs(tmp_path / "ro", size="1m") as state_dir:
        subprocess.run(["mount", "-o", "remount,ro", str(state_dir)], check=True)
        d = daemon_factory(state_dir=state_dir).start().wait_ready()
        st = d.ok("status")
        assert st["state"] == "FAULT" and "read-only" in st["cause"], st
        assert d.call("start")["error"]["code"] == "wrong_state"
        r = d.call("reset")
        assert not r["ok"] and "read-only" in r["error"]["message"]
        assert d.ok("status")["state"] == "FAULT"
        d.proc.send_signal(signal.SIGTERM)
        assert d.wait_exit() == 0


def test_a_daemon_started_on_a_read_only_state_dir_holds_it_once_it_is_writable(daemon_factory, tmp_path):
    """The first daemon starts in FAULT on a read-only directory; made writable, the directory is still the
    first one's: a second daemon on it is refused, naming why, and never reaches ready."""
    with tmpfs(tmp_path / "ro", size="4m") as state_dir:
        subprocess.run(["mount", "-o", "remount,ro", str(state_dir)], check=True)
        first = daemon_factory(state_dir=state_dir).start().wait_ready()
        assert first.ok("status")["state"] == "FAULT"
        subprocess.run(["mount", "-o", "remount,rw", str(state_dir)], check=True)
        (tmp_path / "second").mkdir()
        second = DaemonProcess(tmp_path / "second", config=first.config, state_dir=state_dir)
        try:
            code = second.start().wait_exit(timeout=120)
            assert code != 0
            assert "is using the state directory" in second.log() and str(state_dir) in second.log()
        finally:
            second.cleanup()
        assert not (state_dir / "flgd.sqlite").exists()  # nobody wrote a store there
        assert first.ok("status")["state"] == "FAULT"
        first.proc.send_signal(signal.SIGTERM)
        assert first.wait_exit() == 0


def test_the_state_dir_lock_needs_no_write_access_and_a_missing_dir_is_no_lock(tmp_path):
    """What the daemon's start relies on: the lock of a directory nobody may write is taken and excludes the
    next taker; a directory that cannot be made is an error, never a start without the lock."""
    from flgd.state_dir_lock import StateDirBusy, lock_state_dir

    with tmpfs(tmp_path / "ro", size="1m") as state_dir:
        subprocess.run(["mount", "-o", "remount,ro", str(state_dir)], check=True)
        fd = lock_state_dir(state_dir, create=True)
        try:
            with pytest.raises(StateDirBusy):
                lock_state_dir(state_dir, create=True)
        finally:
            os.close(fd)
        with pytest.raises(OSError):
            lock_state_dir(state_dir / "inside", create=True)


def test_a_second_daemon_on_the_same_state_directory_is_refused(daemon_factory, tmp_path):
    """Two daemons on one cell would drive one arm and write one store; the second exits, naming why."""
    first = daemon_factory().start().wait_ready()
    (tmp_path / "second").mkdir()
    second = DaemonProcess(tmp_path / "second", config=first.config, state_dir=first.state_dir)
    try:
        code = second.start().wait_exit(timeout=120)
        assert code != 0
        assert "is using the state directory" in second.log() and str(first.state_dir) in second.log()
    finally:
        second.cleanup()
    assert first.ok("status")["state"] == "IDLE"  # the first one is untouched
