"""The SQLite store: round trips, one state per row, atomic cycles under kill -9, clear storage errors."""

from __future__ import annotations

import os
import random
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from flgd.actions import Action
from flgd.learning.replay import Transition
from flgd.perception import Heightmaps
from flgd.store import SCHEMA_VERSION, HEIGHT_QUANTUM, CheckpointDir, Store, StoreError

from tests.fakes.daemon import tmpfs
from tests.fakes.store_rows import action_row, random_heightmaps



def test_round_trip_and_states_stored_once(tmp_path):
    store = Store(tmp_path)
    states = [random_heightmaps(i) for i in range(5)]
    for i in range(4):
        t = Transition(states[i], Action("grasp" if i % 2 else "push", i, i + 1, i % 16), float(i % 2),
                       states[i + 1], False)
        store.commit_cycle(action_row(i), t)
    # A done transition: no next state.
    store.commit_cycle(action_row(4), Transition(states[4], Action("grasp", 3, 4, 5), 1.0, None, True))
    assert store.transition_count() == 5
    assert store.state_count() == 5  # s0..s4, each once, although 9 state references were written
    assert store.next_step() == 5
    read = list(store.iter_transitions())
    assert [r.step for r in read] == [0, 1, 2, 3, 4]
    for i, r in enumerate(read[:4]):
        np.testing.assert_array_equal(r.state.color, states[i].color)
        np.testing.assert_allclose(r.state.height, states[i].height, atol=HEIGHT_QUANTUM / 2 + 1e-7)
        assert r.next_state is read[i + 1].state  # shared object, held once in memory
        assert r.action == Action("grasp" if i % 2 else "push", i, i + 1, i % 16)
    assert read[4].done and read[4].next_state is None
    assert [r.step for r in store.iter_transitions(limit=2)] == [3, 4]
    assert store.integrity_check() == "ok"
    mode = sqlite3.connect(tmp_path / "flgd.sqlite").execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"


def test_action_log_without_transition_and_store_time(tmp_path):
    store = Store(tmp_path)
    store.commit_cycle(action_row(0, outcome="discarded", failure="unstable physics"), None)
    store.note_store_time(0, 0.123)
    store.commit_cycle(action_row(1), Transition(random_heightmaps(0), Action("grasp", 0, 0, 0), 0.0, random_heightmaps(1), False))
    log = store.action_log()
    assert [r["outcome"] for r in log] == ["discarded", "executed"]
    assert log[0]["transition_id"] is None and log[1]["transition_id"] == 1
    assert log[0]["t_store"] == pytest.approx(0.123)  # written by the next commit
    assert log[1]["t_store"] is None
    with pytest.raises(ValueError, match="unknown action-log columns"):
        store.commit_cycle({"step": 2, "time": 0.0, "outcome": "x", "bogus": 1}, None)


def test_refused_action_reuses_its_state(tmp_path):
    store = Store(tmp_path)
    s = random_heightmaps(3)
    store.commit_cycle(action_row(0, outcome="refused"), Transition(s, Action("grasp", 1, 1, 0), 0.0, s, False))
    store.commit_cycle(action_row(1), Transition(s, Action("grasp", 2, 2, 0), 1.0, random_heightmaps(4), False))
    assert store.state_count() == 2
    first, second = store.iter_transitions()
    assert first.next_state is first.state and second.state is first.state


def test_duplicate_step_is_rejected_and_rolled_back(tmp_path):
    store = Store(tmp_path)
    store.commit_cycle(action_row(0), Transition(random_heightmaps(0), Action("grasp", 0, 0, 0), 1.0, random_heightmaps(1), False))
    with pytest.raises(StoreError, match="UNIQUE|constraint"):
        store.commit_cycle(action_row(0), Transition(random_heightmaps(2), Action("grasp", 0, 0, 0), 1.0, random_heightmaps(3), False))
    # The whole failed cycle was rolled back: no orphan transition or state.
    assert store.transition_count() == 1 and store.state_count() == 2


def test_schema_version_mismatch_is_a_clear_error(tmp_path):
    Store(tmp_path).close()
    db = sqlite3.connect(tmp_path / "flgd.sqlite")
    db.execute("UPDATE meta SET value='99' WHERE key='schema_version'")
    db.commit()
    db.close()
    with pytest.raises(StoreError, match="schema version 99"):
        Store(tmp_path)


