"""The action log's rows and its write-ahead rule (see the package docstring, "Write-ahead action log").

A decided action that will move the cell is inserted with outcome ``pending`` before the motion and
completed in place after it; a row still ``pending`` when a later cycle is written, or when the store is
next opened, becomes ``interrupted``.
"""

from __future__ import annotations

import json
import sqlite3
from typing import Any

import numpy as np

from flgd.store.schema import ACTION_COLUMNS

# the outcome of an action-log row written before the motion (``Store.record_intent``), until it is completed
INTENT_OUTCOME = "pending"
# ... and of one that was never completed: the cell was told to move, what happened was not recorded
INTERRUPTED_OUTCOME = "interrupted"
INTERRUPTED_FAILURE = ("interrupted: the action was sent to the cell, but its outcome was never recorded (the process "
                       "ended or the store failed during the action); look at the cell before trusting its scene")


def mark_interrupted(db: sqlite3.Connection, step: int | None) -> None:
    """Intent rows (``step``, or all when None) that were never completed become ``interrupted``."""
    where, args = ("step=? AND outcome=?", (step, INTENT_OUTCOME)) if step is not None \
        else ("outcome=?", (INTENT_OUTCOME,))
    db.execute(f"UPDATE actions SET outcome=?, failure=CASE WHEN COALESCE(failure, '')='' THEN ? "
               f"ELSE failure || '; ' || ? END WHERE {where}",
               (INTERRUPTED_OUTCOME, INTERRUPTED_FAILURE, INTERRUPTED_FAILURE, *args))


def insert_action(db: sqlite3.Connection, values: dict) -> None:
    cols = [c for c in ACTION_COLUMNS if c in values]
    db.execute(f"INSERT INTO actions({', '.join(cols)}) VALUES({', '.join('?' * len(cols))})",
               [_sql_value(values[c]) for c in cols])


def complete_action(db: sqlite3.Connection, values: dict) -> None:
    """The intent row of ``values['step']`` gets its outcome (a row marked interrupted meanwhile, too)."""
    cols = [c for c in ACTION_COLUMNS if c in values and c != "step"]
    cur = db.execute(f"UPDATE actions SET {', '.join(f'{c}=?' for c in cols)} WHERE step=? AND outcome IN (?, ?)",
                     [*(_sql_value(values[c]) for c in cols), int(values["step"]), INTENT_OUTCOME,
                      INTERRUPTED_OUTCOME])
    if cur.rowcount == 0:  # the intent row is gone (deleted by hand): the outcome is still recorded
        insert_action(db, values)


def _sql_value(v: Any) -> Any:
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(v)
    return v
