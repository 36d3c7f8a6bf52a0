"""The store's tables (``SCHEMA_VERSION`` 5), and the in-place upgrade of a version-1 to -4 store.

The tables and their columns are described in the package docstring (flgd/store/__init__.py).  An
upgrade adds the missing action-log columns (``contact_stop_mm``, ``policy``, ``cell_time``,
``gripper_time``, ``decide_hidden``), empty for the old rows,
in one transaction, and changes nothing else.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from flgd.store.errors import StoreError

SCHEMA_VERSION = 5
DB_NAME = "flgd.sqlite"
TIMING_PHASES = ("capture", "perceive", "decide", "plan", "execute", "judge", "store")

ACTION_COLUMNS = (
    "step", "time", "backend", "outcome", "primitive", "kind", "row", "col", "rotation", "reward",
    "success", "mu", "eta", "rule", "epsilon", "q_value", "refused", "failure", "contact_stop_mm", "done",
    "duration",
    *(f"t_{p}" for p in TIMING_PHASES), "transition_id", "policy", "cell_time",
    "gripper_time", "decide_hidden",
)

# A cycle as the arm lives it (s): the controller's own work on the wall clock plus its plans on the cell's clock;
# a row without ``cell_time`` (logged before it existed, or a fault) counts its wall time, and a row still without
# a duration (an intent, or one interrupted) counts nothing.  Picks per hour are counted on it.
CYCLE_ON_CELL_CLOCK_SQL = ("CASE WHEN cell_time IS NULL OR COALESCE(duration, 0) = 0 THEN COALESCE(duration, 0) "
                           "ELSE duration - COALESCE(t_execute, 0) + cell_time END")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS states(
    id INTEGER PRIMARY KEY, rows INTEGER NOT NULL, cols INTEGER NOT NULL,
    color BLOB NOT NULL, height BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS transitions(
    id INTEGER PRIMARY KEY, step INTEGER NOT NULL,
    state_id INTEGER NOT NULL REFERENCES states(id),
    next_state_id INTEGER REFERENCES states(id),
    primitive TEXT NOT NULL, row INTEGER NOT NULL, col INTEGER NOT NULL,
    rotation INTEGER NOT NULL, rotations INTEGER NOT NULL,
    reward REAL NOT NULL, done INTEGER NOT NULL, priority REAL);
CREATE TABLE IF NOT EXISTS actions(
    step INTEGER PRIMARY KEY, time REAL NOT NULL, backend TEXT, outcome TEXT NOT NULL,
    primitive TEXT, kind TEXT, row INTEGER, col INTEGER, rotation INTEGER, reward REAL,
    success INTEGER, mu INTEGER, eta INTEGER, rule TEXT, epsilon REAL, q_value REAL,
    refused TEXT, failure TEXT, contact_stop_mm REAL, done INTEGER, duration REAL,
    t_capture REAL, t_perceive REAL, t_decide REAL, t_plan REAL, t_execute REAL,
    t_judge REAL, t_store REAL, transition_id INTEGER REFERENCES transitions(id), policy INTEGER,
    cell_time REAL, gripper_time REAL, decide_hidden REAL);
CREATE TABLE IF NOT EXISTS events(id INTEGER PRIMARY KEY, time REAL NOT NULL,
    kind TEXT NOT NULL, message TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS counters(name TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE INDEX IF NOT EXISTS actions_outcome ON actions(outcome, primitive);
CREATE TABLE IF NOT EXISTS policies(id INTEGER PRIMARY KEY, created REAL NOT NULL, role TEXT NOT NULL,
    file TEXT NOT NULL, sha256 TEXT NOT NULL, origin TEXT NOT NULL, predecessor INTEGER REFERENCES policies(id),
    learner_updates INTEGER, training_steps INTEGER NOT NULL, since_step INTEGER NOT NULL,
    record TEXT);
CREATE TABLE IF NOT EXISTS gate_events(id INTEGER PRIMARY KEY, time REAL NOT NULL, step INTEGER,
    kind TEXT NOT NULL, policy INTEGER, other INTEGER, who TEXT NOT NULL, message TEXT NOT NULL,
    evidence TEXT NOT NULL);
"""
# after any upgrade: the column it indexes is new in version 3
_INDEXES = "CREATE INDEX IF NOT EXISTS actions_policy ON actions(policy, step);"


def create_or_upgrade(db: sqlite3.Connection, path: Path) -> None:
    """Create the tables of a new store, upgrade an older one, refuse an unknown version."""
    db.executescript(_SCHEMA)
    row = db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
    if row is None:
        db.execute("INSERT INTO meta(key, value) VALUES('schema_version', ?)",
                   (str(SCHEMA_VERSION),))
    elif row[0] in ("1", "2", "3", "4"):
        _upgrade(db)
    elif row[0] != str(SCHEMA_VERSION):
        raise StoreError(f"store {path}: schema version {row[0]} is not the supported "
                         f"version {SCHEMA_VERSION}; use a new state directory")
    db.executescript(_INDEXES)


def _upgrade(db: sqlite3.Connection) -> None:
    """Version 1 -> 2: the action log gains ``contact_stop_mm``; 2 -> 3: it gains ``policy`` (the gate's
    policy that acted; the gate's tables are created by the schema script); 3 -> 4: it gains ``cell_time`` and ``gripper_time``;
    4 -> 5: ``decide_hidden``.
    One transaction, nothing else touched."""
    db.execute("BEGIN IMMEDIATE")
    try:
        columns = {r[1] for r in db.execute("PRAGMA table_info(actions)")}
        for name, kind in (("contact_stop_mm", "REAL"), ("policy", "INTEGER"), ("cell_time", "REAL"),
                           ("gripper_time", "REAL"), ("decide_hidden", "REAL")):
            if name not in columns:
                db.execute(f"ALTER TABLE actions ADD COLUMN {name} {kind}")
        db.execute("UPDATE meta SET value=? WHERE key='schema_version'", (str(SCHEMA_VERSION),))
        db.execute("COMMIT")
    except BaseException:
        if db.in_transaction:
            db.execute("ROLLBACK")
        raise
