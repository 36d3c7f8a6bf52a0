"""Persistence of what the cell has experienced: replay transitions, the action log, checkpoints.

Why SQLite in WAL mode: one cycle is written as one transaction (the action-log
row, the transition and any new heightmap), so a process killed at any instant
leaves either the whole cycle or none of it, and readers (``flgctl stats``)
never block the writer.  ``synchronous=FULL``: a commit is on disk when it
returns (one fsync of the WAL per cycle, small next to a cycle's controller
time, BENCHMARKS.md "Controller overhead"), so a power cut loses at most the cycle in flight, as a killed process
does; with NORMAL it could also lose the last few committed cycles.

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
  ``t_store`` of a row is written with the next cycle's commit (a commit cannot
  time itself).
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

Retention: with ``keep_transitions`` (the daemon passes the replay capacity)
only the newest transitions and their states are kept, so the file stops
growing; the action log, events and counters are kept whole.

The step counter is not stored separately: it is ``max(actions.step) + 1``, so
it can never disagree with the log.

Policy checkpoints are files in ``<state_dir>/checkpoints`` written atomically
by ``flgd.learning.policy_file.save_policy``; the last ``keep`` are kept.
"""

from __future__ import annotations

import errno
import json
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
]

SCHEMA_VERSION = 3
HEIGHT_QUANTUM = 1e-4  # metres per stored height unit
DB_NAME = "flgd.sqlite"
TIMING_PHASES = ("capture", "perceive", "decide", "plan", "execute", "judge", "store")

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
    ``PRUNE_EVERY`` commits, so a daemon running for weeks does not fill the
    disk; the action log is kept whole (its ``transition_id`` becomes NULL).
    """

    PRUNE_EVERY = 64

    def __init__(self, state_dir: str | os.PathLike, keep_transitions: int | None = None):
        if keep_transitions is not None and keep_transitions < 1:
            raise ValueError(f"Store.keep_transitions: got {keep_transitions!r}, expected >= 1 or None")
        self.keep_transitions = keep_transitions
        self._commits = 0
        self.state_dir = Path(state_dir)
        self.path = self.state_dir / DB_NAME
        self._lock = threading.RLock()
        self._last_state: tuple[Any, int] | None = None
        self._pending_store_time: tuple[int, float] | None = None
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path, timeout=10.0, isolation_level=None,
                                       check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            mode = self._db.execute("PRAGMA journal_mode").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StoreError(f"store {self.path}: could not switch to WAL mode (got {mode!r})")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
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
                        self._db.execute("ROLLBACK")
                    raise
                return out
            except (sqlite3.Error, OSError) as exc:
                self._last_state = None
                raise StoreError(_explain(exc, self.path)) from exc

    def _read(self, sql: str, args: tuple = ()) -> list[tuple]:
        with self._lock:
            try:
                return self._db.execute(sql, args).fetchall()
            except (sqlite3.Error, OSError) as exc:
                raise StoreError(_explain(exc, self.path)) from exc

    def _state_id(self, db: sqlite3.Connection, hm: Heightmaps) -> int:
        if self._last_state is not None and self._last_state[0] is hm:
            return self._last_state[1]
        cur = db.execute("INSERT INTO states(rows, cols, color, height) VALUES(?,?,?,?)",
                         encode_heightmaps(hm))
        return int(cur.lastrowid)

    # ------------------------------------------------------------------ writing
    def commit_cycle(self, row: dict, transition: Any | None = None,
                     priority: float | None = None) -> int | None:
        """Write one cycle: its action-log ``row`` and, if any, its transition.

        ``transition`` has ``state``, ``action``, ``reward``, ``next_state`` and
        ``done``.  A state that is the very object stored as the previous
        transition's next state is not stored again.  Returns the transition id.
        """
        unknown = set(row) - set(ACTION_COLUMNS)
        if unknown:
            raise ValueError(f"commit_cycle: unknown action-log columns {sorted(unknown)}")
        pending = self._pending_store_time

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
            cols = [c for c in ACTION_COLUMNS if c in values]
            db.execute(f"INSERT INTO actions({', '.join(cols)}) VALUES({', '.join('?' * len(cols))})",
                       [_sql_value(values[c]) for c in cols])
            if pending is not None:
                db.execute("UPDATE actions SET t_store=? WHERE step=?", (pending[1], pending[0]))
            if self.keep_transitions is not None and (self._commits + 1) % self.PRUNE_EVERY == 0:
                self._prune(db, self.keep_transitions)
            self._last_state = new_last
            return tid

        out = self._write(write)
        self._pending_store_time = None
        self._commits += 1
        return out

    @staticmethod
    def _prune(db: sqlite3.Connection, keep: int) -> None:
        row = db.execute("SELECT id FROM transitions ORDER BY id DESC LIMIT 1 OFFSET ?", (keep,)).fetchone()
        if row is None:
            return
        cutoff = row[0]
        db.execute("UPDATE actions SET transition_id=NULL WHERE transition_id <= ?", (cutoff,))
        db.execute("DELETE FROM transitions WHERE id <= ?", (cutoff,))
        db.execute("DELETE FROM states WHERE id < (SELECT COALESCE(MIN(state_id), 0) FROM transitions)")

    def prune(self, keep: int) -> None:
        """Keep only the newest ``keep`` transitions (and their states) now."""
        self._write(lambda db: self._prune(db, keep))

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
