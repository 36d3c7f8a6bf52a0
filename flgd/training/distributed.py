"""``flgd train --workers N``: N simulated cells collect, one learner learns -- on Ray.

The learner is this process (the driver): the same learning stack, store, replay, DQN update, checkpoints,
trainer state, ``actions.csv``, curve and ``run.json`` as the single-process run (``flgd.training.run``), in
the same run directory, so a run started with ``--workers`` resumes with or without it.  The cells are Ray
actors (``flgd.training.cell_worker.CellWorker``), each with its own seed, simulator and acting copy of the
network, running the daemon's cycle and agent.

One rule keeps learning per action independent of N: every collected action is stored, added to the replay
and followed by exactly ``learning.updates_per_action`` updates (``Learner.update_pending``, as in one process).
A worker's next cycle starts as soon as its last one is stored, and the learner runs that one's updates while
the worker acts, so cells and learner work side by side; a worker never runs ahead by more than that one cycle,
and waits when the learner is the slower part.  It gets the learner's newest weights with its next cycle once
they are ``learning.sync_every`` updates newer than its own (0: whenever they changed), so it acts with weights
that lack at most the updates of the last N actions (one process: none).

Faults: a worker that dies (killed, out of memory, a simulator crash) loses the cycle it was running; it is
replaced by a fresh one (new seeds) and the run goes on, said on the progress display and kept in the store's
events (kind ``worker``).  A worker replaced ``MAX_REPLACEMENTS`` times in a row without completing a cycle stops
the run.  Ctrl-C / SIGTERM: the cycles in flight are dropped, a checkpoint is written, exit 130; a killed driver
(``kill -9``) is resumed by running the same command again (what the single-process run restores, restored).
What is recorded per worker (cycles, replacements, CPU seconds) is in ``run.json``, per segment, under ``worker_stats``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from flgd.cycle_record import CycleOutcome
from flgd.learning_stack import Handover
from flgd.training.run import CURVE_FILE, EXIT_INTERRUPTED, EXIT_OK, LOG_FILE, TrainingRun, next_scene_id

if TYPE_CHECKING:
    from flgd.learning.replay import Transition
    from flgd.training.cell_worker import CollectedCycle, WorkerReport

__all__ = ["DistributedTrainingRun", "MAX_REPLACEMENTS"]

MAX_REPLACEMENTS = 3  # a worker replaced this many times in a row without a completed cycle stops the run
POLL_SECONDS = 1.0    # how often the progress display is refreshed while waiting for workers


@dataclasses.dataclass
class _WorkerSlot:
    """The driver's record of one worker position: its actor, its call in flight and what it did."""

    index: int
    actor: Any = None
    incarnation: int = 0
    version: int = -1  # learner update count of the weights it acts with
    cycles: int = 0
    replacements: int = 0
    failures_in_a_row: int = 0
    cpu_seconds: float = 0.0  # of its incarnations so far, the current one's newest report included
    cpu_before: float = 0.0   # of its earlier incarnations
    scene: tuple[int, int] | None = None  # (its own scene number, the run's) of the scene it acts on
    objects: int | None = None
    last_error: str = ""


