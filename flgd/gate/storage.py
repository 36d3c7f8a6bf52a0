"""The gate's policies kept in the state directory: files under ``gate/`` and rows of the ``policies`` table.

Every policy the gate knows is a policy file in ``<state_dir>/gate/`` (written
atomically) and a row of the store's ``policies`` table; ``GateStorage`` writes,
reads, moves aside and prunes the files, and reads the rows.  Which policy acts,
and why, is ``flgd.gate.keeper``'s.

Only a file's content proves it unusable: a size, format or checksum the loader
refuses, weights other than the ones recorded for it, or a file missing from a
gate directory that can be listed (gone for good: no retry brings it back).
Such a file is recorded as ``unusable`` (an event naming it, why, and what to
do), moved to ``gate/unusable/`` for inspection (the newest ``KEEP_UNUSABLE``
are kept), and the gate falls back to its predecessor, then to the configured
policy; if none is usable the daemon refuses to start rather than let a fresh
network act.

A read the operating system refuses (a permission, an I/O error, the gate
directory itself missing, a file swapped while opened) says nothing about the
content.  It is tried again (``READ_RETRY_DELAYS``, about 1.4 s in all: a rename
in progress is over by then), and if it still fails the daemon refuses to start
(``GateFileUnreadable``: the file, the OS error, what to fix) and records
nothing.  It does not act with the predecessor meanwhile: the store would still
name the unreadable policy as champion, so the actions, the tallies and any
promotion would be credited to a line the records do not show, and an older
policy acting quietly hides a fault (a permission, a disk) that a person has to
fix.  A refused start is loud, and systemd starts the daemon again every 5 s
(``RestartSec``), so it acts with the whole line again within seconds of the
file becoming readable.  A start that refuses changes no record at all.  So does
one whose files hold another network variant than ``learning.network``: the
files are sound, the config changed.

A write the operating system refuses (a gate directory made read-only or given
to another user, a full disk) is tried again the same way; if it still fails,
``GateDirUnwritable`` says what failed and what to do, and the caller keeps
what it meant to write (the gatekeeper keeps the learner's hand-over until the
file can be written).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
import sqlite3
from typing import TYPE_CHECKING, Any, Callable

from flgd.config import CellConfig
from flgd.gate.statistics import Tally
from flgd.store import Store

if TYPE_CHECKING:
    from flgd.learning.networks import QMapNetwork
    from flgd.learning.policy_file import PolicyFileUnreadable

__all__ = ["GateStorage", "GateError", "GateFileUnreadable", "GateDirUnwritable", "PolicyRecord", "insert_record", "tally_json",
           "write_event", "GATE_DIR", "UNUSABLE_DIR", "KEEP_UNUSABLE", "READ_RETRY_DELAYS"]

log = logging.getLogger("flgd")

GATE_DIR = "gate"
UNUSABLE_DIR = "unusable"  # under GATE_DIR: files whose content proved them unusable, kept for inspection
# The newest unusable files kept there: enough to compare a few failures (a disk going bad shows as several),
# at most ~150 MB with the largest (DenseNet) policies.
KEEP_UNUSABLE = 5
# Pauses before each further try of a read the OS refused (see the module docstring).
READ_RETRY_DELAYS = (0.1, 0.3, 1.0)


class GateError(RuntimeError):
    """No usable policy to act with (every champion file and the configured policy are unusable)."""


class GateFileUnreadable(GateError):
    """A gate file the OS would not let the daemon read, on every try; nothing was recorded about it."""

    def __init__(self, policy_id: int, path: Path, message: str) -> None:
        super().__init__(message)
        self.policy_id = policy_id
        self.path = path


class GateDirUnwritable(OSError):
    """The gate directory refused a policy file on every try; the message says what to do."""


def _daemon_user() -> str:
    uid = os.geteuid()
    try:
        import pwd
        return f"user {pwd.getpwuid(uid).pw_name} (uid {uid})"
    except (ImportError, KeyError):
        return f"uid {uid}"


def _write_advice(directory: Path, exc: OSError) -> str:
    """What a person does about a refused write into ``directory`` (the gate directory)."""
    if isinstance(exc, PermissionError):
        return (f"The daemon runs as {_daemon_user()} and must be able to write {directory}: give it back to it "
                f"(as installed: owner flgd, mode 0750).")
    if exc.errno == errno.EROFS:
        return f"The filesystem holding {directory} is read-only: remount it read-write."
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"The disk holding {directory} is full: free space on it."
    return f"Check the disk that holds it (an {errno.errorcode.get(exc.errno or 0, 'OS')} error: see `dmesg`)."


def _os_problem(exc: PolicyFileUnreadable) -> str:
    """A PolicyFileUnreadable's OS error in words, without the loader's advice for files outside the state
    directory (which does not fit a gate file)."""
    return exc.problem if exc.os_error is None else str(exc.os_error.strerror or exc.os_error)


def _read_advice(path: Path, exc: OSError | None) -> str:
    """What a person does about a refused read of ``path`` (a gate file)."""
    directory = path.parent
    if isinstance(exc, PermissionError):
        return (f"The daemon runs as {_daemon_user()} and must be able to read {path} and enter {directory}: give them "
                f"back to it (as installed: owner flgd, modes 0640 and 0750).")
    if isinstance(exc, FileNotFoundError):
        return (f"The gate directory {directory} is missing although the store records this policy in it: "
                f"restore it (from a backup). To give up the stored policies instead, create {directory} empty: "
                f"each is then recorded as missing and the configured policy acts.")
    if exc is None:
        return f"It was replaced while being opened on every try: find what rewrites files in {directory}."
    return f"Check the disk that holds it (an {errno.errorcode.get(exc.errno or 0, 'OS')} error: see `dmesg`)."


@dataclass
class PolicyRecord:
    id: int
    role: str
    file: str  # relative to the state directory
    sha256: str
    origin: str
    predecessor: int | None
    learner_updates: int | None
    training_steps: int
    since_step: int
    record: Tally | None  # a retired champion's tally over its tenure

    def as_dict(self) -> dict:
        return {"id": self.id, "role": self.role, "file": self.file, "origin": self.origin,
                "predecessor": self.predecessor, "learner_updates": self.learner_updates,
                "training_steps": self.training_steps, "since_step": self.since_step,
                "record": None if self.record is None else self.record.as_dict()}


_COLUMNS = ("id", "role", "file", "sha256", "origin", "predecessor", "learner_updates", "training_steps",
            "since_step", "record")


def tally_json(t: Tally) -> str:
    """A tally as the ``policies.record`` column holds it."""
    return json.dumps({"actions": t.actions, "successes": t.successes, "grasps": t.grasps})


def _record_from_row(row: tuple) -> PolicyRecord:
    d = dict(zip(_COLUMNS, row))
    rec = None
    if d["record"]:
        r = json.loads(d["record"])
        rec = Tally(int(r["actions"]), int(r["successes"]), int(r["grasps"]))
    return PolicyRecord(id=int(d["id"]), role=d["role"], file=d["file"], sha256=d["sha256"], origin=d["origin"],
                        predecessor=d["predecessor"], learner_updates=d["learner_updates"],
                        training_steps=int(d["training_steps"]), since_step=int(d["since_step"]), record=rec)


def insert_record(db: sqlite3.Connection, r: PolicyRecord) -> None:
    """A new ``policies`` row for ``r`` (in the caller's transaction)."""
    db.execute("INSERT INTO policies(id, created, role, file, sha256, origin, predecessor, learner_updates, "
               "training_steps, since_step, record) VALUES(?,?,?,?,?,?,?,?,?,?,NULL)",
               (r.id, time.time(), r.role, r.file, r.sha256, r.origin, r.predecessor, r.learner_updates,
                r.training_steps, r.since_step))


def _set_file(db: sqlite3.Connection, path: str, policy_id: int) -> None:
    db.execute("UPDATE policies SET file=? WHERE id=?", (path, policy_id))


def write_event(db: sqlite3.Connection, kind: str, step: int, policy: int | None, other: int | None, who: str, message: str,
                evidence: dict) -> None:
    """A ``gate_events`` row: a change of the acting policy (or a file found unusable), with its evidence."""
    db.execute("INSERT INTO gate_events(time, step, kind, policy, other, who, message, evidence) "
               "VALUES(?,?,?,?,?,?,?,?)", (time.time(), int(step), kind, policy, other, who, message,
                                           json.dumps(evidence, sort_keys=True, default=str)))


class GateStorage:
    """The gate's policy files and the records that name them (see the module docstring)."""

    def __init__(self, config: CellConfig, store: Store, state_dir: str | Path, keep_unusable: int = KEEP_UNUSABLE,
                 read_retry_delays: tuple[float, ...] = READ_RETRY_DELAYS,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.config = config
        self.store = store
        self.state_dir = Path(state_dir)
        self.directory = self.state_dir / GATE_DIR
        self.keep_unusable = keep_unusable
        self.read_retry_delays = read_retry_delays
        self.sleep = sleep  # between tries of a refused read

    def path(self, record: PolicyRecord) -> Path:
        """Where the record's file is (its ``file`` is relative to the state directory)."""
        return self.state_dir / record.file

    def write_file(self, policy_id: int, network: QMapNetwork, meta: dict) -> tuple[str, str]:
        """Write the policy's file (atomically); its path relative to the state directory and its weights' sha256.

        A write the OS refuses is tried again (``read_retry_delays``); GateDirUnwritable if every try fails.
        """
        from flgd.learning.policy_file import read_metadata, save_policy

        rel = f"{GATE_DIR}/policy-{policy_id:06d}.safetensors"
        started = time.monotonic()
        for tries, delay in enumerate((*self.read_retry_delays, None), start=1):
            try:
                self.directory.mkdir(parents=True, exist_ok=True)
                save_policy(self.state_dir / rel, network, meta)
                return rel, str(read_metadata(self.state_dir / rel)["weights_sha256"])
            except OSError as exc:
                if delay is None:
                    raise GateDirUnwritable(
                        f"policy #{policy_id}'s file cannot be written into {self.directory}: "
                        f"{exc.strerror or exc} ({tries} tries over {time.monotonic() - started:.1f} s). "
                        f"{_write_advice(self.directory, exc)}") from None
                log.warning("gate: cannot write policy #%d into %s (%s); trying again in %.1f s", policy_id,
                            self.directory, exc.strerror or exc, delay)
                self.sleep(delay)
        raise AssertionError("unreachable")

    def next_id(self) -> int:
        """The id the next policy gets."""
        return int(self.store.query("SELECT COALESCE(MAX(id), 0) + 1 FROM policies")[0][0])

    def row(self, policy_id: int) -> PolicyRecord | None:
        """The stored record of policy ``policy_id``, or None."""
        rows = self.store.query(f"SELECT {', '.join(_COLUMNS)} FROM policies WHERE id=?", (int(policy_id),))
        return _record_from_row(rows[0]) if rows else None

    def by_role(self, role: str) -> PolicyRecord | None:
        """The newest record in ``role`` (``champion``, ``challenger``, ...), or None."""
        rows = self.store.query(f"SELECT {', '.join(_COLUMNS)} FROM policies WHERE role=? ORDER BY id DESC LIMIT 1",
                                (role,))
        return _record_from_row(rows[0]) if rows else None

    def load(self, record: PolicyRecord) -> Any:
        """The record's network.

        PolicyFileError (naming the file): its content proves it unusable.  GateError: the file may be
        sound but cannot act now -- the OS refused every read (GateFileUnreadable), or it holds another
        network variant than the config's; nothing is to be recorded about it then.
        """
        from flgd.learning.policy_file import PolicyFileError, PolicyFileUnreadable, load_policy

        path = self.path(record)
        started = time.monotonic()
        for tries, delay in enumerate((*self.read_retry_delays, None), start=1):
            try:
                loaded = load_policy(path)
                break
            except PolicyFileUnreadable as exc:
                if delay is None:
                    raise self._refused(record, exc, tries, time.monotonic() - started) from None
                log.warning("gate: policy #%d file %s cannot be read (%s); trying again in %.1f s", record.id, path,
                            _os_problem(exc), delay)
                self.sleep(delay)
        variant, configured = loaded.metadata.get("variant"), self.config.learning.network
        if variant != configured:
            raise GateError(f"policy #{record.id}'s file {path} holds a {variant!r} network, but learning.network "
                            f"is {configured!r}: set learning.network back to {variant!r}, or, to give up the "
                            f"stored policies for the configured one, move {path.parent} aside and create it empty "
                            f"(nothing was recorded)")
        if loaded.metadata.get("weights_sha256") != record.sha256:
            raise PolicyFileError(path, "weights differ from the ones the gate recorded for it")
        return loaded.network

    def _refused(self, record: PolicyRecord, exc: PolicyFileUnreadable, tries: int, seconds: float) -> Exception:
        """The error for a read refused on every try: a missing file in a gate directory that can be listed
        is gone for good (PolicyFileError: content); anything else is GateFileUnreadable."""
        from flgd.learning.policy_file import PolicyFileError

        path = self.path(record)
        if isinstance(exc.os_error, FileNotFoundError):
            try:
                os.listdir(path.parent)
            except OSError:
                pass  # the directory itself is gone or unreadable: not the file's doing
            else:
                return PolicyFileError(path, "is missing (the gate directory holds no such file)")
        return GateFileUnreadable(record.id, path, (
            f"policy #{record.id}'s file {path} cannot be read: {_os_problem(exc)} ({tries} tries over {seconds:.1f} s). "
            f"{_read_advice(path, exc.os_error)} Nothing was recorded about it: the daemon acts with it again "
            f"once it can read it."))

    def remove_file(self, record: PolicyRecord) -> None:
        """Delete the record's file; a failure is logged (a file left over does no harm)."""
        try:
            self.path(record).unlink(missing_ok=True)
        except OSError as exc:
            log.warning("gate: cannot remove %s: %s", self.path(record), exc)

    def prune_retired(self, champion: PolicyRecord | None, keep_champions: int) -> None:
        """Keep the files of the champion's last ``keep_champions`` predecessors; older ones are deleted."""
        chain, cur = [], champion
        while cur is not None and cur.predecessor is not None:
            cur = self.row(cur.predecessor)
            if cur is not None:
                chain.append(cur)
        for old in chain[keep_champions:]:
            if self.path(old).exists():
                self.remove_file(old)

    def remove_strays(self) -> None:
        """Files in the gate directory no record points to (a kill between writing a file and its row)."""
        if not self.directory.is_dir():
            return
        known = {r[0] for r in self.store.query(
            "SELECT file FROM policies WHERE role NOT IN ('dropped', 'rolled_back')")}
        try:
            paths = [p for p in self.directory.iterdir() if not p.is_dir()]  # not unusable/
        except OSError as exc:  # the policy files' own reads say what to do
            log.warning("gate: cannot list %s: %s", self.directory, exc)
            return
        for path in paths:
            if f"{GATE_DIR}/{path.name}" not in known:
                try:
                    path.unlink()
                    log.info("gate: removed %s (no record: written just before an interruption)", path)
                except OSError as exc:
                    log.warning("gate: cannot remove %s: %s", path, exc)

    def move_aside(self, record: PolicyRecord) -> str | None:
        """Move the record's file to ``gate/unusable/`` (named by the time, so the newest sort last);
        its new path relative to the state directory, or None when there is none to move or it cannot be."""
        source = self.path(record)
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        rel = f"{GATE_DIR}/{UNUSABLE_DIR}/{stamp}-{source.name}"
        try:
            (self.directory / UNUSABLE_DIR).mkdir(parents=True, exist_ok=True)
            for n in range(2, 100):
                if not (self.state_dir / rel).exists():
                    break
                rel = f"{GATE_DIR}/{UNUSABLE_DIR}/{stamp}.{n}-{source.name}"
            os.rename(source, self.state_dir / rel)
        except FileNotFoundError:
            return None
        except OSError as exc:
            log.warning("gate: cannot move %s aside: %s", source, exc)
            return None
        return rel

    def set_aside(self, unusable: list[tuple[PolicyRecord, Any]], step: int) -> Callable[[Any], None]:
        """Move the files aside now; the returned writer records them as unusable (in the caller's transaction,
        with the change of champion, so that no kill leaves the store without one).  ``unusable``: (record,
        its PolicyFileError)."""
        moved = [(record, exc.problem, self.move_aside(record)) for record, exc in unusable]

        def write(db: sqlite3.Connection) -> None:
            for record, why, rel in moved:
                where = (f"; moved to {self.state_dir / rel} for inspection (the newest {self.keep_unusable} "
                         "unusable files are kept)" if rel is not None else
                         f"; left at {self.path(record)} (it cannot be moved aside)" if self.path(record).exists()
                         else "")
                db.execute("UPDATE policies SET role='unusable', file=? WHERE id=?",
                           (record.file if rel is None else rel, record.id))
                write_event(db, "unusable", step, record.id, None, "flgd",
                            f"policy #{record.id} file {self.path(record)} cannot be used: {why}{where}. To act "
                            "with it again, `flgctl policy load` a good copy (from a backup); several at once "
                            "point to a failing disk", {"error": why, "moved_to": rel})
        for record, why, rel in moved:
            log.error("gate: policy #%d file %s cannot be used: %s%s", record.id, self.path(record), why,
                      "" if rel is None else f"; moved to {self.state_dir / rel}")
        return write

    def set_aside_earlier_unusable(self) -> None:
        """Files recorded unusable before they were moved aside (by an earlier version) go to ``gate/unusable/``."""
        rows = self.store.query(f"SELECT {', '.join(_COLUMNS)} FROM policies WHERE role='unusable' AND file LIKE ?",
                                (f"{GATE_DIR}/policy-%",))
        for record in map(_record_from_row, rows):
            if self.path(record).is_file():
                rel = self.move_aside(record)
                if rel is not None:
                    self.store.transaction(partial(_set_file, path=rel, policy_id=record.id))

    def prune_unusable(self) -> None:
        """Keep the newest ``keep_unusable`` files in ``gate/unusable/``; older ones are deleted."""
        directory = self.directory / UNUSABLE_DIR
        try:
            files = sorted(p for p in directory.iterdir() if p.is_file())
        except OSError:  # none yet, or unreadable: nothing to prune now
            return
        for old in files[:max(0, len(files) - self.keep_unusable)]:
            try:
                old.unlink()
                log.info("gate: removed %s (only the newest %d unusable files are kept)", old, self.keep_unusable)
            except OSError as exc:
                log.warning("gate: cannot remove %s: %s", old, exc)

