"""Where a training run's cycles come from: one simulated cell in the run's process, or N Ray workers.

``flgd.training.run.TrainingRun`` is the one training loop: it asks its collector for the next cell's report,
keeps its cycles (store, replay, learner: ``flgd.cycle_commit``), lets that cell go on, runs the learner's
updates and logs the cycles.  A collector only runs cells: ``LocalCollector`` one ``TrainingCell`` here, acting
with the learner's own weights; ``flgd.training.ray_collector.RayCollector`` N workers, each with a copy of the
weights, replacing a worker that dies.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol

from flgd.config import CellConfig
from flgd.learning_stack import Handover

if TYPE_CHECKING:
    from flgd.cell import Cell
    from flgd.learning.agent import Agent
    from flgd.learning.networks import QMapNetwork
    from flgd.training.cell_loop import TrainingCell
    from flgd.training.collected import CellReport, WriteAhead
    from flgd.training.settings import RunSettings

__all__ = ["Collector", "CollectorStart", "WeightsSource", "LocalCollector"]


class WeightsSource(Protocol):
    """The learner as a collector sees it: the weights its cells act with (``flgd.learning.learner.Learner``)."""

    updates: int
    online: QMapNetwork


@dataclass(frozen=True)
class CollectorStart:
    """What a collector's cells are built from, once the run's store and learning stack are up."""

    config: CellConfig
    settings: RunSettings
    segment: int   # of the run (seeds differ per segment)
    step: int      # the run's next step
    agent: Agent   # the run's acting agent (a cell in the run's process acts with it)
    learner: WeightsSource
    store: WriteAhead
    say: Callable[[str], None]               # a line for the operator
    store_event: Callable[[str, str], None]  # (kind, message) for the store's events


class Collector(Protocol):
    """Runs a training run's cells (module doc)."""

    #: who acts with the learner's weights in the run's process (``LearningStack.build``)
    handover: Handover
    #: how many cells collect side by side (the store keeps that many recent states)
    cells: int

    def prepare(self) -> None:
        """What may fail before the run touches its directory (Ray: start or join the cluster)."""
        ...

    def start(self, start: CollectorStart) -> None:
        """Build the cells; their first cycles act at ``start.step``."""
        ...

    def next_report(self, timeout: float) -> CellReport | None:
        """The next cell's cycle; None when none came within ``timeout`` seconds (e.g. a lost worker replaced)."""
        ...

    def go_on(self, cell: int, step: int) -> None:
        """``cell``'s report was kept: its next cycle acts at the run's ``step``."""
        ...

    @property
    def in_flight(self) -> int:
        """Cycles asked for and not yet reported (dropped when the run stops)."""
        ...

    def where(self, cell: int) -> str:
        """How a line about ``cell`` begins ('' for the one cell of a run)."""
        ...

    def status(self) -> dict[str, str]:
        """Progress fields: objects on each table, workers alive."""
        ...

    def segment_info(self) -> dict[str, Any]:
        """What a segment's record in run.json says of the cells, when it starts."""
        ...

    def stats(self) -> dict[str, Any]:
        """What it says of them after (run.json, per segment)."""
        ...

    def close(self) -> None:
        ...


class LocalCollector:
    """One simulated cell in the run's process, acting with the learner's weights as they are handed over, so
    each decision comes after the updates its previous action owed (a run is reproducible from its seed)."""

    handover = Handover.AGENT
    cells = 1

    def __init__(self, wrap_cell: Callable[[Cell], Cell] | None = None) -> None:
        """``wrap_cell``: a wrapper around the simulated cell (tests inject faults with it)."""
        self._wrap_cell = wrap_cell
        self._cell: TrainingCell | None = None
        self._step = 0

    def prepare(self) -> None:
        pass

    def start(self, start: CollectorStart) -> None:
        from flgd.training.cell_loop import TrainingCell
        from flgd.wiring import resume_seed

        self._step = start.step
        self._cell = TrainingCell(start.config, start.settings, start.agent, step=start.step,
                                  curriculum_seed=resume_seed(start.settings.seed, start.segment, 5),
                                  write_ahead=start.store, wrap_cell=self._wrap_cell)

    @property
    def cell(self) -> Cell:
        """The simulated cell (wrapped, where ``wrap_cell`` was given)."""
        assert self._cell is not None, "start() first"
        return self._cell.cell

    def next_report(self, timeout: float) -> CellReport:
        assert self._cell is not None, "start() first"
        return self._cell.collect(self._step)

    def go_on(self, cell: int, step: int) -> None:
        self._step = step

    @property
    def in_flight(self) -> int:
        return 0   # its cycle runs inside ``next_report``

    def where(self, cell: int) -> str:
        return ""

    def status(self) -> dict[str, str]:
        return {"objects": "-" if self._cell is None else str(self._cell.objects)}

    def segment_info(self) -> dict[str, Any]:
        return {}

    def stats(self) -> dict[str, Any]:
        return {}

    def close(self) -> None:
        if self._cell is not None:
            self._cell.close()
            self._cell = None
