"""Fixtures shared by test modules that ask for them (none is applied on its own)."""

from __future__ import annotations

import os
from typing import Any

import pytest
import torch

from tests.fakes.daemon import DaemonProcess
from tests.fakes.rg2 import LoopbackRG2
from tests.fakes.ur5e import FakeURController

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `pytest -n 2` on a 2-core PC: one torch thread per test process, not two processes of two threads each
    torch.set_num_threads(1)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Order the tests for ``-n N --dist worksteal``: the long (``slow``) tests are dealt out evenly and put at the
    front of each worker's first share, so every process starts on long tests and the run ends on short ones.

    Why this shape: worksteal first hands each worker a contiguous share of the list (the first worker
    ``len // N`` tests, and so on), and an idle worker steals from the *end* of another's queue; long tests at the
    front of each share are therefore never left over for one process at the end."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    slow = [item for item in items if item.get_closest_marker("slow") is not None]
    fast = [item for item in items if item.get_closest_marker("slow") is None]
    if workers < 2:
        items[:] = slow + fast
        return
    sizes, left = [], len(items)
    for k in range(workers):   # worksteal's first split
        sizes.append(left // (workers - k))
        left -= sizes[-1]
    shares = [slow[k::workers] for k in range(workers)]
    rest = iter(fast)
    for k, share in enumerate(shares):
        while len(share) < sizes[k] or k == workers - 1:
            item = next(rest, None)
            if item is None:
                break
            share.append(item)
    items[:] = [item for share in shares for item in share]


@pytest.fixture
def one_torch_thread():
    """Torch on one thread for the test, as the daemon's acting thread runs it; restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def daemon_factory(tmp_path):
    """Make daemons that are always cleaned up, even when a test fails."""
    made: list[DaemonProcess] = []

    def make(**kw: Any) -> DaemonProcess:
        d = DaemonProcess(tmp_path, **kw)
        made.append(d)
        return d

    yield make
    for d in made:
        d.cleanup()


@pytest.fixture
def rg2():
    """A loopback RG2 whose fingers move in 10 ms, closed after the test."""
    server = LoopbackRG2(move_time=0.01)
    yield server
    server.close()


@pytest.fixture
def ctl():
    """A fresh fake UR controller (the arm at home, powered, program running)."""
    return FakeURController()
