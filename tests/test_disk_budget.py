"""The disk: a floor of free space checked before motion, a byte budget for the store, the log's retention.

``FakeDisk`` replaces ``os.statvfs`` for paths under the test's directory only, so
the daemon sees a filesystem with little space left, or one that turned
read-only, without a mount.  The daemon is the real Controller on the simulated
cell (as tests/test_motion_safety.py builds it).
"""

from __future__ import annotations

import os
import sqlite3
import time
from pathlib import Path

import pytest

from flgd import disk_budget
from flgd.actions import Action
from flgd.config import load_config
from flgd.daemon.controller import Controller
from flgd.daemon.protocol import ProtocolError, Request
from flgd.daemon.state import State
from flgd.learning.replay import Transition
from flgd.store import Store, StoreError

from tests.fakes.daemon import write_config
from tests.fakes.store_rows import action_row, random_heightmaps

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class FakeDisk:
    """What ``os.statvfs`` reports for the test's directory: ``free`` bytes (None: the truth), read-only or not."""

    def __init__(self, root: Path):
        self.root = str(root)
        self.free: int | None = None
        self.read_only = False
        self._statvfs = os.statvfs

    def statvfs(self, path):
        st = self._statvfs(path)
        if not os.fspath(path).startswith(self.root):
            return st
        fields = list(st)
        if self.free is not None:
            fields[4] = self.free // st.f_frsize  # f_bavail
        if self.read_only:
            fields[8] |= os.ST_RDONLY  # f_flag
        return os.statvfs_result(fields)


@pytest.fixture
def disk(tmp_path, monkeypatch) -> FakeDisk:
    fake = FakeDisk(tmp_path)
    monkeypatch.setattr(os, "statvfs", fake.statvfs)
    return fake


# --------------------------------------------------------------------------- the floor, in the daemon

@pytest.mark.parametrize("problem", ["below the floor", "read-only"])
def test_a_disk_problem_faults_before_any_motion_and_reset_is_refused_until_it_is_gone(tmp_path, disk, problem):
    floor = 1 << 30
    cfg = load_config(write_config(tmp_path, tmp_path / "state", storage={"min_free_bytes": floor}))
    c = Controller(cfg)
    try:
        c.setup()
        moves: list[str] = []
        execute = c.cell.execute
        c.cell.execute = lambda plan: moves.append(plan.plan.primitive) or execute(plan)
        c.handle(Request("start"))
        c._one_cycle()
        assert c.state.state is State.RUNNING and moves
        rows, before = len(c.store.action_log()), len(moves)

        if problem == "below the floor":
            disk.free = 100 << 20
        else:
            disk.read_only = True
        c._one_cycle()  # the very next cycle notices, before it moves anything
        assert c.state.state is State.FAULT and len(moves) == before
        assert len(c.store.action_log()) == rows
        cause = c.state.cause
        assert str(c.state_dir) in cause and "flgctl reset" in cause, cause
        if problem == "below the floor":
            assert f"({100 << 20} bytes) free" in cause and f"storage.min_free_bytes 1.0 GiB ({floor} bytes)" in cause
            assert c.store.events("fault")[-1]["message"] == cause, "the floor left room to record the fault"
        else:
            assert "read-only filesystem" in cause

        with pytest.raises(ProtocolError, match="reset refused, still FAULT") as refused:
            c.reset()
        assert str(c.state_dir) in refused.value.message
        assert c.state.state is State.FAULT and len(moves) == before
        assert c.handle(Request("status"))["state"] == "FAULT"

        disk.free, disk.read_only = None, False  # space is back / the filesystem is writable again
        assert c.reset() == {"state": "IDLE"}
        c.handle(Request("start"))
        c._one_cycle()
        assert c.state.state is State.RUNNING and len(moves) > before
    finally:
        c.shutdown()


# --------------------------------------------------------------------------- the floor, its words

def _statvfs(free_blocks: int, flag: int = 0, favail: int = 1000):
    return lambda path: os.statvfs_result((4096, 4096, 10**6, free_blocks, free_blocks, 10**5, favail, favail,
                                           flag, 255))


