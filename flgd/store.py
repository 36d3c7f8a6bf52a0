"""Persistence of what the cell has experienced: replay transitions, the action log, checkpoints.

Why SQLite in WAL mode: a cycle's outcome is written as one transaction (the
action-log row, the transition and any new heightmap), so a process killed at
any instant leaves either the whole outcome or none of it, and readers
(``flgctl stats``) never block the writer; a cycle that moves the cell first
commits its intent (below).  ``synchronous=FULL``: a commit is on disk when it
returns (one fsync of the WAL per commit, two per cycle that moves, small next
to a cycle's controller time, BENCHMARKS.md "Controller overhead"), so a power
cut loses at most the outcome of the cycle in flight, as a killed process does;
with NORMAL it could also lose the last few committed cycles.

Schema (``SCHEMA_VERSION`` 3), file ``<state_dir>/flgd.sqlite``:

* ``states(id, rows, cols, color, height)`` -- one heightmap pair per row,
  zlib-compressed; colour HxWx3 uint8, height as uint16 in units of
  ``HEIGHT_QUANTUM`` (0.1 mm).  Each state is stored once: the next state of a
  transition is the state of the following one.
* ``transitions(id, step, state_id, next_state_id, primitive, row, col,
  rotation, rotations, reward, done, priority)`` -- the replay buffer.
* ``actions(step PRIMARY KEY, time, backend, outcome, primitive, kind, row,
  col, rotation, reward, success, mu, eta, rule, epsilon, q_value, refused,
  failure, contact_stop_mm, done, duration, t_capture, t_perceive, t_decide, t_plan, t_execute,
  t_judge, t_store, transition_id, policy)`` -- one row per cycle, whatever happened;
  ``policy`` is the gate's id of the policy whose greedy decision it was (NULL for an
  epsilon-random action or before the gate).
  ``t_store`` of a row is written with the next write of a cycle (its intent or
  its commit: a commit cannot time itself).
* ``events(id, time, kind, message)`` -- state changes, faults, policy loads.
* ``counters(name PRIMARY KEY, value)`` -- e.g. learner updates.
* ``meta(key PRIMARY KEY, value)`` -- schema version.
* ``policies(id, created, role, file, sha256, origin, predecessor, learner_updates,
  training_steps, since_step, record)`` and ``gate_events(id, time, step, kind, policy,
  other, who, message, evidence)`` -- the champion/challenger gate's policies (files in
  ``<state_dir>/gate``) and every promotion, drop, rollback and manual override
  (flgd/gatekeeper.py).

A version-1 or -2 store is upgraded in place when it is opened: the missing columns
(``contact_stop_mm``, ``policy``) are added (empty for the old rows) and nothing else changes.

Write-ahead action log: a decided action that will move the cell is recorded
(``record_intent``: its row with outcome ``pending`` -- step, time, action,
plan kind, rule, policy) in its own transaction *before* the cell is told to
move, and completed (``commit_cycle``: outcome, reward, transition) after.  So a
``kill -9``, a power cut or a full disk at any instant leaves every motion in
the log: a row still ``pending`` when the store is next opened, or when a later
cycle is written, becomes ``interrupted`` (its ``failure`` says so).  Neither
outcome is ``executed`` or ``refused``, so stats and the gate's tallies never
count such a row as an outcome; ``flgctl stats`` shows it under "other".

Retention and the disk budget (flgd/disk_budget.py):

* ``keep_transitions`` (the daemon passes the replay capacity): only the newest
  transitions and their states are kept.
* ``max_bytes`` (``storage.max_bytes``): the database and its write-ahead log
  stay under it; above it the oldest transitions and their states are deleted
  first (the newest one is always kept), and the write-ahead log is truncated
  after each checkpoint to fit.  The file keeps its largest size: freed pages
  are reused, not returned to the filesystem.
* ``action_log_days`` (``storage.action_log_days``, 0 = forever): older
  action-log rows are deleted, except the newest row (the step counter is
  ``max(step) + 1``) and the rows the gate's acting policies are tallied from
  (``policies.since_step`` of the champion and challenger).  Each deleted row is
  counted in the ``actions_deleted`` counter.  Events and counters are kept whole.
* ``min_free_bytes`` (``storage.min_free_bytes``): ``check_space`` raises a
  StoreError naming the directory, the free bytes and the floor when the
  filesystem has less, is read-only, or the directory is not writable; the
  cycle calls it before any motion.

The first storage failure is kept as the diagnosis until a write succeeds
again: SQLite reports later failures of the same broken disk differently (after
an I/O error, "database disk image is malformed" although the file is intact),
so those are appended to the first cause instead of replacing it.

The step counter is not stored separately: it is ``max(actions.step) + 1``, so
it can never disagree with the log.

Policy checkpoints are files in ``<state_dir>/checkpoints`` written atomically
by ``flgd.learning.policy_file.save_policy``; the last ``keep`` are kept.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import re
import sqlite3
import threading
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from flgd import disk_budget
from flgd.actions import Action
from flgd.perception import Heightmaps

__all__ = [
    "SCHEMA_VERSION",
    "HEIGHT_QUANTUM",
    "StoreError",
    "StoredTransition",
    "Store",
    "CheckpointDir",
    "ACTION_COLUMNS",
    "TIMING_PHASES",
    "INTENT_OUTCOME",
    "INTERRUPTED_OUTCOME",
]

log = logging.getLogger("flgd")

# Counters of what the action-log retention deleted (with ``actions_deleted``, the deleted rows): the
# totals in flgd/daemon/metrics.py add them, so a counter never goes down when old rows go.
DELETED_TOTALS = ("deleted_executed", "deleted_refused", "deleted_grasp_attempts", "deleted_grasp_successes",
                  "deleted_push", "deleted_shift", "deleted_cycle_ms")

SCHEMA_VERSION = 3
HEIGHT_QUANTUM = 1e-4  # metres per stored height unit
DB_NAME = "flgd.sqlite"
TIMING_PHASES = ("capture", "perceive", "decide", "plan", "execute", "judge", "store")
# the outcome of an action-log row written before the motion (``Store.record_intent``), until it is completed
INTENT_OUTCOME = "pending"
# ... and of one that was never completed: the cell was told to move, what happened was not recorded
INTERRUPTED_OUTCOME = "interrupted"
INTERRUPTED_FAILURE = ("interrupted: the action was sent to the cell, but its outcome was never recorded (the process "
                       "ended or the store failed during the action); look at the cell before trusting its scene")

ACTION_COLUMNS = (
    "step", "time", "backend", "outcome", "primitive", "kind", "row", "col", "rotation", "reward",
    "success", "mu", "eta", "rule", "epsilon", "q_value", "refused", "failure", "contact_stop_mm", "done",
    "duration",
    *(f"t_{p}" for p in TIMING_PHASES), "transition_id", "policy",
)

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
    t_judge REAL, t_store REAL, transition_id INTEGER REFERENCES transitions(id), policy INTEGER);
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


class StoreError(RuntimeError):
    """The store cannot be read or written; the message names the path and the likely cause."""


@dataclass(frozen=True)
class StoredTransition:
    """A transition as read back from the store (converted to the replay's type by the caller)."""

    id: int
    step: int
    state: Heightmaps
    action: Action
    reward: float
    next_state: Heightmaps | None
    done: bool
    priority: float | None


def _directory_problem(path: Path) -> str | None:
    """What is wrong with the filesystem holding ``path``, if we can tell (read-only, full, no access)."""
    d = path if path.is_dir() else path.parent
    while not d.exists() and d != d.parent:
        d = d.parent
    try:
        st = os.statvfs(d)
    except OSError:
        return None
    if st.f_flag & os.ST_RDONLY:
        return f"the state directory is on a read-only filesystem ({d})"
    if not os.access(d, os.W_OK):
        return f"the state directory is read-only for this user ({d})"
    if st.f_bavail == 0 or st.f_favail == 0:
        return f"the disk is full ({d})"
    return None


def _generic_cause(sqlite_name: str, code: int | None) -> str:
    if sqlite_name.startswith("SQLITE_READONLY") or code in (errno.EROFS, errno.EACCES, errno.EPERM):
        return "the state directory is read-only or not writable by this user"
    if sqlite_name.startswith("SQLITE_CANTOPEN"):
        return "the database file cannot be opened (missing directory or no permission)"
    if code == errno.EFBIG or sqlite_name.startswith("SQLITE_IOERR"):
        return "a write failed (disk full, file size limit or I/O error)"
    return "an unexpected storage error"


def _explain(exc: BaseException, path: Path) -> str:
    """A sentence a cell operator can act on, from an sqlite3 or OS error."""
    name = getattr(exc, "sqlite_errorname", "") or ""
    code = getattr(exc, "errno", None)
    text = str(exc)
    if name.startswith("SQLITE_FULL") or code == errno.ENOSPC or "disk is full" in text:
        why = "the disk is full"
    elif name.startswith("SQLITE_CORRUPT") or name.startswith("SQLITE_NOTADB"):
        why = "the database file is damaged"
    elif name.startswith("SQLITE_CONSTRAINT"):
        why = "a write broke a database constraint"
    else:
        why = _directory_problem(path) or _generic_cause(name, code)
    return f"store {path}: {why} ({type(exc).__name__}: {text})"


def encode_heightmaps(hm: Heightmaps) -> tuple[int, int, bytes, bytes]:
    color = np.ascontiguousarray(hm.color, dtype=np.uint8)
    height = np.asarray(hm.height, dtype=np.float32)
    rows, cols = height.shape
    if color.shape != (rows, cols, 3):
        raise ValueError(f"heightmaps: colour {color.shape} does not match height {height.shape}")
    q = np.clip(np.nan_to_num(height, nan=0.0) / HEIGHT_QUANTUM, 0, np.iinfo(np.uint16).max)
    q = np.rint(q).astype("<u2")
    return rows, cols, zlib.compress(color.tobytes(), 1), zlib.compress(q.tobytes(), 1)


def decode_heightmaps(rows: int, cols: int, color: bytes, height: bytes) -> Heightmaps:
    c = np.frombuffer(zlib.decompress(color), dtype=np.uint8).reshape(rows, cols, 3).copy()
    h = np.frombuffer(zlib.decompress(height), dtype="<u2").reshape(rows, cols)
    return Heightmaps(color=c, height=(h.astype(np.float32) * np.float32(HEIGHT_QUANTUM)))


class Store:
    """The SQLite store of one state directory.  Thread-safe (one connection behind a lock).

    ``keep_transitions``: when set, transitions older than the newest N (the
    replay capacity) and the states only they used are deleted every
    ``PRUNE_EVERY`` commits (the action log's ``transition_id`` becomes NULL).
    ``max_bytes``, ``action_log_days`` and ``min_free_bytes``: the disk budget,
    the action log's retention and the free-space floor (module docstring).
    ``connect``: how the database is opened (``sqlite3.connect``; tests inject
    a connection that fails like a full disk).
    """

    PRUNE_EVERY = 64
    RETAIN_EVERY = 1024  # commits between two action-log retention passes (one scan of the old rows)

    def __init__(self, state_dir: str | os.PathLike, keep_transitions: int | None = None, *,
                 max_bytes: int | None = None, action_log_days: float = 0.0, min_free_bytes: int = 0,
                 connect: Callable[..., sqlite3.Connection] = sqlite3.connect):
        if keep_transitions is not None and keep_transitions < 1:
            raise ValueError(f"Store.keep_transitions: got {keep_transitions!r}, expected >= 1 or None")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"Store.max_bytes: got {max_bytes!r}, expected >= 1 or None")
        if action_log_days < 0 or min_free_bytes < 0:
            raise ValueError(f"Store: got action_log_days {action_log_days!r}, min_free_bytes {min_free_bytes!r}, "
                             "expected >= 0")
        self.keep_transitions = keep_transitions
        self.max_bytes = max_bytes
        self.action_log_days = float(action_log_days)
        self.min_free_bytes = int(min_free_bytes)
        self._commits = 0
        self.state_dir = Path(state_dir)
        self.path = self.state_dir / DB_NAME
        self._lock = threading.RLock()
        self._last_state: tuple[Any, int] | None = None
        self._pending_store_time: tuple[int, float] | None = None
        self._open_intent: int | None = None  # the step recorded by record_intent and not completed yet
        self._state_bytes = 0  # encoded size of the newest stored state: what evicting one transition frees
        self._first_failure = ""  # the diagnosis of the first failure since the last successful write
        self.budget_problem = ""  # the action log and other records alone fill max_bytes (nothing left to evict)
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            self._db = connect(self.path, timeout=10.0, isolation_level=None, check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            mode = self._db.execute("PRAGMA journal_mode").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StoreError(f"store {self.path}: could not switch to WAL mode (got {mode!r})")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            # a pruned state's pages are reused, not overwritten with zeros first (some builds do that by
            # default): nothing in the store is secret, and the zeros would double the I/O of every eviction
            self._db.execute("PRAGMA secure_delete=FAST")
            if max_bytes is not None:
                # the write-ahead log stays within its reserve of the budget (disk_budget.database_limit)
                self._db.execute(f"PRAGMA wal_autocheckpoint={disk_budget.wal_autocheckpoint_pages(max_bytes)}")
                self._db.execute(f"PRAGMA journal_size_limit={disk_budget.wal_log_limit(max_bytes)}")
            self._db.executescript(_SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
            if row is None:
                self._db.execute("INSERT INTO meta(key, value) VALUES('schema_version', ?)",
                                 (str(SCHEMA_VERSION),))
            elif row[0] in ("1", "2"):
                self._upgrade(int(row[0]))
            elif row[0] != str(SCHEMA_VERSION):
                raise StoreError(f"store {self.path}: schema version {row[0]} is not the supported "
                                 f"version {SCHEMA_VERSION}; use a new state directory")
            self._db.executescript(_INDEXES)
            if self._db.execute("SELECT 1 FROM actions WHERE outcome=? LIMIT 1", (INTENT_OUTCOME,)).fetchone():
                self._write(lambda db: self._mark_interrupted(db, None))
            if self.action_log_days > 0:
                self._write(self._retain_action_log)
        except StoreError:
            raise
        except (sqlite3.Error, OSError) as exc:
            raise StoreError(_explain(exc, self.path)) from exc

    # ------------------------------------------------------------------ internals
    def _upgrade(self, version: int) -> None:
        """Version 1 -> 2: the action log gains ``contact_stop_mm``; 2 -> 3: it gains ``policy`` (the gate's
        policy that acted; the gate's tables are created by the schema script).  One transaction, nothing else
        touched."""
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            columns = {r[1] for r in db.execute("PRAGMA table_info(actions)")}
            for name, kind in (("contact_stop_mm", "REAL"), ("policy", "INTEGER")):
                if name not in columns:
                    db.execute(f"ALTER TABLE actions ADD COLUMN {name} {kind}")
            db.execute("UPDATE meta SET value=? WHERE key='schema_version'", (str(SCHEMA_VERSION),))
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise

    def _write(self, fn: Callable[[sqlite3.Connection], Any]) -> Any:
        """Run ``fn`` in one write transaction; map storage failures to StoreError."""
        with self._lock:
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    out = fn(self._db)
                    self._db.execute("COMMIT")
                except BaseException:
                    if self._db.in_transaction:
                        try:
                            self._db.execute("ROLLBACK")
                        except sqlite3.Error:
                            pass  # the failure that got us here is the one to report
                    raise
                self._first_failure = ""
                return out
            except (sqlite3.Error, OSError) as exc:
                self._last_state = None
                raise StoreError(self._diagnose(exc)) from exc

    def _read(self, sql: str, args: tuple = ()) -> list[tuple]:
        with self._lock:
            try:
                return self._db.execute(sql, args).fetchall()
            except (sqlite3.Error, OSError) as exc:
                raise StoreError(self._diagnose(exc)) from exc

    def _diagnose(self, exc: BaseException) -> str:
        """The operator's sentence for ``exc``; the first storage failure stays the cause until a write succeeds.

        Why: a disk that failed once keeps failing, and SQLite's later words for it mislead (after an I/O
        error it reports "database disk image is malformed" for a file that is intact).  A broken constraint
        is a bug, not the disk, and is reported on its own.
        """
        why = _explain(exc, self.path)
        if isinstance(exc, sqlite3.IntegrityError):
            return why
        if self._first_failure:
            return f"{self._first_failure} (still failing since: {type(exc).__name__}: {exc})"
        self._first_failure = why
        return why

    def _state_id(self, db: sqlite3.Connection, hm: Heightmaps) -> int:
        if self._last_state is not None and self._last_state[0] is hm:
            return self._last_state[1]
        encoded = encode_heightmaps(hm)
        self._state_bytes = len(encoded[2]) + len(encoded[3])
        cur = db.execute("INSERT INTO states(rows, cols, color, height) VALUES(?,?,?,?)", encoded)
        return int(cur.lastrowid)

    @staticmethod
    def _mark_interrupted(db: sqlite3.Connection, step: int | None) -> None:
        """Intent rows (``step``, or all when None) that were never completed become ``interrupted``."""
        where, args = ("step=? AND outcome=?", (step, INTENT_OUTCOME)) if step is not None \
            else ("outcome=?", (INTENT_OUTCOME,))
        db.execute(f"UPDATE actions SET outcome=?, failure=CASE WHEN COALESCE(failure, '')='' THEN ? "
                   f"ELSE failure || '; ' || ? END WHERE {where}",
                   (INTERRUPTED_OUTCOME, INTERRUPTED_FAILURE, INTERRUPTED_FAILURE, *args))

    def _insert_action(self, db: sqlite3.Connection, values: dict) -> None:
        cols = [c for c in ACTION_COLUMNS if c in values]
        db.execute(f"INSERT INTO actions({', '.join(cols)}) VALUES({', '.join('?' * len(cols))})",
                   [_sql_value(values[c]) for c in cols])

    # ------------------------------------------------------------------ writing
    def record_intent(self, row: dict) -> None:
        """Write-ahead: commit the decided action's row, outcome ``pending``, before the cell is told to move.

        ``row`` is the cycle's action-log row as far as it is known (step, time, action, plan kind, rule,
        policy, timings); ``commit_cycle`` of the same step completes it.  An earlier intent that was never
        completed (its completion failed) becomes ``interrupted`` in the same transaction.  Raises
        StoreError when it cannot be written: then nothing may move.
        """
        unknown = set(row) - set(ACTION_COLUMNS)
        if unknown:
            raise ValueError(f"record_intent: unknown action-log columns {sorted(unknown)}")
        pending = self._pending_store_time
        earlier = self._open_intent
        step = int(row["step"])

        def write(db: sqlite3.Connection) -> None:
            if earlier is not None:
                self._mark_interrupted(db, earlier)
            self._insert_action(db, dict(row, outcome=INTENT_OUTCOME))
            if pending is not None:
                db.execute("UPDATE actions SET t_store=? WHERE step=?", (pending[1], pending[0]))

        self._write(write)
        self._pending_store_time = None
        self._open_intent = step

    def commit_cycle(self, row: dict, transition: Any | None = None,
                     priority: float | None = None) -> int | None:
        """Write one cycle: its action-log ``row`` and, if any, its transition.

        ``transition`` has ``state``, ``action``, ``reward``, ``next_state`` and
        ``done``.  A state that is the very object stored as the previous
        transition's next state is not stored again.  A row whose intent was
        recorded (``record_intent``) is completed in place.  Returns the transition id.
        """
        unknown = set(row) - set(ACTION_COLUMNS)
        if unknown:
            raise ValueError(f"commit_cycle: unknown action-log columns {sorted(unknown)}")
        pending = self._pending_store_time
        intent = self._open_intent

        def write(db: sqlite3.Connection) -> int | None:
            tid = None
            new_last = None
            if transition is not None:
                sid = self._state_id(db, transition.state)
                nid = None
                if transition.next_state is not None:
                    nid = self._state_id(db, transition.next_state) \
                        if transition.next_state is not transition.state else sid
                    new_last = (transition.next_state, nid)
                a = transition.action
                cur = db.execute(
                    "INSERT INTO transitions(step, state_id, next_state_id, primitive, row, col, rotation, "
                    "rotations, reward, done, priority) VALUES(?,?,?,?,?,?,?,?,?,?,?)",
                    (int(row["step"]), sid, nid, a.primitive, int(a.row), int(a.col), int(a.rotation),
                     int(a.rotations), float(transition.reward), int(bool(transition.done)),
                     None if priority is None else float(priority)))
                tid = int(cur.lastrowid)
            values = dict(row, transition_id=tid)
            step = int(values["step"])
            if intent is not None and intent != step:
                self._mark_interrupted(db, intent)
            if intent == step:
                self._complete_action(db, values)
            else:
                self._insert_action(db, values)
            if pending is not None:
                db.execute("UPDATE actions SET t_store=? WHERE step=?", (pending[1], pending[0]))
            if self.keep_transitions is not None and (self._commits + 1) % self.PRUNE_EVERY == 0:
                self._prune(db, self.keep_transitions)
            if self.max_bytes is not None and transition is not None:
                self._evict_to_budget(db)
            if self.action_log_days > 0 and (self._commits + 1) % self.RETAIN_EVERY == 0:
                self._retain_action_log(db)
            self._last_state = new_last
            return tid

        out = self._write(write)
        self._pending_store_time = None
        self._open_intent = None
        self._commits += 1
        return out

    def _complete_action(self, db: sqlite3.Connection, values: dict) -> None:
        """The intent row of ``values['step']`` gets its outcome (a row marked interrupted meanwhile, too)."""
        cols = [c for c in ACTION_COLUMNS if c in values and c != "step"]
        cur = db.execute(f"UPDATE actions SET {', '.join(f'{c}=?' for c in cols)} WHERE step=? AND outcome IN (?, ?)",
                         [*(_sql_value(values[c]) for c in cols), int(values["step"]), INTENT_OUTCOME,
                          INTERRUPTED_OUTCOME])
        if cur.rowcount == 0:  # the intent row is gone (deleted by hand): the outcome is still recorded
            self._insert_action(db, values)

    @staticmethod
    def _evict_through(db: sqlite3.Connection, cutoff: int) -> None:
        """Delete the transitions with id <= ``cutoff`` and the states only they used."""
        last_step = db.execute("SELECT step FROM transitions WHERE id=?", (cutoff,)).fetchone()
        if last_step is None:
            return
        # a transition's action-log row has the same step, so the step bound keeps this a range scan
        db.execute("UPDATE actions SET transition_id=NULL WHERE step <= ? AND transition_id <= ?",
                   (last_step[0], cutoff))
        db.execute("DELETE FROM transitions WHERE id <= ?", (cutoff,))
        db.execute("DELETE FROM states WHERE id < (SELECT COALESCE(MIN(state_id), 0) FROM transitions)")

    @classmethod
    def _prune(cls, db: sqlite3.Connection, keep: int) -> None:
        row = db.execute("SELECT id FROM transitions ORDER BY id DESC LIMIT 1 OFFSET ?", (keep,)).fetchone()
        if row is not None:
            cls._evict_through(db, row[0])

    def prune(self, keep: int) -> None:
        """Keep only the newest ``keep`` transitions (and their states) now."""
        self._write(lambda db: self._prune(db, keep))

    @staticmethod
    def _used_bytes(db: sqlite3.Connection) -> int:
        """Bytes of the database's pages in use (the file's pages less the free ones)."""
        pages = db.execute("PRAGMA page_count").fetchone()[0]
        free = db.execute("PRAGMA freelist_count").fetchone()[0]
        return int((pages - free) * db.execute("PRAGMA page_size").fetchone()[0])

    def _evict_to_budget(self, db: sqlite3.Connection) -> None:
        """Over ``max_bytes``: delete the oldest transitions and their states, never the newest one."""
        limit = disk_budget.database_limit(self.max_bytes)
        for _ in range(16):  # each round frees about what it estimated; a few rounds at most
            used = self._used_bytes(db)
            k = disk_budget.transitions_to_evict(used, limit, self._state_bytes)
            if k == 0:
                self.budget_problem = ""
                return
            newest = db.execute("SELECT COALESCE(MAX(id), 0) FROM transitions").fetchone()[0]
            row = db.execute("SELECT id FROM transitions WHERE id < ? ORDER BY id LIMIT 1 OFFSET ?",
                             (newest, k - 1)).fetchone()
            if row is None:  # fewer than k older ones: all but the newest go
                row = db.execute("SELECT MAX(id) FROM transitions WHERE id < ?", (newest,)).fetchone()
            if row is None or row[0] is None:
                if not self.budget_problem:
                    self.budget_problem = (
                        f"store {self.path}: {disk_budget.format_bytes(used)} in use with no replay left to evict, "
                        f"over storage.max_bytes {disk_budget.format_bytes(self.max_bytes)}: the action log and "
                        "the other records fill the budget; lower storage.action_log_days or raise storage.max_bytes")
                    log.warning("%s", self.budget_problem)
                    db.execute("INSERT INTO events(time, kind, message) VALUES(?, 'storage_budget', ?)",
                               (time.time(), self.budget_problem))
                return
            self._evict_through(db, row[0])

    def _retain_action_log(self, db: sqlite3.Connection) -> None:
        """Delete action-log rows older than ``action_log_days``, except the newest and those the gate tallies."""
        cutoff = disk_budget.action_log_cutoff(time.time(), self.action_log_days)
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
            "COALESCE(SUM(duration), 0) FROM actions WHERE step < ? AND time < ?", (bound, cutoff)).fetchone()
        cur = db.execute("DELETE FROM actions WHERE step < ? AND time < ?", (bound, cutoff))
        if cur.rowcount > 0:
            names = ("actions_deleted", *DELETED_TOTALS)
            for name, value in zip(names, (cur.rowcount, *totals[:-1], round(1000.0 * totals[-1]))):
                db.execute("INSERT INTO counters(name, value) VALUES(?, ?) "
                           "ON CONFLICT(name) DO UPDATE SET value=value + excluded.value", (name, int(value)))

    def retain_action_log(self) -> None:
        """Apply ``action_log_days`` now (it also runs when the store opens and every ``RETAIN_EVERY`` commits)."""
        self._write(self._retain_action_log)

    # ------------------------------------------------------------------ the disk
    def space_problem(self) -> str:
        """What keeps the state directory from taking the next writes ('' = nothing; flgd/disk_budget.py)."""
        return disk_budget.space_problem(self.state_dir, self.min_free_bytes)

    def check_space(self) -> None:
        """Raise StoreError, naming the directory, the numbers and what to do, unless a motion may start."""
        problem = self.space_problem()
        if problem:
            raise StoreError(f"store {self.path}: {problem}")

    def file_bytes(self) -> int:
        """Bytes of the store's files on disk: the database, its write-ahead log and the log's index."""
        total = 0
        for suffix in ("", "-wal", "-shm"):
            try:
                total += os.stat(f"{self.path}{suffix}").st_size
            except FileNotFoundError:
                pass
            except OSError as exc:
                raise StoreError(self._diagnose(exc)) from exc
        return total

    def note_store_time(self, step: int, seconds: float) -> None:
        """The measured store time of ``step``; written with the next commit."""
        self._pending_store_time = (int(step), float(seconds))

    def forget_last_state(self) -> None:
        """The next transition starts from a fresh capture (after a reset or a discarded action)."""
        self._last_state = None

    def record_event(self, kind: str, message: str) -> None:
        self._write(lambda db: db.execute("INSERT INTO events(time, kind, message) VALUES(?,?,?)",
                                          (time.time(), kind, message)))

    def set_counter(self, name: str, value: int) -> None:
        self._write(lambda db: db.execute(
            "INSERT INTO counters(name, value) VALUES(?, ?) "
            "ON CONFLICT(name) DO UPDATE SET value=excluded.value", (name, int(value))))

    # ------------------------------------------------------------------ reading
    def counter(self, name: str, default: int = 0) -> int:
        rows = self._read("SELECT value FROM counters WHERE name=?", (name,))
        return int(rows[0][0]) if rows else default

    def next_step(self) -> int:
        return int(self._read("SELECT COALESCE(MAX(step) + 1, 0) FROM actions")[0][0])

    def transition_count(self) -> int:
        return int(self._read("SELECT COUNT(*) FROM transitions")[0][0])

    def state_count(self) -> int:
        return int(self._read("SELECT COUNT(*) FROM states")[0][0])

    def save_priorities(self, pairs: list[tuple[int, float]]) -> None:
        """Write the replay priorities the learner set ((transition id, raw priority)), in one transaction.

        Ids pruned meanwhile are simply not there any more.
        """
        rows = [(float(p), int(tid)) for tid, p in pairs]
        for p, tid in rows:
            if not (np.isfinite(p) and p > 0):
                raise ValueError(f"save_priorities: transition {tid}: got priority {p!r}, expected > 0")
        if rows:
            self._write(lambda db: db.executemany("UPDATE transitions SET priority=? WHERE id=?", rows))

    def iter_transitions(self, limit: int | None = None) -> Iterator[StoredTransition]:
        """The last ``limit`` transitions (all if None), oldest first.

        A state shared by consecutive transitions is decoded once and the same
        object is handed out for both, so a rebuilt replay holds it once in memory.
        """
        total = self.transition_count()
        offset = 0 if limit is None else max(0, total - int(limit))
        rows = self._read(
            "SELECT id, step, state_id, next_state_id, primitive, row, col, rotation, rotations, reward, "
            "done, priority FROM transitions ORDER BY id LIMIT -1 OFFSET ?", (offset,))
        last: dict[int, Heightmaps] = {}
        for (tid, step, sid, nid, prim, r, c, rot, rots, reward, done, prio) in rows:
            s = last.get(sid) or self._load_state(sid)
            ns = None
            if nid is not None:
                ns = s if nid == sid else (last.get(nid) or self._load_state(nid))
            last = {sid: s} if ns is None else {sid: s, nid: ns}
            yield StoredTransition(tid, step, s, Action(prim, r, c, rot, rots), float(reward), ns,
                                   bool(done), prio)

    def _load_state(self, sid: int) -> Heightmaps:
        r = self._read("SELECT rows, cols, color, height FROM states WHERE id=?", (sid,))
        if not r:
            raise StoreError(f"store {self.path}: a transition refers to missing state {sid}")
        return decode_heightmaps(*r[0])

    def action_log(self, limit: int | None = None) -> list[dict]:
        """The last ``limit`` action-log rows (all if None), oldest first, as dicts."""
        sql = f"SELECT {', '.join(ACTION_COLUMNS)} FROM actions ORDER BY step DESC"
        args: tuple = ()
        if limit is not None:
            sql += " LIMIT ?"
            args = (int(limit),)
        rows = self._read(sql, args)
        return [dict(zip(ACTION_COLUMNS, r)) for r in reversed(rows)]

    def events(self, kind: str | None = None) -> list[dict]:
        sql, args = "SELECT id, time, kind, message FROM events", ()
        if kind is not None:
            sql, args = sql + " WHERE kind=?", (kind,)
        return [dict(zip(("id", "time", "kind", "message"), r)) for r in self._read(sql + " ORDER BY id", args)]

    def query(self, sql: str, args: tuple = ()) -> list[tuple]:
        """Read-only SQL for metrics."""
        return self._read(sql, args)

    def transaction(self, fn: Callable[[sqlite3.Connection], Any]) -> Any:
        """Run ``fn(db)`` in one write transaction (for the gate's records); storage failures are StoreError."""
        return self._write(fn)

    def integrity_check(self) -> str:
        return str(self._read("PRAGMA integrity_check")[0][0])

    def close(self) -> None:
        with self._lock:
            try:
                self._db.close()
            except sqlite3.Error:
                pass


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


_CKPT_RE = re.compile(r"^checkpoint-(\d{10})\.safetensors$")


class CheckpointDir:
    """Policy checkpoints named by learner update count; the newest ``keep`` are kept."""

    def __init__(self, directory: str | os.PathLike, keep: int = 3):
        if keep < 1:
            raise ValueError(f"CheckpointDir.keep: got {keep!r}, expected >= 1")
        self.directory = Path(directory)
        self.keep = keep

    def path_for(self, updates: int) -> Path:
        return self.directory / f"checkpoint-{int(updates):010d}.safetensors"

    def write(self, save: Callable[[Path], None], updates: int) -> Path:
        """Write a checkpoint with ``save(path)`` (which must write atomically), then prune."""
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            path = self.path_for(updates)
            save(path)
            for old in self.checkpoints()[self.keep:]:
                old.unlink(missing_ok=True)
            return path
        except OSError as exc:
            raise StoreError(_explain(exc, self.directory)) from exc

    def remove_temporary(self) -> int:
        """Delete temporary files of checkpoint writes interrupted by a kill (never a finished checkpoint)."""
        if not self.directory.is_dir():
            return 0
        stale = [p for p in self.directory.iterdir() if p.name.startswith(".checkpoint-") and p.name.endswith(".tmp")]
        for p in stale:
            p.unlink(missing_ok=True)
        return len(stale)

    def checkpoints(self) -> list[Path]:
        """Existing checkpoints, newest first."""
        if not self.directory.is_dir():
            return []
        found = [p for p in self.directory.iterdir() if _CKPT_RE.match(p.name)]
        return sorted(found, key=lambda p: p.name, reverse=True)

    @staticmethod
    def updates_of(path: Path) -> int:
        m = _CKPT_RE.match(path.name)
        if not m:
            raise ValueError(f"{path}: not a checkpoint name")
        return int(m.group(1))
