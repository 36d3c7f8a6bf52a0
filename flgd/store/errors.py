"""StoreError and the sentence a cell operator can act on, from an sqlite3 or OS error."""

from __future__ import annotations

import errno
import os
from pathlib import Path


class StoreError(RuntimeError):
    """The store cannot be read or written; the message names the path and the likely cause."""


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


def explain(exc: BaseException, path: Path) -> str:
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
