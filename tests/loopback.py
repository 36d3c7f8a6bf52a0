"""Loopback hosts for emulated controllers in tests.

ur_rtde connects to fixed ports (30004, 29999, 30001-30003), so two emulators can only run side by side on two
hosts: each pytest-xdist worker gets its own 127.0.N.x, and none uses 127.0.0.1, where a developer's own emulator
may be running.
"""

from __future__ import annotations

import os


def worker_host(last_octet: int) -> str:
    """127.0.N.``last_octet`` with N = 10 + the xdist worker's number (10 outside xdist)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    number = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    return f"127.0.{10 + number}.{last_octet}"
