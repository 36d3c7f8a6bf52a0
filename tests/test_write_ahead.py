"""Nothing moves unrecorded: the action is in the log before the cell moves, whatever fails and whenever.

``FullDisk`` stands in for ``sqlite3.connect``: a real connection whose writes fail
as a full disk makes them fail (``database or disk is full``) from a chosen
instant on.  The cycle runs on the real simulated cell with the real agent; a
wrapper around the cell notes every step whose action plan was sent to it.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from flgd.actions import Action
from flgd.cell import make_cell
from flgd.config import load_config
from flgd.cycle import CycleRunner
from flgd.daemon.metrics import compute_stats, status_summary
from flgd.gate.keeper import CREDITED_OUTCOMES
from flgd.learning.agent import Agent
from flgd.learning.networks import build_network
from flgd.learning.replay import Transition
from flgd.store import INTENT_OUTCOME, INTERRUPTED_OUTCOME, Store, StoreError

from tests.fakes.store_rows import action_row, random_heightmaps

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_torch_thread")

ACTION_PRIMITIVES = ("grasp", "push", "shift")
_WRITES = ("INSERT", "UPDATE", "DELETE", "REPLACE", "COMMIT")


class FullDisk:
    """``connect`` for the Store: once ``full`` is set, every write fails as SQLite fails on a full disk."""

    def __init__(self) -> None:
        self.full = False
        self.refused = 0

    def connect(self, *args, **kwargs) -> "_FullDiskConnection":
        return _FullDiskConnection(sqlite3.connect(*args, **kwargs), self)


class _FullDiskConnection:
    def __init__(self, inner: sqlite3.Connection, disk: FullDisk):
        self.inner, self.disk = inner, disk

    def _check(self, sql: str) -> None:
        if self.disk.full and sql.lstrip().upper().startswith(_WRITES):
            self.disk.refused += 1
            raise sqlite3.OperationalError("database or disk is full")

    def execute(self, sql: str, args=()):
        self._check(sql)
        return self.inner.execute(sql, args)

    def executemany(self, sql: str, rows):
        self._check(sql)
        return self.inner.executemany(sql, rows)

    def executescript(self, script: str):
        return self.inner.executescript(script)

    @property
    def in_transaction(self) -> bool:
        return self.inner.in_transaction

    def close(self) -> None:
        self.inner.close()


class MotionLog:
    """Wraps the cell: which steps had their action plan sent to it; optionally fills the disk mid-motion."""

    def __init__(self, cell, disk: FullDisk):
        self.cell, self.disk = cell, disk
        self.runner: CycleRunner | None = None
        self.moved: set[int] = set()
        self.fill_during_motion = False
        self._execute = cell.execute
        cell.execute = self.execute

    def execute(self, plan):
        if plan.plan.primitive in ACTION_PRIMITIVES:
            self.moved.add(self.runner.step - 1)  # the runner counts a step as soon as it is decided
            if self.fill_during_motion:
                self.disk.full = True
        return self._execute(plan)


def _runner(tmp_path: Path, disk: FullDisk) -> tuple[CycleRunner, MotionLog, Store]:
    cfg = load_config(REPO / "cell_config" / "sim.yaml")
    cfg = dataclasses.replace(cfg, state_dir=str(tmp_path),
                              sim=dataclasses.replace(cfg.sim, objects=6, seed=5),
                              storage=dataclasses.replace(cfg.storage, min_free_bytes=0))
    cell = make_cell(cfg)
    agent = Agent(cfg, build_network(cfg.learning.network, rotations=cfg.learning.rotations, seed=0), seed=0)
    store = Store(tmp_path, connect=disk.connect)
    motions = MotionLog(cell, disk)
    runner = CycleRunner(cfg, cell, agent, store=store)
    motions.runner = runner
    return runner, motions, store


# the disk fills after this phase of the second cycle ("during motion": as the action's plan starts)
PHASES = ("decide", "plan", "during motion", "execute", "capture", "perceive", "judge", "store")


@pytest.mark.parametrize("phase", PHASES)
def test_a_disk_that_fills_at_any_phase_leaves_every_executed_motion_in_the_action_log(tmp_path, phase):
    disk = FullDisk()
    runner, motions, store = _runner(tmp_path, disk)
    armed = {"on": False}

    def on_phase(name: str) -> None:
        if armed["on"] and name == phase:
            disk.full = True

    runner.on_phase = on_phase
    try:
        while runner.step < 1:  # a first cycle with a step, written whole
            runner.run_once()
        armed["on"] = True
        motions.fill_during_motion = phase == "during motion"
        with pytest.raises(StoreError, match="disk is full"):
            for _ in range(4):
                runner.run_once()
        assert disk.refused > 0
    finally:
        runner.cell.close()
        store.close()
    moved_before = set(motions.moved)
    disk.full = False
    log = {r["step"]: r for r in Store(tmp_path).action_log()}  # the next start, with space again
    assert motions.moved == moved_before and motions.moved, "nothing moved after the failed write"
    missing = sorted(motions.moved - set(log))
    assert not missing, f"steps {missing} moved the arm but have no row in the action log"
    unfinished = [s for s, r in log.items() if r["outcome"] == INTERRUPTED_OUTCOME]
    for s in unfinished:
        assert s in motions.moved and "interrupted" in log[s]["failure"]
    for s, r in log.items():
        if r["outcome"] == "executed":
            assert s in motions.moved
    # the failure before the motion leaves no row at all; the one after it leaves the intent, marked
    if phase in ("decide", "plan", "store"):
        assert unfinished == [], "the write that failed came before the motion: nothing moved for it"
    else:
        assert len(unfinished) == 1 and unfinished[0] == max(motions.moved)


def test_an_intent_never_completed_is_interrupted_and_counted_as_no_outcome(tmp_path):
    store = Store(tmp_path)
    store.commit_cycle(action_row(0, success=1), Transition(random_heightmaps(0), Action("grasp", 0, 0, 0), 1.0, random_heightmaps(1), False))
    store.record_intent({"step": 1, "time": time.time(), "backend": "test", "primitive": "grasp", "kind": "grasp",
                         "row": 3, "col": 4, "rotation": 5, "rule": "greedy", "policy": 1})
    assert store.action_log()[-1]["outcome"] == INTENT_OUTCOME
    store.close()  # the process ends here, the motion in flight
    store = Store(tmp_path)
    row = store.action_log()[-1]
    assert (row["step"], row["outcome"], row["primitive"], row["row"], row["policy"]) == \
        (1, INTERRUPTED_OUTCOME, "grasp", 3, 1)
    assert "sent to the cell" in row["failure"]
    stats = compute_stats(store)
    assert stats["cycles"] == 2 and stats["actions_executed"] == 1 and stats["grasp_attempts"] == 1
    assert stats["grasp_success"] == 1.0 and stats["actions_since_pick"] == 0
    assert status_summary(store)["grasp_success_last_50"] == 1.0
    assert INTENT_OUTCOME not in CREDITED_OUTCOMES and INTERRUPTED_OUTCOME not in CREDITED_OUTCOMES
    assert store.next_step() == 2, "the interrupted step is not decided again"


def test_a_completion_after_a_failed_one_marks_the_earlier_intent_interrupted(tmp_path):
    disk = FullDisk()
    store = Store(tmp_path, connect=disk.connect)
    store.record_intent({"step": 0, "time": time.time(), "primitive": "push", "kind": "push"})
    disk.full = True
    with pytest.raises(StoreError):
        store.commit_cycle(action_row(0), Transition(random_heightmaps(0), Action("push", 0, 0, 0), 0.5, random_heightmaps(1), False))
    disk.full = False
    store.forget_last_state()
    store.record_intent({"step": 1, "time": time.time(), "primitive": "grasp", "kind": "grasp"})
    store.commit_cycle(action_row(1), Transition(random_heightmaps(2), Action("grasp", 0, 0, 0), 1.0, random_heightmaps(3), False))
    assert [(r["step"], r["outcome"]) for r in store.action_log()] == [(0, INTERRUPTED_OUTCOME), (1, "executed")]
    assert store.integrity_check() == "ok"


_MOVING = textwrap.dedent("""
    import sys, time
    from flgd.store import Store
    store = Store(sys.argv[1])
    store.record_intent({"step": 0, "time": time.time(), "primitive": "grasp", "kind": "grasp"})
    print("moving", flush=True)
    time.sleep(60)  # the arm is in motion when the kill comes
""")


def test_kill_minus_9_during_the_motion_leaves_the_action_in_the_log(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", _MOVING, str(tmp_path)], stdout=subprocess.PIPE, cwd=REPO)
    try:
        assert proc.stdout.readline().strip() == b"moving"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    store = Store(tmp_path)
    assert [(r["step"], r["outcome"]) for r in store.action_log()] == [(0, INTERRUPTED_OUTCOME)]
    assert store.integrity_check() == "ok"