class DistributedTrainingRun(TrainingRun):
    """A training run whose cells are Ray actors (module doc)."""

    learner_hands_to = Handover.NOBODY  # nobody acts in this process: the weights go to the workers (``_weights``)

    def __init__(self, *args: Any, workers: int, address: str | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if workers < 1:
            raise ValueError(f"--workers: got {workers}, expected >= 1")
        self.workers = workers
        self.address = address or ""
        self.engine: Any = None
        self.slots: list[_WorkerSlot] = []
        self._next_step = int(self.run_info.get("step", 0))  # until setup reads the store
        self._next_scene = 0
        self._worker_class: Any = None
        self._weights_ref: tuple[int, Any] | None = None  # (version, Ray object ref) of the newest weights sent
        self._last_states: dict[int, Any] = {}  # worker -> the Heightmaps of its newest stored next state

    # ------------------------------------------------------------------ setup
    @property
    def step(self) -> int:
        return self._next_step

    def setup(self) -> None:
        """The Ray engine first (a cluster that cannot be started or joined leaves the run directory as it
        was), then the run as in one process, with N workers instead of a cell."""
        from flgd.training.ray_engine import start_engine

        self.engine = start_engine(self.address, self.workers)
        super().setup()

    def _setup_cell(self, step: int) -> None:
        """Instead of a cell here: N workers."""
        from flgd.training.cell_worker import CellWorker
        from flgd.training.ray_engine import remote_class

        self._next_step = step
        self._next_scene = next_scene_id(self.actions.rows)
        self.store.remember_states = self.workers   # each worker's last next state, their cycles interleaved
        if self.engine.cpus < self.workers:
            self.progress.message(f"flgd train: the Ray cluster has {self.engine.cpus:g} CPUs for {self.workers} "
                                  f"workers of one CPU each: the rest wait until CPUs free up")
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        if not self.address and self.workers + 1 > cores:
            # the local cluster gives every worker a CPU slot anyway: they and the learner share the cores
            self.progress.message(f"flgd train: {self.workers} workers and the learner on {cores} cores: they share "
                                  f"them, so workers beyond {max(1, cores - 1)} add little (docs/"
                                  f"training-and-evaluation.md, 'Training on many simulated cells')")
        self._worker_class = remote_class(self.engine.ray, CellWorker, cpus=1.0)
        self.slots = [_WorkerSlot(i) for i in range(self.workers)]
        for slot in self.slots:
            self._spawn(slot)

    def _begin_segment(self, step: int) -> None:
        super()._begin_segment(step)
        segment = self.run_info["segments"][-1]
        segment.update({"workers": self.workers, "ray_address": self.address or "local",
                        "ray_cpus": self.engine.cpus})
        self._write_run_info("running")

    def _spawn(self, slot: _WorkerSlot) -> None:
        """A fresh actor in ``slot`` (its first, or the replacement of a lost one), with the learner's weights."""
        version, ref = self._weights()
        slot.actor = self._worker_class.remote(self.config, self.settings, slot.index, slot.incarnation,
                                               self.segment, ref, version, self._next_step)
        slot.version = version
        slot.scene = None

    def _weights(self) -> tuple[int, Any]:
        """The learner's newest weights in Ray's object store (put once per version, shared by every worker)."""
        version = int(self.learner.updates)
        if self._weights_ref is None or self._weights_ref[0] != version:
            weights = {k: v.detach().to("cpu", copy=True) for k, v in self.learner.online.state_dict().items()}
            self._weights_ref = (version, self.engine.ray.put(weights))
        return self._weights_ref

    def _submit(self, slot: _WorkerSlot) -> Any:
        self.store.check_space()  # StoreError before a worker acts on a cycle that could not be stored
        sync_every = max(1, self.config.learning.sync_every)
        if self.learner.updates - slot.version >= sync_every:
            version, ref = self._weights()
            slot.version = version
            return slot.actor.collect.remote(self._next_step, ref, version)
        return slot.actor.collect.remote(self._next_step)

    # ------------------------------------------------------------------ the loop
    def train(self) -> int:
        from flgd.training.ray_engine import worker_lost_errors

        ray = self.engine.ray
        lost = worker_lost_errors(ray)
        start_step, t0 = self._next_step, time.monotonic()
        target = self.settings.steps
        if start_step >= target:
            self.progress.message(f"flgd train: already at step {start_step} >= --steps {target}; nothing to do")
        self.progress.start(start_step, target)
        in_flight: dict[Any, _WorkerSlot] = {}
        if start_step < target:
            in_flight = {self._submit(slot): slot for slot in self.slots}
        while self._next_step < target and not self.stop_signals:
            ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=POLL_SECONDS)
            if not ready:
                self._show(start_step, t0)
                continue
            ref = ready[0]
            slot = in_flight.pop(ref)
            try:
                report = ray.get(ref)
            except lost as exc:
                self._replace(slot, exc)
                in_flight[self._submit(slot)] = slot
                continue
            stored = self._take(slot, report)
            # the worker's next cycle starts before this one is learned from: the learner's updates and the
            # worker's cycle run side by side (the worker acts with weights one action older)
            if self._next_step < target:
                in_flight[self._submit(slot)] = slot
            self._learn(stored)
            self._show(start_step, t0)
        interrupted = bool(self.stop_signals) and self._next_step < target
        self._show(start_step, t0, force=True)
        self.progress.finish()
        self.final_checkpoint()
        self._write_run_info("interrupted" if interrupted else "finished")
        dropped = len(in_flight)
        self.progress.message(f"flgd train: {'interrupted' if interrupted else 'finished'} at step {self._next_step}, "
                              f"{self.learner.updates} updates, {self.workers} workers"
                              + (f" ({dropped} cycles in flight dropped)" if dropped and interrupted else "")
                              + f"; log {self.out / LOG_FILE}, curve {self.out / CURVE_FILE}")
        return EXIT_INTERRUPTED if interrupted else EXIT_OK

    def _take(self, slot: _WorkerSlot, report: WorkerReport) -> list[tuple[_WorkerSlot, Any, dict, float]]:
        """Store a worker's cycle under the run's next step (``_learn`` learns from it and logs it); a cycle that
        raised in the worker stops the run after its rows are stored and learned from, as it does in one
        process."""
        slot.cpu_seconds = slot.cpu_before + report.cpu_seconds
        slot.objects = report.objects
        for key, version, index in report.decisions:  # the double-DQN a' the worker found, for the learner
            self.learner.note_greedy(key, version, index)
        for kind, event, message in report.notes:
            self.progress.message(f"flgd train: worker {slot.index}: {message}")
            if event:
                self.store.record_event(kind, f"worker {slot.index}: {event}")
        stored = []
        for cycle in report.cycles:
            if self._next_step >= self.settings.steps:
                break  # a cycle beyond --steps (several workers were in flight): not taken
            stored.append(self._store_cycle(slot, cycle))
            slot.failures_in_a_row = 0
        if report.error:
            slot.last_error = report.error
            self._learn(stored)
            raise RuntimeError(f"worker {slot.index}: {report.error}")
        return stored

    def _store_cycle(self, slot: _WorkerSlot, cycle: CollectedCycle) -> tuple[_WorkerSlot, Any, dict, float]:
        """Commit one collected cycle under the run's next step; its transition goes to the replay and
        schedules the learner's updates (``notify_new_transition``), which ``_learn`` runs."""
        row = dict(cycle.row, step=self._next_step)
        transition = self._relinked(slot, cycle.transition)
        t_store = time.perf_counter()
        tid = self.store.commit_cycle(row, transition)
        if transition is not None:
            self.replay.add(transition, tag=tid)
            self.learner.notify_new_transition()
            if transition.next_state is None:
                self._last_states.pop(slot.index, None)
            else:
                self._last_states[slot.index] = transition.next_state
        t_store = time.perf_counter() - t_store
        self.store.note_store_time(row["step"], t_store)
        self._next_step += 1
        return slot, cycle, row, t_store

    def _learn(self, stored: list[tuple[_WorkerSlot, Any, dict, float]]) -> None:
        """The updates the stored cycles scheduled (``learning.updates_per_action`` each), then their rows in
        actions.csv (a fault's row stays in the store's action log only, as in one process)."""
        t_update = time.perf_counter()
        updates = self.learner.update_pending()
        t_update = time.perf_counter() - t_update
        for slot, cycle, row, t_store in stored:
            if cycle.outcome == CycleOutcome.FAULT:
                slot.scene = None
                continue
            slot.cycles += 1
            if slot.scene is None or slot.scene[0] != cycle.scene:  # a new scene of this worker: a new run-wide id
                slot.scene = (cycle.scene, self._next_scene)
                self._next_scene += 1
            self._log_step(_RowRecord(row, cycle), _SceneOf(cycle.objects_left, slot.scene[1], cycle.scene_kind),
                           updates, t_update, t_store)

    def _relinked(self, slot: _WorkerSlot, transition: Transition) -> Transition:
        """The transition with its state replaced by the very object stored as this worker's last next state,
        when it is that state (same pixels): the store, which remembers one recent next state per worker, then
        keeps it once, as in one process, instead of a second copy per action -- also when other workers'
        cycles were stored in between."""
        previous = self._last_states.get(slot.index)
        if transition is None or previous is None:
            return transition
        state = transition.state
        if previous.height.shape == state.height.shape and np.array_equal(previous.height, state.height) \
                and np.array_equal(previous.color, state.color):
            same = transition.next_state is transition.state
            return dataclasses.replace(transition, state=previous, next_state=previous if same
                                       else transition.next_state)
        return transition

    def _replace(self, slot: _WorkerSlot, exc: BaseException) -> None:
        """A lost worker: a fresh one in its place (new seeds), said and kept in the events."""
        slot.failures_in_a_row += 1
        slot.replacements += 1
        slot.last_error = _describe_loss(exc)
        what = f"worker {slot.index} lost ({slot.last_error}); its cycle in flight is dropped"
        if slot.failures_in_a_row > MAX_REPLACEMENTS:
            raise RuntimeError(f"{what}; replaced {MAX_REPLACEMENTS} times in a row without a completed cycle: "
                               f"stopping the run")
        self.progress.message(f"flgd train: {what}; starting a new one")
        self.store.record_event("worker", what)
        try:
            self.engine.ray.kill(slot.actor)
        except Exception:  # already gone
            pass
        slot.cpu_before = slot.cpu_seconds
        slot.incarnation += 1
        self._last_states.pop(slot.index, None)
        self._spawn(slot)

    # ------------------------------------------------------------------ records
    def _alive(self) -> int:
        return sum(1 for s in self.slots if not s.failures_in_a_row)

    def _show(self, start_step: int, t0: float, force: bool = False) -> None:
        done = self._next_step - start_step
        rate = done / max(1e-9, time.monotonic() - t0)
        eta = (self.settings.steps - self._next_step) / rate if rate > 0 else math.inf
        objects = "/".join("-" if s.objects is None else str(s.objects) for s in self.slots)
        fields = self._status(rate if done else None, eta if done else None, objects=objects)
        fields["workers"] = f"{self._alive()}/{self.workers}"
        self.progress.show(self._next_step, fields, force=force)

    def _segment_run_info(self) -> dict[str, Any]:
        return {"worker_stats": [{"worker": s.index, "cycles": s.cycles, "replacements": s.replacements,
                             "cpu_seconds": round(s.cpu_seconds, 1), "last_error": s.last_error}
                            for s in self.slots]}

    def close(self) -> None:
        try:
            super().close()
        finally:
            if self.engine is not None:
                self.engine.stop()
                self.engine = None


class _RowRecord:
    """A stored worker row seen as the CycleRecord fields ``TrainingRun._log_step`` reads."""

    def __init__(self, row: dict, cycle: CollectedCycle) -> None:
        self._row = row
        self.outcome = cycle.outcome
        self.primitive = cycle.primitive
        self.success = cycle.success

    def row(self) -> dict:
        return self._row


@dataclasses.dataclass
class _SceneOf:
    objects_left: int | None
    scene: int
    scene_kind: str


def _describe_loss(exc: BaseException) -> str:
    """One line on why a worker's call failed: Ray's first line, or the error raised inside the worker."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException) and not isinstance(cause, type(exc)):
        return f"{type(cause).__name__}: {cause}".splitlines()[0][:300]
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}"[:300]
