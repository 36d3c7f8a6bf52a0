"""The cell side of a training run: one simulated cell running the daemon's cycle, scene after scene.

``flgd train`` runs one of these in its own process, ``flgd train --workers N`` one in each Ray worker
(``flgd.training.cell_worker``); either way ``collect`` runs one cycle and returns what it did as a
``CellReport`` for the run's loop (``flgd.training.run``), which keeps it in the store, the replay and
``actions.csv`` and runs the learner.  So both get the same scenes, curriculum, give-up rule and fault
handling, and a cycle is kept one way (``flgd.cycle_commit``).

What it adds to ``CycleRunner.run_once``: the scene an action acted on (numbered, with its object count and
kind, noted before the runner replaces an ended scene), a new scene after ``give_up_after`` actions without a
successful grasp, and recovery from a cell fault or a simulator error (a new scene; an error after
``MAX_CONSECUTIVE_FAULTS`` in a row).
"""

from __future__ import annotations

import sys
import time
import traceback
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from flgd.config import CellConfig
from flgd.cycle_record import CycleOutcome
from flgd.training.collected import CellReport, CollectedCycle, CollectingStore, DecisionNotes, WriteAhead

if TYPE_CHECKING:
    from flgd.cell import Cell
    from flgd.cycle_parts import CycleAgent
    from flgd.cycle_record import CycleRecord
    from flgd.training.settings import RunSettings

__all__ = ["TrainingCycle", "TrainingCell", "MAX_CONSECUTIVE_FAULTS"]

MAX_CONSECUTIVE_FAULTS = 5



@dataclass
class TrainingCycle:
    """One step of a training run: the cycle's record and the scene it acted on."""

    record: CycleRecord
    objects_left: int | None  # after the action, in its scene (None for a discarded action)
    scene: int
    scene_kind: str


