"""``flgd train --workers N``: N simulated cells collect in Ray actors, the run's process learns.

Each worker (``flgd.training.cell_worker.CellWorker``) has its own seed, simulator and acting copy of the
network and runs the run's training cell.  The run's loop (``flgd.training.run``) keeps each worker's cycle as
it keeps one cell's, so a run started with ``--workers`` resumes with or without it, and one rule keeps
learning per action independent of N: every kept action is followed by exactly ``learning.updates_per_action``
updates.  A worker's next cycle starts as soon as its last one is kept (``go_on``), so the learner runs that
one's updates while the worker acts; a worker never runs ahead by more than that one cycle, and waits when the
learner is the slower part.  It gets the learner's newest weights with its next cycle once they are
``learning.sync_every`` updates newer than its own (0: whenever they changed), so it acts with weights that lack
at most the updates of the last N actions (one process: none).

Faults: a worker that dies (killed, out of memory, a simulator crash) loses the cycle it was running; it is
replaced by a fresh one (new seeds) and the run goes on, said on the progress display and kept in the store's
events (kind ``worker``).  A worker replaced ``MAX_REPLACEMENTS`` times in a row without completing a cycle stops
the run.  What is recorded per worker (cycles, replacements, CPU seconds) is in ``run.json``, per segment, under
``worker_stats``.
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Any

from flgd.cycle_record import CycleOutcome
from flgd.learning_stack import Handover

if TYPE_CHECKING:
    from flgd.training.collected import CellReport
    from flgd.training.collector import CollectorStart
    from flgd.training.ray_engine import Engine

__all__ = ["RayCollector", "MAX_REPLACEMENTS"]

MAX_REPLACEMENTS = 3  # a worker replaced this many times in a row without a completed cycle stops the run


@dataclasses.dataclass
class WorkerSlot:
    """The collector's record of one worker position: its actor, its call in flight and what it did."""

    index: int
    actor: Any = None   # a Ray actor handle (untyped: Ray's)
    incarnation: int = 0
    version: int = -1  # learner update count of the weights it acts with
    cycles: int = 0
    replacements: int = 0
    failures_in_a_row: int = 0
    cpu_seconds: float = 0.0  # of its incarnations so far, the current one's newest report included
    cpu_before: float = 0.0   # of its earlier incarnations
    objects: int | None = None
    last_error: str = ""


