"""Atomic file replacement: after a power cut a file is either the old one or the new one, whole.

Used for everything flgd must not lose or corrupt: policy files and checkpoints, trainer state, and a
config file rewritten by calibration.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def temporary_prefix(name: str) -> str:
    """How the temporary files of ``write_atomically`` to a file called ``name`` begin (they end in .tmp)."""
    return f".{name}."


def remove_temporaries(directory: str | os.PathLike, name: str) -> int:
    """Delete the temporary files that writes of ``name`` in ``directory`` left when killed; how many.

    Only call this while no write of ``name`` can be in progress (the daemon holds its state-directory
    lock, a training run its run directory); the finished file itself is never touched.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return 0
    prefix = temporary_prefix(name)
    stale = [p for p in directory.iterdir() if p.name.startswith(prefix) and p.name.endswith(".tmp")]
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)


def write_atomically(path: str | os.PathLike, data: bytes, mode: int | None = None) -> None:
    """Write ``data`` to a temp file beside ``path``, fsync it, rename it over ``path``, fsync the directory.

    ``mode`` sets the new file's permission bits exactly (the umask does not apply); default: those of
    mkstemp, 0600, which only the owner can read -- pass a mode for files other users must read.  The
    bits are set on the open file before the data is written, so the fsync covers them and the file
    never appears under ``path`` with other bits.  On any error the temp file is removed and ``path``
    is untouched.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(path.name), suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            if mode is not None:
                os.fchmod(f.fileno(), mode)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