def _interleaved_chains(store: Store, order: str = "abababab") -> None:
    """Two cells' cycles in ``order``: a0->a1, b0->b1, a1->a2, ... (``flgd train --workers 2``; one cell can be
    faster than the other)."""
    chains = {c: [random_heightmaps((100 if c == "a" else 200) + i) for i in range(order.count(c) + 1)] for c in "ab"}
    done = {"a": 0, "b": 0}
    for step, c in enumerate(order):
        i = done[c]
        store.commit_cycle(action_row(step), Transition(chains[c][i], Action("grasp", 0, 0, 0), 0.0,
                                                        chains[c][i + 1], False))
        done[c] += 1


def test_interleaved_cells_store_each_state_once_when_the_store_remembers_one_per_cell(tmp_path):
    one = Store(tmp_path / "one")
    _interleaved_chains(one)
    assert one.state_count() == 16            # every state twice, as a next state and again as a start
    two = Store(tmp_path / "two")
    two.remember_states = 2
    _interleaved_chains(two)
    assert two.state_count() == 10            # a0..a4, b0..b4 once
    read = list(two.iter_transitions())
    assert all(r.next_state is not None for r in read) and two.integrity_check() == "ok"
    np.testing.assert_array_equal(read[2].state.height, read[0].next_state.height)   # a1 links a0->a1 and a1->a2
    uneven = Store(tmp_path / "uneven")
    uneven.remember_states = 2
    _interleaved_chains(uneven, "abbabbba")   # b's used-up states must not push out a's current one
    assert uneven.state_count() == 4 + 6       # a0..a3, b0..b5 once


def test_a_remembered_state_whose_row_was_pruned_is_stored_again(tmp_path, monkeypatch):
    monkeypatch.setattr(Store, "PRUNE_EVERY", 1)
    store = Store(tmp_path, keep_transitions=1)
    store.remember_states = 3
    s = [random_heightmaps(i) for i in range(4)]
    store.commit_cycle(action_row(0), Transition(s[0], Action("grasp", 0, 0, 0), 0.0, s[1], False))
    store.commit_cycle(action_row(1), Transition(s[2], Action("grasp", 0, 0, 0), 0.0, s[3], False))  # prunes 0
    # s[1] is still remembered, but its row went with transition 0: a fresh row, not a dangling id
    store.commit_cycle(action_row(2), Transition(s[1], Action("grasp", 0, 0, 0), 0.0, None, True))
    read = list(store.iter_transitions())
    np.testing.assert_allclose(read[-1].state.height, s[1].height, atol=HEIGHT_QUANTUM)
    assert store.integrity_check() == "ok"


def test_retention_keeps_the_newest_transitions_and_the_whole_log(tmp_path, monkeypatch):
    monkeypatch.setattr(Store, "PRUNE_EVERY", 5)
    store = Store(tmp_path, keep_transitions=7)
    states = [random_heightmaps(i) for i in range(31)]
    for i in range(30):
        store.commit_cycle(action_row(i), Transition(states[i], Action("grasp", 0, 0, 0), 1.0, states[i + 1], False))
    assert store.transition_count() == 7  # pruned at commit 30 down to the newest 7
    read = list(store.iter_transitions())
    assert [t.step for t in read] == list(range(23, 30))
    np.testing.assert_array_equal(read[0].state.color, states[23].color)
    assert store.state_count() == 8  # s23..s30, older ones deleted with their transitions
    assert len(store.action_log()) == 30 and store.next_step() == 30
    assert store.query("SELECT COUNT(*) FROM actions WHERE transition_id IS NOT NULL")[0][0] == 7
    # a state still in use as the next start survives the pruning: the chain continues without a copy
    store.commit_cycle(action_row(30), Transition(states[30], Action("grasp", 0, 0, 0), 1.0, random_heightmaps(99), False))
    assert store.state_count() == 9
    assert store.integrity_check() == "ok"


def test_checkpoint_dir_keeps_the_newest(tmp_path):
    ck = CheckpointDir(tmp_path / "checkpoints", keep=2)
    for u in (10, 20, 30):
        ck.write(lambda p, u=u: p.write_text(str(u)), u)
    names = [p.name for p in ck.checkpoints()]
    assert names == ["checkpoint-0000000030.safetensors", "checkpoint-0000000020.safetensors"]
    assert CheckpointDir.updates_of(ck.checkpoints()[0]) == 30
    (ck.directory / ".checkpoint-0000000040.safetensors.abc123.tmp").write_text("torn")
    assert ck.remove_temporary() == 1
    assert len(list(ck.directory.iterdir())) == 2


_WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from flgd.actions import Action
    from flgd.learning.replay import Transition
    from flgd.perception import Heightmaps
    from flgd.store import Store
    store = Store(sys.argv[1])
    step = store.next_step()
    rng = np.random.default_rng(step)
    def hm():
        return Heightmaps(rng.integers(0, 255, (96, 96, 3), dtype=np.uint8),
                          rng.uniform(0, 0.1, (96, 96)).astype(np.float32))
    state = hm()
    print("ready", flush=True)
    while True:
        nxt = hm()
        store.commit_cycle({"step": step, "time": time.time(), "outcome": "executed", "primitive": "push",
                            "kind": "push", "reward": 0.5, "duration": 0.01},
                           Transition(state, Action("push", 1, 2, 3), 0.5, nxt, False))
        state, step = nxt, step + 1
""")


def test_kill_minus_9_never_corrupts_or_splits_a_cycle(tmp_path):
    """A writer killed at random instants: every cycle is all-or-nothing and the file stays sound."""
    rng = random.Random(5)
    runs_with_commits = 0
    for _run in range(6):
        before = Store(tmp_path).next_step()
        proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp_path)], stdout=subprocess.PIPE,
                                cwd=Path(__file__).resolve().parents[1])
        assert proc.stdout.readline().strip() == b"ready"
        time.sleep(rng.uniform(0.05, 0.6))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        store = Store(tmp_path)
        assert store.integrity_check() == "ok"
        n_actions = store.query("SELECT COUNT(*) FROM actions")[0][0]
        assert n_actions == store.transition_count() == store.next_step()
        assert store.query("SELECT COUNT(*) FROM actions WHERE transition_id IS NULL")[0][0] == 0
        runs_with_commits += n_actions > before
        # one state per transition, plus the first state of each writer run: no torn or orphan rows
        assert store.state_count() == n_actions + runs_with_commits
        for t in store.iter_transitions():
            assert t.next_state is not None
        store.close()
    assert n_actions > 0


def test_read_only_state_dir_is_a_clear_store_error(tmp_path):
    with tmpfs(tmp_path / "ro", size="4m") as mnt:
        store = Store(mnt)
        store.commit_cycle(action_row(0), Transition(random_heightmaps(0), Action("grasp", 0, 0, 0), 1.0, random_heightmaps(1), False))
        store.close()
        subprocess.run(["mount", "-o", "remount,ro", str(mnt)], check=True)
        with pytest.raises(StoreError, match="read-only"):
            Store(mnt)
        with pytest.raises(StoreError, match="read-only"):
            Store(mnt / "new")


def test_full_disk_is_a_clear_store_error(tmp_path):
    with tmpfs(tmp_path / "full", size="1m") as mnt:
        store = Store(mnt)
        with pytest.raises(StoreError, match="disk is full"):
            for i in range(200):  # incompressible heightmaps: ~40 kB per cycle
                rng = np.random.default_rng(i)
                big = Heightmaps(rng.integers(0, 255, (96, 96, 3), dtype=np.uint8),
                                 rng.uniform(0, 1, (96, 96)).astype(np.float32))
                store.commit_cycle(action_row(i), Transition(big, Action("grasp", 0, 0, 0), 0.0, big, False))
        done = store.next_step()
        assert 0 < done < 200
        assert store.integrity_check() == "ok"
        assert store.transition_count() == done  # the failed cycle left nothing behind
        store.close()


def _as_written_by_version(tmp_path, version: int, *statements: str) -> None:
    """A store with one committed cycle, turned into exactly what schema ``version`` wrote by ``statements``."""
    store = Store(tmp_path)
    store.commit_cycle(action_row(0), Transition(random_heightmaps(0), Action("grasp", 0, 0, 0), 1.0, random_heightmaps(1), False))
    store.close()
    db = sqlite3.connect(tmp_path / "flgd.sqlite")
    for statement in statements:
        db.execute(statement)
    db.execute("UPDATE meta SET value=? WHERE key='schema_version'", (str(version),))
    db.commit()
    db.close()


def test_a_version_1_store_is_upgraded_in_place_without_losing_anything(tmp_path):
    _as_written_by_version(tmp_path, 1, "ALTER TABLE actions DROP COLUMN contact_stop_mm",
                           "ALTER TABLE actions DROP COLUMN cell_time", "ALTER TABLE actions DROP COLUMN gripper_time",
                           "ALTER TABLE actions DROP COLUMN decide_hidden")

    store = Store(tmp_path)
    try:
        assert store.query("SELECT value FROM meta WHERE key='schema_version'") == [(str(SCHEMA_VERSION),)]
        assert store.transition_count() == 1 and store.next_step() == 1
        assert store.query("SELECT step, success, contact_stop_mm FROM actions") == [(0, 1, None)]
        store.commit_cycle(action_row(1, contact_stop_mm=7.5),
                           Transition(random_heightmaps(1), Action("grasp", 0, 0, 0), 0.0, random_heightmaps(2), False))
        assert store.query("SELECT contact_stop_mm FROM actions WHERE step=1") == [(7.5,)]
        assert store.integrity_check() == "ok"
    finally:
        store.close()


def test_stats_count_the_grasps_whose_descent_stopped_at_a_contact(tmp_path):
    from flgd.daemon.metrics import compute_stats, format_stats

    store = Store(tmp_path)
    try:
        for step, mm in enumerate([None, 4.0, None, 12.0, 9.0]):
            store.commit_cycle(action_row(step, contact_stop_mm=mm))
        store.commit_cycle(action_row(5, primitive="push", kind="push", success=None, contact_stop_mm=3.0))
        stats = compute_stats(store)
    finally:
        store.close()
    assert stats["grasp_attempts"] == 5
    assert (stats["contact_stops"], stats["contact_stop_share"], stats["contact_stop_mm_median"]) == (3, 0.6, 9.0)
    assert "contact stops        3 of the grasps (60.0%), median 9.0 mm" in format_stats(stats)


def test_picks_per_hour_counts_successful_grasps_only_and_status_agrees_with_stats(tmp_path):
    """A push whose reward counts as a success is not a pick (the status line once counted it)."""
    from flgd.daemon.metrics import compute_stats, status_summary

    store = Store(tmp_path)
    try:
        store.commit_cycle(action_row(0, duration=10.0))                                       # a pick
        store.commit_cycle(action_row(1, success=0, reward=0.0, duration=10.0))                # a failed grasp
        store.commit_cycle(action_row(2, primitive="push", kind="push", success=1, duration=10.0))  # a useful push
        store.commit_cycle(action_row(3, outcome="refused", success=None, duration=0.0))
        stats, status = compute_stats(store), status_summary(store)
    finally:
        store.close()
    assert stats["picks_per_hour"] == pytest.approx(1 * 3600.0 / 30.0)
    assert status["picks_per_hour"] == stats["picks_per_hour"]


def test_commits_are_fsynced_so_a_power_cut_loses_at_most_the_cycle_in_flight(tmp_path):
    """WAL with synchronous=NORMAL survives a killed process but may lose committed cycles in a power cut;
    the README promises only the action in flight is lost, which needs FULL (2)."""
    store = Store(tmp_path)
    try:
        assert store.query("PRAGMA synchronous")[0][0] == 2
        assert store.query("PRAGMA journal_mode")[0][0] == "wal"
    finally:
        store.close()


def test_a_version_2_store_gains_the_gate_column_and_tables_in_place(tmp_path):
    _as_written_by_version(tmp_path, 2, "DROP INDEX actions_policy", "ALTER TABLE actions DROP COLUMN policy",
                           "ALTER TABLE actions DROP COLUMN cell_time", "ALTER TABLE actions DROP COLUMN gripper_time",
                           "ALTER TABLE actions DROP COLUMN decide_hidden", "DROP TABLE policies", "DROP TABLE gate_events")

    store = Store(tmp_path)
    try:
        assert store.query("SELECT value FROM meta WHERE key='schema_version'") == [(str(SCHEMA_VERSION),)]
        assert store.query("SELECT step, success, policy FROM actions") == [(0, 1, None)]
        store.commit_cycle(action_row(1, policy=4), None)
        assert store.query("SELECT policy FROM actions WHERE step=1") == [(4,)]
        assert store.query("SELECT COUNT(*) FROM policies") == [(0,)]
        assert store.integrity_check() == "ok"
    finally:
        store.close()


def test_a_version_3_store_gains_the_cell_and_gripper_time_columns_in_place(tmp_path):
    _as_written_by_version(tmp_path, 3, "ALTER TABLE actions DROP COLUMN cell_time",
                           "ALTER TABLE actions DROP COLUMN gripper_time", "ALTER TABLE actions DROP COLUMN decide_hidden")

    store = Store(tmp_path)
    try:
        assert store.query("SELECT value FROM meta WHERE key='schema_version'") == [(str(SCHEMA_VERSION),)]
        assert store.query("SELECT step, success, cell_time, gripper_time FROM actions") == [(0, 1, None, None)]
        store.commit_cycle(action_row(1, cell_time=8.25, gripper_time=1.5), None)
        assert store.query("SELECT cell_time, gripper_time FROM actions WHERE step=1") == [(8.25, 1.5)]
        assert store.transition_count() == 1 and store.integrity_check() == "ok"
    finally:
        store.close()


def test_a_version_4_store_gains_the_hidden_decision_column_in_place(tmp_path):
    _as_written_by_version(tmp_path, 4, "ALTER TABLE actions DROP COLUMN decide_hidden")

    store = Store(tmp_path)
    try:
        assert store.query("SELECT value FROM meta WHERE key='schema_version'") == [(str(SCHEMA_VERSION),)]
        assert store.query("SELECT step, success, decide_hidden FROM actions") == [(0, 1, None)]
        store.commit_cycle(action_row(1, decide_hidden=0.31), None)
        assert store.query("SELECT decide_hidden FROM actions WHERE step=1") == [(0.31,)]
        assert store.transition_count() == 1 and store.integrity_check() == "ok"
    finally:
        store.close()


def test_picks_per_hour_count_the_motions_on_the_cells_clock_and_survive_retention(tmp_path):
    """A simulated arm moves 9 s in 0.2 s of the PC's time: its picks per hour are the arm's (one pick per 9.5 s),
    not the simulator's; rows the retention deletes keep counting the same way."""
    import time

    from flgd import disk_budget
    from flgd.daemon.metrics import compute_stats, status_summary

    old = time.time() - 400 * disk_budget.DAY
    store = Store(tmp_path)
    for step in range(4):   # the controller's work 0.5 s + execute 0.2 s of wall clock; the motions 9 s of the cell's
        store.commit_cycle(action_row(step, duration=0.7, t_execute=0.2, cell_time=9.0,
                                      time=old if step < 3 else time.time()))
    # a cycle cut short before its commit: its home move has a time on the cell's clock, the cycle no duration
    store.commit_cycle(action_row(4, outcome="interrupted", success=None, duration=0.0, t_execute=0.3,
                                  cell_time=4.0))
    before = compute_stats(store)["picks_per_hour"]
    assert before == pytest.approx(4 * 3600.0 / (4 * 9.5))
    assert status_summary(store)["picks_per_hour"] == pytest.approx(before)
    store.close()
    store = Store(tmp_path, action_log_days=365)   # a start applies the retention
    try:
        assert len(store.action_log()) == 2, "the retention deleted the old rows"
        assert compute_stats(store)["picks_per_hour"] == pytest.approx(before)
    finally:
        store.close()