class RayCollector:
    """N training cells in Ray actors (module doc)."""

    handover = Handover.NOBODY  # nobody acts in the run's process: the weights go to the workers (``_weights``)

    def __init__(self, workers: int, address: str = "") -> None:
        if workers < 1:
            raise ValueError(f"--workers: got {workers}, expected >= 1")
        self.cells = workers
        self.address = address
        self.engine: Engine | None = None
        self.slots = [WorkerSlot(i) for i in range(workers)]
        self._start: CollectorStart | None = None
        self._step = 0
        self._worker_class: Any = None   # Ray's remote class (untyped: Ray's)
        self._weights_ref: tuple[int, Any] | None = None  # (version, Ray object ref) of the newest weights sent
        self._in_flight: dict[Any, WorkerSlot] = {}   # Ray object ref of a collect call -> its worker
        self._first_cycles_asked = False

    def prepare(self) -> None:
        """Start or join the cluster: one that cannot be started or joined leaves the run directory as it was."""
        from flgd.training.ray_engine import start_engine

        self.engine = start_engine(self.address, self.cells)

    def start(self, start: CollectorStart) -> None:
        from flgd.training.cell_worker import CellWorker
        from flgd.training.ray_engine import remote_class

        engine = self._engine()
        self._start, self._step = start, start.step
        if engine.cpus < self.cells:
            start.say(f"flgd train: the Ray cluster has {engine.cpus:g} CPUs for {self.cells} workers of one CPU "
                      f"each: the rest wait until CPUs free up")
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        if not self.address and self.cells + 1 > cores:
            # the local cluster gives every worker a CPU slot anyway: they and the learner share the cores
            start.say(f"flgd train: {self.cells} workers and the learner on {cores} cores: they share them, so "
                      f"workers beyond {max(1, cores - 1)} add little (docs/training-and-evaluation.md, 'Training "
                      f"on many simulated cells')")
        self._worker_class = remote_class(engine.ray, CellWorker, cpus=1.0)
        for slot in self.slots:
            self._spawn(slot)
        self._first_cycles_asked = False

    def _engine(self) -> Engine:
        assert self.engine is not None, "prepare() first"
        return self.engine

    def _spawn(self, slot: WorkerSlot) -> None:
        """A fresh actor in ``slot`` (its first, or the replacement of a lost one), with the learner's weights."""
        assert self._start is not None
        s = self._start
        version, ref = self._weights()
        slot.actor = self._worker_class.remote(s.config, s.settings, slot.index, slot.incarnation, s.segment, ref,
                                               version, self._step)
        slot.version = version

    def _weights(self) -> tuple[int, Any]:
        """The learner's newest weights in Ray's object store (put once per version, shared by every worker)."""
        assert self._start is not None
        learner = self._start.learner
        version = int(learner.updates)
        if self._weights_ref is None or self._weights_ref[0] != version:
            weights = {k: v.detach().to("cpu", copy=True) for k, v in learner.online.state_dict().items()}
            self._weights_ref = (version, self._engine().ray.put(weights))
        return self._weights_ref

    def _submit(self, slot: WorkerSlot) -> None:
        assert self._start is not None
        self._start.store.check_space()  # StoreError before a worker acts on a cycle that could not be stored
        sync_every = max(1, self._start.config.learning.sync_every)
        if self._start.learner.updates - slot.version >= sync_every:
            version, ref = self._weights()
            slot.version = version
            call = slot.actor.collect.remote(self._step, ref, version)
        else:
            call = slot.actor.collect.remote(self._step)
        self._in_flight[call] = slot

    def next_report(self, timeout: float) -> CellReport | None:
        from flgd.training.ray_engine import worker_lost_errors

        ray = self._engine().ray
        if not self._first_cycles_asked:   # asked for by the run's loop, once its segment is on record
            self._first_cycles_asked = True
            for slot in self.slots:
                self._submit(slot)
        ready, _ = ray.wait(list(self._in_flight), num_returns=1, timeout=timeout)
        if not ready:
            return None
        slot = self._in_flight.pop(ready[0])
        try:
            report: CellReport = ray.get(ready[0])
        except worker_lost_errors(ray) as exc:
            self._replace(slot, exc)
            self._submit(slot)
            return None
        slot.cpu_seconds = slot.cpu_before + report.cpu_seconds
        slot.objects = report.objects
        kept = sum(1 for c in report.cycles if c.outcome != CycleOutcome.FAULT)
        slot.cycles += kept
        if report.cycles:
            slot.failures_in_a_row = 0
        if report.error:
            slot.last_error = report.error
        return report

    def go_on(self, cell: int, step: int) -> None:
        self._step = step
        self._submit(self.slots[cell])

    @property
    def in_flight(self) -> int:
        """Cycles asked for and not yet reported (dropped when the run stops)."""
        return len(self._in_flight)

    def _replace(self, slot: WorkerSlot, exc: BaseException) -> None:
        """A lost worker: a fresh one in its place (new seeds), said and kept in the events."""
        assert self._start is not None
        slot.failures_in_a_row += 1
        slot.replacements += 1
        slot.last_error = _describe_loss(exc)
        what = f"worker {slot.index} lost ({slot.last_error}); its cycle in flight is dropped"
        if slot.failures_in_a_row > MAX_REPLACEMENTS:
            raise RuntimeError(f"{what}; replaced {MAX_REPLACEMENTS} times in a row without a completed cycle: "
                               f"stopping the run")
        self._start.say(f"flgd train: {what}; starting a new one")
        self._start.store_event("worker", what)
        try:
            self._engine().ray.kill(slot.actor)
        except Exception:  # already gone
            pass
        slot.cpu_before = slot.cpu_seconds
        slot.incarnation += 1
        self._spawn(slot)

    def where(self, cell: int) -> str:
        return f"worker {cell}: "

    def status(self) -> dict[str, str]:
        alive = sum(1 for s in self.slots if not s.failures_in_a_row)
        return {"objects": "/".join("-" if s.objects is None else str(s.objects) for s in self.slots),
                "workers": f"{alive}/{self.cells}"}

    def segment_info(self) -> dict[str, Any]:
        return {"workers": self.cells, "ray_address": self.address or "local", "ray_cpus": self._engine().cpus}

    def stats(self) -> dict[str, Any]:
        return {"worker_stats": [{"worker": s.index, "cycles": s.cycles, "replacements": s.replacements,
                                  "cpu_seconds": round(s.cpu_seconds, 1), "last_error": s.last_error}
                                 for s in self.slots]}

    def close(self) -> None:
        if self.engine is not None:
            self.engine.stop()
            self.engine = None


def _describe_loss(exc: BaseException) -> str:
    """One line on why a worker's call failed: Ray's first line, or the error raised inside the worker."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException) and not isinstance(cause, type(exc)):
        return f"{type(cause).__name__}: {cause}".splitlines()[0][:300]
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}"[:300]
