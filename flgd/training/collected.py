"""What a training cell hands its run's loop: the cycles it ran, its notes and its decisions.

The cell's cycle runner writes into stand-ins for the store and the learner (``CollectingStore``,
``DecisionNotes``) instead of the run's own: the run's loop keeps every collected cycle in the one store,
replay and learner (``flgd.cycle_commit``), whether the cell runs in the learner's process or in a Ray worker,
so the two collectors differ only in where the cell runs.  Everything here is plain data, sent between
processes by Ray.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Protocol

from flgd.cycle_record import CycleOutcome

if TYPE_CHECKING:
    from flgd.learning.agent import Decision
    from flgd.learning.replay import Transition
    from flgd.perception import Heightmaps

__all__ = ["CollectedCycle", "CellReport", "Greedy", "WriteAhead", "CollectingStore", "DecisionNotes"]

# (replay key of the state, update count of the weights that decided, the greedy a' index or None)
Greedy = tuple[bytes, int, "tuple[int, int, int, int] | None"]


@dataclass
class CollectedCycle:
    """One step as its cell saw it; the run's loop gives it the run's step when it keeps it."""

    row: dict[str, Any]  # CycleRecord.row()
    transition: Transition | None  # None: nothing to learn (a refused action is kept, faults not)
    outcome: CycleOutcome
    primitive: str | None
    success: bool | None
    objects_left: int | None = None
    scene: int = 0  # the cell's own scene number
    scene_kind: str = ""


@dataclass
class CellReport:
    """What one cycle of a training cell returns to the run's loop."""

    cell: int = 0  # the worker's index (0 in one process)
    incarnation: int = 0  # of that worker (a replacement starts its own scenes and states afresh)
    cycles: list[CollectedCycle] = field(default_factory=list)
    notes: list[tuple[str, str, str]] = field(default_factory=list)  # (kind, event, message)
    # the greedy a' of each decision, for the learner's double-DQN target cache (``DQNUpdate.note_greedy``)
    decisions: list[Greedy] = field(default_factory=list)
    weights_version: int = -1
    cpu_seconds: float = 0.0  # of the cell's process since it started
    objects: int | None = None  # objects on its table now
    error: str = ""  # the cycle raised: the run stops after keeping what was collected (rows and notes)
    # the step of a write-ahead intent the cycle left open (it raised after the intent, before a row): that step
    # is used up -- the store marks it interrupted at its next write -- and the run goes on after it
    open_intent: int | None = None


class WriteAhead(Protocol):
    """The run's store as far as a cell in its process uses it before a cycle moves (``flgd.store.Store``)."""

    def check_space(self) -> None: ...

    def record_intent(self, row: dict[str, Any]) -> None: ...


class CollectingStore:
    """The cell's stand-in for the store (a ``CycleStore``): the cycle's rows and transitions are kept for the
    run's loop, an event goes to the cell's notes (``on_event``).

    ``write_ahead``: the run's store when the cell runs in its process -- the space check and the write-ahead
    intent reach it before the arm moves, as in the daemon; a Ray worker has none (the loop checks the space
    before it asks for a cycle)."""

    def __init__(self, on_event: Callable[[str, str, str], None], write_ahead: WriteAhead | None = None) -> None:
        self.committed: list[tuple[dict[str, Any], Transition | None]] = []
        self._on_event = on_event
        self._write_ahead = write_ahead
        self._open_intent: int | None = None

    def check_space(self) -> None:
        if self._write_ahead is not None:
            self._write_ahead.check_space()

    def record_intent(self, row: dict[str, Any]) -> None:
        if self._write_ahead is not None:
            self._write_ahead.record_intent(row)
            self._open_intent = int(row["step"])

    def record_event(self, kind: str, message: str) -> None:
        self._on_event(kind, message, message)

    def commit_cycle(self, row: dict[str, Any], transition: Transition | None = None, priority: float | None = None) -> None:
        self.committed.append((dict(row), transition))
        if self._open_intent is not None and row.get("step") == self._open_intent:
            self._open_intent = None
        return None

    def note_store_time(self, step: int, seconds: float) -> None:
        pass  # the run's loop times its own commit of the row

    def forget_last_state(self) -> None:
        pass  # the run's loop links a cell's states (``flgd.training.run``)

    def take(self) -> list[tuple[dict[str, Any], Transition | None]]:
        out, self.committed = self.committed, []
        return out

    def take_open_intent(self) -> int | None:
        """The step of an intent written and not completed since the last call (None: none)."""
        out, self._open_intent = self._open_intent, None
        return out


class DecisionNotes:
    """The cell's stand-in for the learner (a ``CycleLearner``): it keeps each decision's greedy a' for the run's
    learner; a new transition schedules nothing here (the run's loop tells the learner when it keeps the cycle),
    and nothing is waited for."""

    def __init__(self) -> None:
        self.notes: list[Greedy] = []

    def note_decision(self, state: Heightmaps, decision: Decision, weights_version: int) -> None:
        from flgd.learning.replay import state_key

        if decision.greedy is not None and weights_version >= 0:
            g = decision.greedy
            self.notes.append((state_key(state), int(weights_version), (int(g[0]), int(g[1]), int(g[2]), int(g[3]))))

    def notify_new_transition(self) -> None:
        pass

    def wait_idle(self, timeout: float | None = None) -> bool:
        return True

    def take(self) -> list[Greedy]:
        out, self.notes = self.notes, []
        return out
