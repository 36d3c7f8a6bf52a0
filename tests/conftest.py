"""Fixtures shared by test modules that ask for them (none is applied on its own)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture
def one_torch_thread():
    """Torch on one thread for the test, as the daemon's acting thread runs it; restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