class TrainingCell:
    """A simulated cell, its cycle runner and the scene bookkeeping of a training run (module doc)."""

    def __init__(self, config: CellConfig, settings: RunSettings, agent: CycleAgent, *, step: int,
                 curriculum_seed: int, write_ahead: WriteAhead | None = None,
                 wrap_cell: Callable[[Cell], Cell] | None = None) -> None:
        """``write_ahead``: the run's store when the cell runs in its process (``CollectingStore``);
        ``wrap_cell``: a wrapper around the simulated cell (tests inject faults with it)."""
        from flgd.cell import make_cell
        from flgd.cycle import CycleRunner

        self.config = config
        self.settings = settings
        self.agent = agent
        self.scene = 0
        self.consecutive_faults = 0
        self.actions_without_grasp = 0  # in the current scene (give_up_after)
        # (objects, scene kind) of the scene the current cycle acts on, noted before the runner resets it
        self._cycle_scene: tuple[int | None, str] = (None, "")
        self._notes: list[tuple[str, str, str]] = []
        self.store = CollectingStore(self.note, write_ahead)
        self.decisions = DecisionNotes()
        cell = make_cell(config)
        if settings.curriculum:
            from flgd.curriculum import Curriculum, CurriculumCell
            from sim_cell.cell import preset_scenes

            curriculum = Curriculum()
            cell.set_object_count(curriculum.object_count(step))
            cell.reset_scene()
            cell = CurriculumCell(cell, curriculum, lambda: self.runner.step, preset_scenes(),
                                  np.random.default_rng(curriculum_seed))
            cell.scene_kind = f"random {curriculum.object_count(step)}"
        if wrap_cell is not None:
            cell = wrap_cell(cell)
        self.runner = CycleRunner(config, cell, agent, store=self.store, learner=self.decisions, step=step,
                                  backend=config.backend, on_phase=self._on_phase,
                                  decide_while_placing=False)   # each decision after the updates its action owes

    def note(self, kind: str, event: str, message: str) -> None:
        """A fault or a give-up: ``event`` for the run's events ('' = none), ``message`` for its operator."""
        self._notes.append((kind, event, message))

    @property
    def cell(self) -> Cell:
        """The cell the runner acts on (a caller may wrap it, e.g. to inject faults)."""
        return self.runner.cell

    @property
    def objects(self) -> int:
        """Objects on its table now."""
        return int(self.cell.object_count)

    @property
    def step(self) -> int:
        return self.runner.step

    @property
    def scene_of_cycle(self) -> tuple[int | None, str]:
        """(objects, kind) of the scene the last cycle acted on."""
        return self._cycle_scene

    def collect(self, step: int) -> CellReport:
        """One cycle at the run's ``step`` (exploration and curriculum follow it) and what it did: its rows and
        transitions, notes and decisions.  An error that ends the cell ("N cell faults in a row", a store's
        space check) is in ``error``; what the cycle collected before it is still sent."""
        self.runner.step = int(step)
        report = CellReport()
        scene = self.scene  # the scene this cycle acts on (a fault in it moves the loop to the next)
        cycle = None
        try:
            cycle = self.cycle()
        except Exception as exc:  # "N cell faults in a row", a full disk: the run stops after keeping the rows
            report.error = f"{type(exc).__name__}: {exc}"
        report.notes, self._notes = self._notes, []
        report.open_intent = self.store.take_open_intent()
        report.decisions = self.decisions.take()
        objects, kind = self._cycle_scene  # noted during this cycle's plan and judge phases
        for row, transition in self.store.take():
            # a row whose cycle then failed (a reset after it) still belongs to the scene it acted on
            report.cycles.append(CollectedCycle(row, transition, CycleOutcome(row.get("outcome")),
                                                row.get("primitive"),
                                                None if row.get("success") is None else bool(row["success"]),
                                                objects, scene, kind))
        if cycle is not None and report.cycles:
            last = report.cycles[-1]
            last.objects_left, last.scene, last.scene_kind = cycle.objects_left, cycle.scene, cycle.scene_kind
        report.cpu_seconds = time.process_time()
        report.objects = self.objects
        return report

    def cycle(self) -> TrainingCycle | None:
        """Run one cycle; None when it took no step (an empty table, a fault recovered from).

        Raises RuntimeError after ``MAX_CONSECUTIVE_FAULTS`` faults in a row."""
        from flgd.cell import CellFault
        from flgd.store import StoreError

        try:
            record = self.runner.run_once()
        except CellFault as exc:
            self._handle_fault(exc)
            self.scene += 1
            return None
        except StoreError:
            raise  # disk full, read-only ...: stop with a checkpoint rather than lose steps
        except Exception as exc:  # the simulator failing inside a cycle: log it, new scene, go on
            traceback.print_exc(file=sys.stderr)
            self._handle_fault(exc)
            self.scene += 1
            return None
        self.consecutive_faults = 0
        if record.outcome == CycleOutcome.EMPTY or record.step is None:
            self.scene += 1
            return None
        objects, kind = self._cycle_scene
        # a discarded action's scene blew up and was replaced: its object count means nothing
        out = TrainingCycle(record, None if record.outcome == CycleOutcome.DISCARDED else objects, self.scene, kind)
        if record.done or record.outcome == CycleOutcome.DISCARDED:  # the runner has started a new scene
            self.scene += 1
            self.actions_without_grasp = 0
        elif record.outcome == CycleOutcome.EXECUTED:
            self._maybe_give_up(record)
        return out

    # ------------------------------------------------------------------ scenes
    def _on_phase(self, name: str) -> None:
        """Note the scene an action acts on while it is still there: a cycle that ends its scene resets it
        before returning, so reading the cell afterwards would describe the next scene."""
        if name in ("plan", "judge"):
            cell = self.cell
            kind = getattr(cell, "scene_kind", f"random {self.settings.objects}") if name == "plan" \
                else self._cycle_scene[1]
            self._cycle_scene = (cell.object_count, kind)

    def _new_scene_state(self) -> None:
        self.runner.forget_state()
        self.agent.reset_episode()
        self.actions_without_grasp = 0

    def _handle_fault(self, exc: Exception) -> None:
        """A cell fault or a simulator error inside a cycle: recover, new scene; give up after several in a row."""
        from flgd.cell import CellFault

        self.consecutive_faults += 1
        what = str(exc) if isinstance(exc, CellFault) else f"{type(exc).__name__}: {exc}"
        self.note("fault", what, f"cell fault at step {self.runner.step}: {what}; recovering")
        while True:
            if self.consecutive_faults >= MAX_CONSECUTIVE_FAULTS:
                raise RuntimeError(f"{self.consecutive_faults} cell faults in a row; last: {what}")
            try:
                self.cell.recover()
                self.cell.reset_scene()
                break
            except Exception as again:  # recovering failed too: count it and try again
                self.consecutive_faults += 1
                what = f"recovery: {type(again).__name__}: {again}"
                self.note("fault", "", what)
        self._new_scene_state()

    def _maybe_give_up(self, record: CycleRecord) -> None:
        """A new scene after ``give_up_after`` actions in a row without a successful grasp.

        Why: a scene the policy cannot clear is otherwise kept for ever, and
        the move reward pays for shuffling its last objects about (each shift
        changes the heightmap by more than tau1): a fine-tune collapsed that
        way on a single block (BENCHMARKS.md, "Fine-tuning the shipped policy").
        """
        if record.primitive == "grasp" and record.success:
            self.actions_without_grasp = 0
            return
        self.actions_without_grasp += 1
        limit = self.settings.give_up_after
        if limit <= 0 or self.actions_without_grasp < limit:
            return
        what = (f"{self.actions_without_grasp} actions without a successful grasp at step {self.runner.step}, "
                f"{self.cell.object_count} objects left: new scene")
        self.note("give-up", what, what)
        self.scene += 1
        self.actions_without_grasp = 0
        try:
            self.cell.reset_scene()
        except Exception as exc:  # the simulator failing to lay out the new scene: recover as from a fault
            self._handle_fault(exc)
            return
        self._new_scene_state()

    def close(self) -> None:
        self.cell.close()
