"""``python -m flgd.training.ray_reaper DRIVER_PID``: kill a local Ray cluster's processes when its driver dies.

Started by ``flgd.training.ray_engine`` with a pipe from the driver on its standard input.  Every second it
notes the driver's descendants that are Ray's (their command line names ray); when the pipe closes without the
driver's "clean" line (the driver was killed), it kills the noted processes that still run.  Ray stops its
processes itself on a clean exit; killed, some of them would otherwise live on for good.
"""

from __future__ import annotations

import os
import select
import signal
import sys
from pathlib import Path

__all__ = ["main"]


def _children() -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        # pid (comm) state ppid ...: comm may hold spaces and parentheses, so split after the last ')'
        fields = stat[stat.rfind(")") + 2:].split()
        if len(fields) > 1:
            out.setdefault(int(fields[1]), []).append(int(entry.name))
    return out


def _start_time(pid: int) -> str:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return ""
    return stat[stat.rfind(")") + 2:].split()[19]


def _is_ray(pid: int) -> bool:
    """A process of Ray's: its workers and agents (``ray::...``), its binaries, its Python services."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    if not argv or not argv[0]:
        return False
    if argv[0].startswith(b"ray::") or Path(argv[0].decode(errors="replace")).name in ("raylet", "gcs_server"):
        return True
    return any(b"/site-packages/ray/" in a or b"/dist-packages/ray/" in a for a in argv[:3])


def _descendants(root: int) -> set[int]:
    children, found, todo = _children(), set(), [root]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found


def main(argv: list[str]) -> int:
    driver = int(argv[0])
    driver_started = _start_time(driver)  # a pid reused after the driver died is not the driver
    me = os.getpid()
    noted: dict[int, str] = {}  # pid -> start time (a reused pid is not the process noted)
    while True:
        ready, _, _ = select.select([sys.stdin.buffer], [], [], 1.0)
        if ready:
            line = sys.stdin.buffer.readline()
            if line.strip() == b"clean":
                return 0
            if not line:
                break  # the pipe closed: the driver is gone
        if _start_time(driver) != driver_started:
            break  # the driver is gone (its pipe closing is seen next; its processes are noted already)
        for pid in _descendants(driver):
            if pid != me and pid not in noted and _is_ray(pid):
                noted[pid] = _start_time(pid)
    for pid, started in noted.items():
        if started and _start_time(pid) == started:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