@pytest.mark.parametrize("statvfs, access, words", [
    (_statvfs(10**6), lambda p, m: False, "not writable by this user"),
    (_statvfs(0), lambda p, m: True, "the disk is full"),
    (_statvfs(10**6, favail=0), lambda p, m: True, "no free inodes"),
    (_statvfs(10**6, flag=os.ST_RDONLY), lambda p, m: True, "read-only filesystem"),
    (_statvfs(100), lambda p, m: True, "only 400.0 KiB (409600 bytes) free"),
])
def test_each_disk_problem_names_the_directory_and_what_to_do(statvfs, access, words):
    text = disk_budget.space_problem("/srv/flgd", 1 << 20, statvfs=statvfs, access=access)
    assert words in text and "/srv/flgd" in text and "flgctl reset" in text
    assert disk_budget.space_problem("/srv/flgd", 1 << 20, statvfs=_statvfs(10**6), access=lambda p, m: True) == ""


# --------------------------------------------------------------------------- the byte budget

def test_the_store_stays_under_max_bytes_by_evicting_the_oldest_transitions(tmp_path):
    budget = 2 << 20
    store = Store(tmp_path, max_bytes=budget)
    n = 300  # ~12.5 KB per state: about twice the budget in all
    states = [random_heightmaps(i, shape=(64, 64)) for i in range(n + 1)]
    largest = 0
    for i in range(n):
        store.commit_cycle(action_row(i), Transition(states[i], Action("push", 1, 2, 3), 0.5, states[i + 1], False))
        largest = max(largest, store.file_bytes())
    assert largest <= budget, f"the store's files reached {largest} bytes, over the budget of {budget}"
    kept = [t.step for t in store.iter_transitions()]
    assert 0 < len(kept) < n and kept == list(range(n - len(kept), n)), "the oldest went first, the newest stay"
    assert len(kept) * 12_000 > budget // 2, "the budget is used, not emptied"
    assert store.state_count() == len(kept) + 1
    assert len(store.action_log()) == n and store.next_step() == n  # the log is not the replay's to evict
    assert store.query("SELECT COUNT(*) FROM actions WHERE transition_id IS NOT NULL")[0][0] == len(kept)
    assert store.integrity_check() == "ok"


# --------------------------------------------------------------------------- the action log's retention

def test_old_action_log_rows_go_except_the_newest_and_those_the_gate_tallies(tmp_path):
    old, now = time.time() - 400 * disk_budget.DAY, time.time()
    store = Store(tmp_path)
    for i in range(50):
        store.commit_cycle(action_row(i, time=old if i < 40 else now), None)
    store.transaction(lambda db: db.execute(
        "INSERT INTO policies(created, role, file, sha256, origin, training_steps, since_step) "
        "VALUES(0, 'champion', 'gate/p1.safetensors', 'x', 'test', 0, 30)"))
    store.close()
    store = Store(tmp_path, action_log_days=365)  # a start applies the retention
    assert [r["step"] for r in store.action_log()] == list(range(30, 50))
    assert store.counter("actions_deleted") == 30 and store.next_step() == 50

    lone = tmp_path / "lone"
    store = Store(lone)
    for i in range(5):
        store.commit_cycle(action_row(i, time=old), None)
    store.close()
    store = Store(lone, action_log_days=365)
    assert [r["step"] for r in store.action_log()] == [4], "the newest row keeps the step counter"
    assert store.next_step() == 5


def test_totals_of_stats_and_metrics_never_go_down_when_old_rows_are_deleted(tmp_path):
    from flgd.daemon.metrics import compute_stats, status_summary

    old, now = time.time() - 400 * disk_budget.DAY, time.time()
    store = Store(tmp_path)
    kinds = [dict(primitive="grasp", kind="grasp", success=1), dict(primitive="grasp", kind="grasp", success=0),
             dict(primitive="push", kind="push", success=0), dict(primitive="shift", kind="shift", success=0),
             dict(outcome="refused", primitive="grasp", kind="grasp", success=None)]
    for i in range(60):
        store.commit_cycle(action_row(i, time=old if i < 45 else now, duration=0.5 + i % 3, **kinds[i % 5]), None)
    keys = ("cycles", "actions_executed", "plans_refused", "grasp_attempts", "grasp_successes", "moves",
            "picks_per_hour", "cycle_time_total")
    before = {k: compute_stats(store)[k] for k in keys}
    summary = status_summary(store)
    store.close()
    store = Store(tmp_path, action_log_days=365)
    assert len(store.action_log()) == 15, "the retention deleted the old rows"
    after = compute_stats(store)
    assert after["moves"] == before.pop("moves")
    assert {k: after[k] for k in before} == pytest.approx(before)
    assert status_summary(store)["cycles"] == summary["cycles"] == 60
    assert status_summary(store)["picks_per_hour"] == pytest.approx(summary["picks_per_hour"])


