"""The SQLite store of one state directory: ``Store`` opens it, writes each cycle in one transaction
and reads it back (see the package docstring for why SQLite in WAL mode, the tables and the write-ahead
action log).

Failures are reported as ``StoreError`` with the operator's sentence, and the first storage failure
stays the diagnosis until a write succeeds again.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np

from flgd import disk_budget
from flgd.actions import Action
from flgd.perception import Heightmaps
from flgd.store import action_log, replay_rows, retention, schema
from flgd.store.action_log import INTENT_OUTCOME
from flgd.store.errors import StoreError, explain
from flgd.store.replay_rows import StoredTransition
from flgd.store.schema import ACTION_COLUMNS, DB_NAME

if TYPE_CHECKING:
    from flgd.learning.replay import Transition

log = logging.getLogger("flgd")


class Store:
    """The SQLite store of one state directory.  Thread-safe (one connection behind a lock).

    ``keep_transitions``: when set, transitions older than the newest N (the
    replay capacity) and the states only they used are deleted every
    ``PRUNE_EVERY`` commits (the action log's ``transition_id`` becomes NULL).
    ``max_bytes``, ``action_log_days`` and ``min_free_bytes``: the disk budget,
    the action log's retention and the free-space floor (package docstring).
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
        # the newest next states stored, (Heightmaps object, state id), newest last: a transition whose state is
        # one of these very objects refers to its row instead of storing it again. One in a daemon; one per cell
        # where several cells' cycles interleave (``flgd train --workers N``).
        self.remember_states = 1
        self._recent_states: list[tuple[Any, int]] = []
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
            schema.create_or_upgrade(self._db, self.path)
            if self._db.execute("SELECT 1 FROM actions WHERE outcome=? LIMIT 1", (INTENT_OUTCOME,)).fetchone():
                self._write(lambda db: action_log.mark_interrupted(db, None))
            if self.action_log_days > 0:
                self.retain_action_log()
        except StoreError:
            raise
        except (sqlite3.Error, OSError) as exc:
            raise StoreError(explain(exc, self.path)) from exc

    # ------------------------------------------------------------------ internals
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
                self._recent_states = []
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
        why = explain(exc, self.path)
        if isinstance(exc, sqlite3.IntegrityError):
            return why
        if self._first_failure:
            return f"{self._first_failure} (still failing since: {type(exc).__name__}: {exc})"
        self._first_failure = why
        return why

    def _state_id(self, db: sqlite3.Connection, hm: Heightmaps) -> int:
        for known, sid in reversed(self._recent_states):
            # still there: retention or the disk budget may have removed an older transition's rows since
            if known is hm and db.execute("SELECT 1 FROM states WHERE id=?", (sid,)).fetchone():
                return sid
        encoded = replay_rows.encode_heightmaps(hm)
        self._state_bytes = len(encoded[2]) + len(encoded[3])
        cur = db.execute("INSERT INTO states(rows, cols, color, height) VALUES(?,?,?,?)", encoded)
        return int(cur.lastrowid)

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
                action_log.mark_interrupted(db, earlier)
            action_log.insert_action(db, dict(row, outcome=INTENT_OUTCOME))
            if pending is not None:
                db.execute("UPDATE actions SET t_store=? WHERE step=?", (pending[1], pending[0]))

        self._write(write)
        self._pending_store_time = None
        self._open_intent = step

    def commit_cycle(self, row: dict, transition: Transition | None = None,
                     priority: float | None = None) -> int | None:
        """Write one cycle: its action-log ``row`` and, if any, its transition.

        ``transition`` has ``state``, ``action``, ``reward``, ``next_state`` and
        ``done``.  A state that is the very object stored as a recent
        transition's next state (``remember_states``) is not stored again.  A row whose intent was
        recorded (``record_intent``) is completed in place.  Returns the transition id.
        """
        unknown = set(row) - set(ACTION_COLUMNS)
        if unknown:
            raise ValueError(f"commit_cycle: unknown action-log columns {sorted(unknown)}")
        pending = self._pending_store_time
        intent = self._open_intent

        def write(db: sqlite3.Connection) -> tuple[int | None, tuple[Any, int] | None]:
            tid = None
            new_last = None
            if transition is not None:
                sid = self._state_id(db, transition.state)
                nid = None
                if transition.next_state is not None:
                    nid = self._state_id(db, transition.next_state) \
                        if transition.next_state is not transition.state else sid
                    new_last = (transition.next_state, nid)
                tid = replay_rows.insert_transition(db, int(row["step"]), sid, nid, transition, priority)
            values = dict(row, transition_id=tid)
            step = int(values["step"])
            if intent is not None and intent != step:
                action_log.mark_interrupted(db, intent)
            if intent == step:
                action_log.complete_action(db, values)
            else:
                action_log.insert_action(db, values)
            if pending is not None:
                db.execute("UPDATE actions SET t_store=? WHERE step=?", (pending[1], pending[0]))
            if self.keep_transitions is not None and (self._commits + 1) % self.PRUNE_EVERY == 0:
                retention.prune(db, self.keep_transitions)
            if self.max_bytes is not None and transition is not None:
                self._evict_to_budget(db)
            if self.action_log_days > 0 and (self._commits + 1) % self.RETAIN_EVERY == 0:
                retention.retain_action_log(db, self.action_log_days)
            return tid, new_last

        out, new_last = self._write(write)
        # only after the commit: a rolled-back write's ids may be handed to other states
        if transition is not None:
            # a next state taken up as this transition's start has done its job: it leaves room for other cells'
            kept = [s for s in self._recent_states if s[0] is not transition.state]
            if new_last is not None:
                kept = [s for s in kept if s[0] is not new_last[0]] + [new_last]
            self._recent_states = kept[-max(1, self.remember_states):]
        self._pending_store_time = None
        self._open_intent = None
        self._commits += 1
        return out

    def prune(self, keep: int) -> None:
        """Keep only the newest ``keep`` transitions (and their states) now."""
        self._write(lambda db: retention.prune(db, keep))

    def _evict_to_budget(self, db: sqlite3.Connection) -> None:
        """Over ``max_bytes``: delete the oldest transitions and their states, never the newest one."""
        limit = disk_budget.database_limit(self.max_bytes)
        for _ in range(16):  # each round frees about what it estimated; a few rounds at most
            used = retention.used_bytes(db)
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
            retention.evict_through(db, row[0])

    def retain_action_log(self) -> None:
        """Apply ``action_log_days`` now (it also runs when the store opens and every ``RETAIN_EVERY`` commits)."""
        self._write(lambda db: retention.retain_action_log(db, self.action_log_days))

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
        self._recent_states = []

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
        return replay_rows.decode_heightmaps(*r[0])

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
