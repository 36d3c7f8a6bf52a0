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
    """Tests marked ``slow`` run first (each group in file order): with ``--dist worksteal`` the long ones are
    spread over both processes from the start and the run ends on short tests, not on one long straggler."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


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