# --------------------------------------------------------------------------- the first diagnosis stays

class FailingWrites:
    """``connect`` whose writes raise the queued exceptions, one per write, then work again."""

    def __init__(self) -> None:
        self.queue: list[BaseException] = []

    def connect(self, *args, **kwargs):
        inner = sqlite3.connect(*args, **kwargs)
        outer = self

        class Connection:
            def execute(self, sql, params=()):
                if outer.queue and sql.lstrip().upper().startswith(("INSERT", "UPDATE", "DELETE")):
                    raise outer.queue.pop(0)
                return inner.execute(sql, params)

            def executescript(self, script):
                return inner.executescript(script)

            @property
            def in_transaction(self):
                return inner.in_transaction

            def close(self):
                inner.close()

        return Connection()


def _sqlite_error(cls, text: str, name: str) -> sqlite3.Error:
    exc = cls(text)
    exc.sqlite_errorname = name
    return exc


def test_a_malformed_report_after_an_io_error_does_not_replace_the_first_cause(tmp_path):
    writes = FailingWrites()
    store = Store(tmp_path, connect=writes.connect)
    writes.queue = [_sqlite_error(sqlite3.OperationalError, "disk I/O error", "SQLITE_IOERR_WRITE"),
                    _sqlite_error(sqlite3.DatabaseError, "database disk image is malformed", "SQLITE_CORRUPT")]
    with pytest.raises(StoreError) as first:
        store.record_event("fault", "one")
    with pytest.raises(StoreError) as later:
        store.record_event("fault", "two")
    assert "disk I/O error" in str(first.value)
    assert str(later.value).startswith(str(first.value)), str(later.value)
    assert "damaged" not in str(later.value) and "malformed" in str(later.value)
    store.record_event("state", "the disk is back")  # a write that works ends the episode
    writes.queue = [_sqlite_error(sqlite3.DatabaseError, "database disk image is malformed", "SQLITE_CORRUPT")]
    with pytest.raises(StoreError, match="the database file is damaged"):
        store.record_event("fault", "three")


def test_a_budget_the_log_alone_fills_is_said_once_as_an_event_and_in_flgctl_status(tmp_path):
    from flgd.ctl import _human

    store = Store(tmp_path, max_bytes=256 << 10)
    tiny = [random_heightmaps(i, shape=(16, 20)) for i in range(2)]  # the replay is small; the log is what fills the budget

    def cycle(step: int) -> None:
        store.commit_cycle(action_row(step), Transition(tiny[step % 2], Action("push", 1, 2, 3), 0.5, tiny[1 - step % 2],
                                                  False))

    for i in range(5000):
        cycle(i)
        if store.budget_problem:
            break
    assert "no replay left to evict" in store.budget_problem and "storage.action_log_days" in store.budget_problem
    for j in range(i + 1, i + 50):
        cycle(j)
    assert len(store.events("storage_budget")) == 1
    status = {"state": "RUNNING", "cause": "", "since": time.time(), "cycles": j, "backend": "sim", "config": "c",
              "policy": "p", "learner_updates": 0, "replay_size": 0, "stored_transitions": 1,
              "last_checkpoint": None, "state_dir": str(tmp_path), "pid": 1,
              "storage_budget_problem": store.budget_problem}
    text = _human("status", {"ok": True, "state": "RUNNING", "result": status}, {})
    assert "disk budget" in text and "storage.max_bytes" in text
