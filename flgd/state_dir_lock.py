"""One process at a time owns a state directory: the daemon, ``flgd calibrate`` or ``flgd train``.

The daemon and ``flgd calibrate`` would command the same arm and camera (a UR controller takes one RTDE
control client, a RealSense one streaming process); the daemon and ``flgd train`` would write the same
store, checkpoints and policies.  So every command that drives a cell or writes a state directory takes
the same advisory lock: an flock on the state directory itself.  Why the directory and not a file in it:
a lock file cannot be created in a directory that is read-only or on a full disk, and a daemon that
started there without its lock would share the store with the next one once the directory is writable
again.  Opening a directory needs no write access and no free space.  The kernel drops an flock with its
process, so a crash or ``kill -9`` never leaves a stale lock.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path


class StateDirBusy(Exception):
    """Another process holds the state directory's lock."""


def lock_state_dir(state_dir: str | os.PathLike, *, create: bool) -> int:
    """Take the lock and return its descriptor (keep it open; closing it releases the lock).

    ``create`` makes the directory if missing (the daemon, a training run); without it a missing directory
    is FileNotFoundError (no daemon ever ran there).  StateDirBusy if another process holds it; OSError if
    the directory cannot be made or opened.
    """
    path = Path(state_dir)
    if create:
        path.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise StateDirBusy(f"another flgd process (the daemon, flgd calibrate or flgd train) is using the state "
                           f"directory {path}") from None
    return fd
