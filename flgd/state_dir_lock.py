"""One process at a time owns a state directory: the daemon, ``flgd calibrate`` or ``flgd train``.

The daemon and ``flgd calibrate`` would command the same arm and camera (a UR controller takes one RTDE
control client, a RealSense one streaming process); the daemon and ``flgd train`` would write the same
store, checkpoints and policies.  So every command that drives a cell or writes a state directory takes
the same advisory lock, ``flgd.lock`` in that directory. The kernel drops an flock with its process, so a crash or ``kill -9`` never leaves a stale lock.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

LOCK_NAME = "flgd.lock"


class StateDirBusy(Exception):
    """Another process holds the state directory's lock."""


def lock_state_dir(state_dir: str | os.PathLike, *, create: bool) -> int:
    """Take the lock and return its descriptor (keep it open; closing it releases the lock).

    ``create`` makes the directory and lock file if missing (the daemon); without it a missing lock
    file is FileNotFoundError (no daemon ever ran there).  StateDirBusy if another process holds it;
    OSError if it cannot be opened.
    """
    path = Path(state_dir) / LOCK_NAME
    if create:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o640)
    else:
        fd = os.open(path, os.O_RDONLY)  # flock needs no write access: an operator account can check too
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise StateDirBusy(f"another flgd process (the daemon, flgd calibrate or flgd train) is using the state "
                           f"directory {Path(state_dir)}") from None
    return fd
