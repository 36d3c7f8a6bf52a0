"""The store-derived metrics behind ``flgd run --metrics``: phase histograms read incrementally, faults by kind."""

from __future__ import annotations

import sqlite3

from flgd.daemon.metrics import FAULT_KINDS, PhaseHistograms, fault_counts
from flgd.store import TIMING_PHASES


class _Log:
    """The two tables the metrics read, with Store's ``query``."""

    def __init__(self):
        self.db = sqlite3.connect(":memory:")
        cols = ", ".join(f"t_{p} REAL" for p in TIMING_PHASES)
        self.db.execute(f"CREATE TABLE actions(step INTEGER PRIMARY KEY, duration REAL, {cols})")
        self.db.execute("CREATE TABLE events(id INTEGER PRIMARY KEY, kind TEXT, message TEXT)")

    def query(self, sql: str, args: tuple = ()) -> list[tuple]:
        return self.db.execute(sql, args).fetchall()

    def cycle(self, step: int, seconds: float, store: float | None = None) -> None:
        phases = [seconds / 10] * len(TIMING_PHASES)
        phases[TIMING_PHASES.index("store")] = store
        self.db.execute(f"INSERT INTO actions VALUES (?, ?, {', '.join('?' * len(TIMING_PHASES))})",
                        (step, seconds, *phases))


def test_histograms_count_every_finished_cycle_once_across_reads():
    log, h = _Log(), PhaseHistograms(buckets=(1.0, 5.0))
    for step, seconds in enumerate((0.5, 2.0, 7.0)):
        log.cycle(step, seconds, store=0.01)
    first = h.read(log)
    assert first["cycle"] == ([1, 2], 2.5, 2)  # the newest row waits: its store time is written later
    log.cycle(3, 0.2)
    second = h.read(log)
    assert second["cycle"] == ([1, 2], 9.5, 3)  # step 2 now counted, once
    assert h.read(log) == second  # nothing new: nothing counted twice
    assert second["store"][2] == 3 and second["capture"][2] == 3


def test_histograms_of_an_empty_log_are_empty():
    assert PhaseHistograms().read(_Log())["cycle"] == ([0] * 13, 0.0, 0)


def test_faults_are_counted_by_kind_with_every_kind_present():
    log = _Log()
    for message in ("cell fault: protective stop", "cell fault during snapshot capture: no frame",
                    "store /var/lib/flgd/flgd.db: the disk is full (OperationalError: ...)",
                    "checkpoint failed: store ...: the disk is full", "something new"):
        log.db.execute("INSERT INTO events(kind, message) VALUES ('fault', ?)", (message,))
    log.db.execute("INSERT INTO events(kind, message) VALUES ('state', 'cell fault: not a fault event')")
    counts = fault_counts(log)
    assert counts == {"cell": 2, "storage": 1, "learning": 1, "reset": 0, "internal": 0, "other": 1}
    assert set(counts) == {k for _, k in FAULT_KINDS} | {"other"}
