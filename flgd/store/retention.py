"""Retention and the disk budget inside the database (the rules are in flgd/disk_budget.py).

Old transitions and the states only they used are deleted when the replay keeps fewer
(``keep_transitions``) or the database grows over ``max_bytes`` (``Store`` decides how many, and keeps
the newest); action-log rows older than ``action_log_days`` are deleted, except the newest and those the
gate's acting policies are tallied from, and what they counted is added to the ``deleted_*`` counters.
Each function runs inside the caller's write transaction.
"""

from __future__ import annotations

import sqlite3
import time

from flgd import disk_budget
from flgd.store.schema import CYCLE_ON_CELL_CLOCK_SQL

# Counters of what the action-log retention deleted (with ``actions_deleted``, the deleted rows): the
# totals in flgd/daemon/metrics.py add them, so a counter never goes down when old rows go.
DELETED_TOTALS = ("deleted_executed", "deleted_refused", "deleted_grasp_attempts", "deleted_grasp_successes",
                  "deleted_push", "deleted_shift", "deleted_cycle_ms")


def evict_through(db: sqlite3.Connection, cutoff: int) -> None:
    """Delete the transitions with id <= ``cutoff`` and the states only they used."""
    last_step = db.execute("SELECT step FROM transitions WHERE id=?", (cutoff,)).fetchone()
    if last_step is None:
        return
    # a transition's action-log row has the same step, so the step bound keeps this a range scan
    db.execute("UPDATE actions SET transition_id=NULL WHERE step <= ? AND transition_id <= ?",
               (last_step[0], cutoff))
    db.execute("DELETE FROM transitions WHERE id <= ?", (cutoff,))
    db.execute("DELETE FROM states WHERE id < (SELECT COALESCE(MIN(state_id), 0) FROM transitions)")


def prune(db: sqlite3.Connection, keep: int) -> None:
    """Keep only the newest ``keep`` transitions (and their states)."""
    row = db.execute("SELECT id FROM transitions ORDER BY id DESC LIMIT 1 OFFSET ?", (keep,)).fetchone()
    if row is not None:
        evict_through(db, row[0])


def used_bytes(db: sqlite3.Connection) -> int:
    """Bytes of the database's pages in use (the file's pages less the free ones)."""
    pages = db.execute("PRAGMA page_count").fetchone()[0]
    free = db.execute("PRAGMA freelist_count").fetchone()[0]
    return int((pages - free) * db.execute("PRAGMA page_size").fetchone()[0])


def retain_action_log(db: sqlite3.Connection, days: float) -> None:
    """Delete action-log rows older than ``days``, except the newest and those the gate tallies."""
    cutoff = disk_budget.action_log_cutoff(time.time(), days)
    if cutoff is None:
        return
    newest = db.execute("SELECT MAX(step) FROM actions").fetchone()[0]
    if newest is None:
        return
    bound = newest
    tallied = db.execute("SELECT MIN(since_step) FROM policies WHERE role IN ('champion', 'challenger')").fetchone()
    if tallied[0] is not None:
        bound = min(bound, int(tallied[0]))
    # what the deleted rows counted is kept, so the totals of flgctl stats and the metrics never go down
    totals = db.execute(
        "SELECT COALESCE(SUM(outcome='executed'), 0), COALESCE(SUM(outcome='refused'), 0), "
        "COALESCE(SUM(outcome='executed' AND primitive='grasp'), 0), "
        "COALESCE(SUM(outcome='executed' AND primitive='grasp' AND success=1), 0), "
        "COALESCE(SUM(outcome='executed' AND primitive!='grasp' AND kind='push'), 0), "
        "COALESCE(SUM(outcome='executed' AND primitive!='grasp' AND kind='shift'), 0), "
        f"COALESCE(SUM({CYCLE_ON_CELL_CLOCK_SQL}), 0) FROM actions WHERE step < ? AND time < ?",
        (bound, cutoff)).fetchone()
    cur = db.execute("DELETE FROM actions WHERE step < ? AND time < ?", (bound, cutoff))
    if cur.rowcount > 0:
        names = ("actions_deleted", *DELETED_TOTALS)
        for name, value in zip(names, (cur.rowcount, *totals[:-1], round(1000.0 * totals[-1]))):
            db.execute("INSERT INTO counters(name, value) VALUES(?, ?) "
                       "ON CONFLICT(name) DO UPDATE SET value=value + excluded.value", (name, int(value)))
