"""The cell side of a training run: one simulated cell running the daemon's cycle, scene after scene.

``flgd train`` runs one of these in its own process; ``flgd train --workers N`` runs one in each worker
(``flgd.training.cell_worker``).  Both get the same scenes, curriculum, give-up rule and fault handling from
here, so a distributed run collects what a single-process run collects; only who stores the transitions and
when the learner runs differ.

What it adds to ``CycleRunner.run_once``: the scene an action acted on (numbered, with its object count and
kind, noted before the runner replaces an ended scene), a new scene after ``give_up_after`` actions without a
successful grasp, and recovery from a cell fault or a simulator error (a new scene; an error after
``MAX_CONSECUTIVE_FAULTS`` in a row).
"""

from __future__ import annotations

import sys
import traceback
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from flgd.config import CellConfig
from flgd.cycle_record import CycleOutcome

if TYPE_CHECKING:
    from flgd.cell import Cell
    from flgd.cycle_parts import CycleAgent, CycleLearner, CycleStore
    from flgd.cycle_record import CycleRecord
    from flgd.learning.replay import PrioritizedReplay
    from flgd.training.settings import RunSettings

__all__ = ["TrainingCycle", "TrainingCell", "MAX_CONSECUTIVE_FAULTS"]

MAX_CONSECUTIVE_FAULTS = 5

# note(kind, event, message): a fault or a give-up; ``event`` for the run's events ('' = none), ``message`` for
# its operator
Note = Callable[[str, str, str], None]


@dataclass
class TrainingCycle:
    """One step of a training run: the cycle's record and the scene it acted on."""

    record: CycleRecord
    objects_left: int | None  # after the action, in its scene (None for a discarded action)
    scene: int
    scene_kind: str


class TrainingCell:
    """A simulated cell, its cycle runner and the scene bookkeeping of a training run (module doc)."""

    def __init__(self, config: CellConfig, settings: RunSettings, agent: CycleAgent, *, step: int, scene: int,
                 curriculum_seed: int, note: Note, store: CycleStore | None = None,
                 replay: PrioritizedReplay | None = None, learner: CycleLearner | None = None) -> None:
        from flgd.cell import make_cell
        from flgd.cycle import CycleRunner

        self.config = config
        self.settings = settings
        self.agent = agent
        self.note = note
        self.scene = scene
        self.consecutive_faults = 0
        self.actions_without_grasp = 0  # in the current scene (give_up_after)
        # (objects, scene kind) of the scene the current cycle acts on, noted before the runner resets it
        self._cycle_scene: tuple[int | None, str] = (None, "")
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
        self.runner = CycleRunner(config, cell, agent, store=store, replay=replay, learner=learner, step=step,
                                  backend=config.backend, on_phase=self._on_phase,
                                  decide_while_placing=False)   # each decision after the updates its action owes

    @property
    def cell(self) -> Cell:
        """The cell the runner acts on (a caller may wrap it, e.g. to inject faults)."""
        return self.runner.cell

    @property
    def step(self) -> int:
        return self.runner.step

    @property
    def scene_of_cycle(self) -> tuple[int | None, str]:
        """(objects, kind) of the scene the last cycle acted on."""
        return self._cycle_scene

    def cycle(self) -> TrainingCycle | None:
        """Run one cycle; None when it took no step (an empty table, a fault recovered from).

        Raises StoreError (a run stops on it with a checkpoint) and RuntimeError after
        ``MAX_CONSECUTIVE_FAULTS`` faults in a row."""
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
