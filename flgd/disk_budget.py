"""The disk a state directory may use (a budget) and must leave free (a floor).

Why a floor checked before motion: the store records every action before the
cell moves (flgd/cycle.py); a disk that is full, or a filesystem that turned
read-only, must stop the cell *before* a motion whose record cannot be
written, and leave room for the fault event that says why.  The check is one
``statvfs`` and one ``access`` call, so it runs at the start of every cycle.

Why a budget in bytes: the replay's capacity in transitions says nothing about
the disk (a stored state is ~35 KB at 224 x 224 px, more for larger
heightmaps).  ``storage.max_bytes`` bounds the store's files (the database and
its write-ahead log); above it the oldest replay transitions and their states
are deleted first.  The action log is bounded by its own retention
(``storage.action_log_days``), because stats and the gate's tallies read it.

The numbers here are pure functions of the configuration, so the store and
the tests share one definition of "over budget".
"""

from __future__ import annotations

import math
import os
from typing import Callable

__all__ = ["GIB", "MIB", "KIB", "MIN_STORE_BYTES", "DAY", "format_bytes", "space_problem", "wal_reserve",
           "database_limit", "wal_autocheckpoint_pages", "wal_log_limit", "transitions_to_evict", "action_log_cutoff"]

KIB = 1024
MIB = 1024 * KIB
GIB = 1024 * MIB
DAY = 86400.0
# the smallest storage.max_bytes a config may set: room for a useful replay next to a month's action log
MIN_STORE_BYTES = 64 * MIB
# at most this much of the budget is set aside for the write-ahead log (and its index file)
WAL_RESERVE_MAX = 16 * MIB
WAL_RESERVE_MIN = 512 * KIB
SQLITE_DEFAULT_AUTOCHECKPOINT = 1000  # pages
WAL_FRAME_BYTES = 4096 + 24  # a WAL frame of a default-sized page: the page and its header


def format_bytes(n: float) -> str:
    """``1.5 GiB`` style, for messages a person reads (exact byte counts go beside it where they matter)."""
    for unit, size in (("GiB", GIB), ("MiB", MIB), ("KiB", KIB)):
        if abs(n) >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def space_problem(directory: str | os.PathLike, min_free_bytes: int, *,
                  statvfs: Callable[[str], os.statvfs_result] | None = None,
                  access: Callable[[str, int], bool] | None = None) -> str:
    """What keeps ``directory`` from taking the next writes ('' = nothing): read-only, below the floor, full.

    Each answer names the directory, the numbers and what to do, since it becomes the FAULT cause an operator
    reads in ``flgctl status``.  A directory that cannot be examined at all is a problem too: the store
    would not be writable there either.  ``statvfs`` and ``access`` default to the os module's (looked up
    at each call).
    """
    d = os.fspath(directory)
    statvfs = statvfs or os.statvfs
    access = access or os.access
    try:
        st = statvfs(d)
    except OSError as exc:
        return f"the state directory {d} cannot be examined ({exc}); check that it exists and is mounted"
    if st.f_flag & os.ST_RDONLY:
        return (f"the state directory {d} is on a read-only filesystem; nothing moves until it is writable "
                f"again (a filesystem turns read-only after disk errors: check the system log), then flgctl reset")
    if not access(d, os.W_OK):
        return (f"the state directory {d} is not writable by this user; nothing moves until it is (check its "
                f"owner and mode), then flgctl reset")
    free = int(st.f_bavail) * int(st.f_frsize)
    if st.f_bavail == 0:
        return (f"the disk is full (no space free on the filesystem of the state directory {d}); nothing moves "
                f"until space is freed there, then flgctl reset")
    if free < min_free_bytes:
        return (f"only {format_bytes(free)} ({free} bytes) free on the filesystem of the state directory {d}, "
                f"below storage.min_free_bytes {format_bytes(min_free_bytes)} ({min_free_bytes} bytes); nothing "
                f"moves until space is freed there (or the floor lowered), then flgctl reset")
    if st.f_files and st.f_favail == 0:
        return (f"no free inodes on the filesystem of the state directory {d}; nothing moves until files are "
                f"removed there, then flgctl reset")
    return ""


def wal_reserve(max_bytes: int) -> int:
    """The part of a store budget kept for the write-ahead log and its index (the rest is the database's)."""
    return int(min(WAL_RESERVE_MAX, max(WAL_RESERVE_MIN, max_bytes // 16)))


def database_limit(max_bytes: int) -> int:
    """The bytes the database's used pages may take under the budget ``max_bytes``.

    The file keeps its largest size (freed pages are reused, not returned), and grows past the used pages by
    at most one cycle's write before the same transaction evicts.  The write-ahead log is copied into the
    database once it holds a quarter of the reserve and truncated to that size afterwards
    (``wal_autocheckpoint_pages``, ``journal_size_limit``), so it never holds more than that plus one
    transaction; with its 32 KiB index, database + log stay under ``max_bytes`` as long as a cycle's
    transaction is well under a quarter of the reserve (a 224 x 224 px state: ~35 KB, its transaction ~100 KB).
    """
    return int(max_bytes - wal_reserve(max_bytes))


def wal_autocheckpoint_pages(max_bytes: int) -> int:
    """Write-ahead-log pages after which SQLite copies the log into the database (never above its default)."""
    return int(max(8, min(SQLITE_DEFAULT_AUTOCHECKPOINT, wal_log_limit(max_bytes) // WAL_FRAME_BYTES)))


def wal_log_limit(max_bytes: int) -> int:
    """The size the write-ahead log is truncated to after a checkpoint (SQLite's ``journal_size_limit``)."""
    return int(wal_reserve(max_bytes) // 4)


def transitions_to_evict(used_bytes: int, limit: int, bytes_per_transition: int) -> int:
    """How many of the oldest transitions to delete so that ``used_bytes`` falls a little below ``limit``.

    Why below: evicting exactly the excess would delete one transition per cycle, and each deletion also
    clears the action log's references, so the budget evicts in steps of ~1/32 of the limit instead.
    """
    if used_bytes <= limit:
        return 0
    target = limit - limit // 32
    return max(1, math.ceil((used_bytes - target) / max(1, bytes_per_transition)))


def action_log_cutoff(now: float, days: float) -> float | None:
    """The time before which action-log rows may be deleted (None: kept forever, ``days`` 0)."""
    return None if days <= 0 else now - days * DAY
