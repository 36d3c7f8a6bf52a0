"""A training worker: one simulated cell with its own seed, acting network and agent, collecting for the learner.

``flgd train --workers N`` runs N of these as Ray actors (``flgd.training.distributed``).  Each builds
everything inside its own process -- torch limited to its threads, the PyBullet simulation, the network, the
daemon's agent (``flgd.wiring.make_agent``) -- from plain data (the config, the run settings, a weights
dictionary), so nothing that holds a simulator or a thread is ever pickled.  ``collect`` runs one cycle of the
daemon's cycle (``flgd.training.cell_loop.TrainingCell``) with the newest weights the learner sent and returns
what it did: the action-log row and the transition for the learner's store and replay, the scene it acted
on, and any fault or give-up.  The worker stores nothing itself; a worker that dies loses at most the cycle
it was running.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from flgd.config import CellConfig

if TYPE_CHECKING:
    from flgd.learning.replay import Transition
    from flgd.training.settings import RunSettings
    from flgd.learning.agent import Decision
    from flgd.perception import Heightmaps

__all__ = ["CollectedCycle", "WorkerReport", "CollectingStore", "CellWorker", "worker_seed"]


def worker_seed(seed: int, segment: int, worker: int, incarnation: int, stream: int) -> int:
    """A worker's seed for one random stream (sim, agent, curriculum): distinct per run seed, segment, worker,
    restart of that worker and stream, so that no two workers -- or a worker and its replacement -- lay out
    the same scenes or make the same exploration draws."""
    return int(np.random.SeedSequence([int(seed), int(segment), int(worker), int(incarnation),
                                       int(stream)]).generate_state(1)[0])


@dataclass
class CollectedCycle:
    """One step as the worker saw it; the learner gives it its global step when it stores it."""

    row: dict[str, Any]  # CycleRecord.row()
    transition: Transition | None  # None: nothing to learn (a refused action is kept, faults not)
    outcome: str
    primitive: str | None
    success: bool | None
    objects_left: int | None = None
    scene: int = 0  # the worker's own scene number
    scene_kind: str = ""


@dataclass
class WorkerReport:
    """What one ``collect`` call returns."""

    worker: int
    cycles: list[CollectedCycle] = field(default_factory=list)
    notes: list[tuple[str, str, str]] = field(default_factory=list)  # (kind, event, message)
    # the greedy a' of each decision: (replay key of the state, weights' update count, index), for the learner's
    # double-DQN target cache (``DQNUpdate.note_greedy``; as ``note_decision`` in one process)
    decisions: list[tuple[bytes, int, Any]] = field(default_factory=list)
    weights_version: int = -1
    cpu_seconds: float = 0.0  # of the worker's process since it started
    objects: int | None = None  # objects on its table now
    error: str = ""  # the cycle raised: the run stops, as it does in one process (rows and notes still sent)


class DecisionNotes:
    """The worker's stand-in for the learner (a ``CycleLearner``): the cycle runner tells it each decision
    (``note_decision``); the learner that trains on the worker's transitions is in the driver's process, so a new
    transition schedules nothing here and nothing is waited for."""

    def __init__(self) -> None:
        self.notes: list[tuple[bytes, int, Any]] = []

    def note_decision(self, state: Heightmaps, decision: Decision, weights_version: int) -> None:
        from flgd.learning.replay import state_key

        if decision.greedy is not None and weights_version >= 0:
            self.notes.append((state_key(state), int(weights_version), tuple(int(v) for v in decision.greedy)))

    def notify_new_transition(self) -> None:
        pass

    def wait_idle(self, timeout: float | None = None) -> bool:
        return True

    def take(self) -> list[tuple[bytes, int, Any]]:
        out, self.notes = self.notes, []
        return out


class CollectingStore:
    """The worker's stand-in for the store (a ``CycleStore``): the cycle's rows and transitions are kept for the
    learner.

    The cycle runner writes through ``commit_cycle`` (and a fault's row with no transition); the write-ahead
    intent and the space check are the learner's store's business, so they do nothing here; an event goes to the
    worker's notes (``on_event``), which the learner records in its store."""

    def __init__(self, on_event: Callable[[str, str, str], None]) -> None:
        self.committed: list[tuple[dict[str, Any], Any]] = []
        self._on_event = on_event

    def check_space(self) -> None:
        pass

    def record_intent(self, row: dict) -> None:
        pass

    def record_event(self, kind: str, message: str) -> None:
        self._on_event(kind, message, message)

    def commit_cycle(self, row: dict, transition: Transition | None = None, priority: float | None = None) -> None:
        self.committed.append((dict(row), transition))
        return None

    def note_store_time(self, step: int, seconds: float) -> None:
        pass  # the learner times its own commit of the row

    def forget_last_state(self) -> None:
        pass

    def take(self) -> list[tuple[dict[str, Any], Any]]:
        out, self.committed = self.committed, []
        return out


class CellWorker:
    """One simulated cell of a multi-worker run (module doc); made a Ray actor by the driver."""

    def __init__(self, config: CellConfig, settings: RunSettings, index: int, incarnation: int, segment: int,
                 weights: dict[str, Any], version: int, step: int = 0, threads: int = 1) -> None:
        import torch

        from flgd.learning.networks import build_network
        from flgd.training.cell_loop import TrainingCell
        from flgd.wiring import make_agent

        torch.set_num_threads(max(1, int(threads)))
        self.index = index
        self.notes: list[tuple[str, str, str]] = []
        seed = settings.seed
        config = dataclasses.replace(
            config, sim=dataclasses.replace(config.sim, seed=worker_seed(seed, segment, index, incarnation, 2)))
        lc = config.learning
        network = build_network(lc.network, rotations=lc.rotations, seed=0)
        self.agent = make_agent(config, network, worker_seed(seed, segment, index, incarnation, 4))
        self.agent.act_with(weights, None, version)
        self.store = CollectingStore(self._note)
        self.decisions = DecisionNotes()
        # the run's step: the curriculum's first scene and the exploration schedule follow it
        self.loop = TrainingCell(config, settings, self.agent, step=step, scene=0,
                                 curriculum_seed=worker_seed(seed, segment, index, incarnation, 5),
                                 note=self._note, store=self.store, learner=self.decisions)

    def _note(self, kind: str, event: str, message: str) -> None:
        self.notes.append((kind, event, message))

    def pid(self) -> int:
        return os.getpid()

    def collect(self, step: int, weights: dict[str, Any] | None = None, version: int = -1) -> WorkerReport:
        """One cycle at the run's ``step`` (exploration and curriculum follow it), with ``weights`` (the learner's
        newest, when it sent them) acting; what it did (module doc)."""
        if weights is not None:
            self.agent.mailbox.post(weights, version=version)
        self.loop.runner.step = int(step)
        report = WorkerReport(self.index)
        scene = self.loop.scene  # the scene this cycle acts on (a fault in it moves the loop to the next)
        cycle = None
        try:
            cycle = self.loop.cycle()
        except Exception as exc:  # StoreError cannot happen here; "N cell faults in a row" and the like
            report.error = f"{type(exc).__name__}: {exc}"
        report.notes, self.notes = self.notes, []
        report.decisions = self.decisions.take()
        objects, kind = self.loop.scene_of_cycle  # noted during this cycle's plan and judge phases
        for row, transition in self.store.take():
            # a row whose cycle then failed (a reset after it) still belongs to the scene it acted on
            report.cycles.append(CollectedCycle(row, transition, str(row.get("outcome")), row.get("primitive"),
                                                None if row.get("success") is None else bool(row["success"]),
                                                objects, scene, kind))
        if cycle is not None and report.cycles:
            last = report.cycles[-1]
            last.objects_left, last.scene, last.scene_kind = cycle.objects_left, cycle.scene, cycle.scene_kind
        report.weights_version = self.agent.weights_version
        report.cpu_seconds = time.process_time()
        report.objects = self.loop.cell.object_count
        return report

    def close(self) -> None:
        self.loop.close()
