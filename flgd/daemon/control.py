"""What the operator's commands may see and do of the daemon: the controller's public face.

``flgd.daemon.commands`` is written against this protocol and never against ``Controller`` itself, so the
handlers use no private member of the controller and the two modules do not import each other (the controller
imports the handlers; the handlers import this).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Protocol

if TYPE_CHECKING:
    from flgd.calibration_watch import CalibrationWatch
    from flgd.cell import Cell
    from flgd.config import CellConfig
    from flgd.cycle import CycleRunner
    from flgd.cycle_record import CycleRecord
    from flgd.daemon.state import StateMachine
    from flgd.gate.keeper import Gatekeeper
    from flgd.learning.agent import Agent
    from flgd.learning.learner import Learner
    from flgd.learning.networks import QMapNetwork
    from flgd.learning_stack import LearningStack
    from flgd.store import Store

__all__ = ["DaemonControl"]


class DaemonControl(Protocol):
    """The daemon as a command handler sees it (``flgd.daemon.controller.Controller`` implements it)."""

    config: CellConfig
    state: StateMachine
    state_dir: Path
    store: Store | None
    store_problem: str
    cell: Cell | None
    backend: str
    runner: CycleRunner | None
    learning: LearningStack
    agent: Agent
    learner: Learner
    gate: Gatekeeper | None
    policy_source: str
    policy_arg: str | None
    last_checkpoint: str
    fine_tune: bool
    learning_why: str
    calibration_watch: CalibrationWatch | None
    last_record: CycleRecord | None
    last_stuck: dict[str, Any] | None
    cycle_in_flight: bool
    started_at: float
    learning_lock: threading.Lock
    learner_quiet_timeout: float

    def run_on_loop(self, fn: Callable[[], dict[str, Any]], timeout: float = ...) -> dict[str, Any]:
        """Run ``fn`` on the run loop between cycles; its result."""
        ...

    def record_event(self, kind: str, message: str) -> None:
        ...

    def fault(self, cause: str) -> None:
        ...

    def wake(self) -> None:
        ...

    def request_stop(self, cause: str) -> None:
        ...

    def clear_stop_latch(self) -> bool:
        ...

    def reset(self) -> dict[str, Any]:
        ...

    def write_checkpoint(self, network: QMapNetwork, updates: int) -> None:
        ...

    def cell_config_at(self, step: int) -> CellConfig:
        ...

    def swap_cell(self, cell: Cell, backend: str) -> str:
        ...