def test_stats_split_the_cycle_on_the_cells_clock_into_motion_gripper_and_waiting(tmp_path):
    from flgd.daemon.metrics import compute_stats, format_stats

    store = Store(tmp_path)
    try:
        # decisions of 0.3 s: the first made with the arm still, the others 0.2 s and 0.3 s behind the place
        for step, (cell, gripper, hidden) in enumerate([(9.0, 1.0, None), (10.0, 1.5, 0.2), (11.0, 2.0, 0.3)]):
            store.commit_cycle(action_row(step, duration=0.7, t_execute=0.2, cell_time=cell, gripper_time=gripper,
                                          t_decide=0.3, decide_hidden=hidden))
        store.commit_cycle(action_row(3, outcome="fault", success=None, duration=5.0))   # no cell time: not in it
        stats = compute_stats(store)
        t = stats["timing_median"]
        text = format_stats(stats)
    finally:
        store.close()
    assert (t["motion"], t["gripper"], t["waiting"], t["cycle_on_cell_clock"]) == pytest.approx((8.5, 1.5, 0.5, 10.5))
    assert stats["decide_hidden_share"] == pytest.approx(0.5 / 0.9)
    assert ("on the cell's clock: cycle 10.500 s, motion 8.500 s, gripper 1.500 s, waiting for the controller "
            "0.500 s") in text
    assert "decide time hidden behind the arm's motion: 55.6%" in text
