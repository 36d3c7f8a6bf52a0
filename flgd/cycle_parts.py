"""What the cycle needs of its collaborators, and nothing more.

The daemon, ``flgd train``, ``flgd eval`` and a training worker each run ``flgd.cycle.CycleRunner`` with their own
parts: the real store, or a worker's stand-in that collects the rows for the learner's store; the real learner, or
the notes a worker keeps of its decisions for the learner it feeds.  Each part implements the whole protocol (a
stand-in with no use for a call does nothing in it), so the cycle never asks whether a part can do something.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    import numpy as np

    from flgd.actions import Action
    from flgd.learning.agent import Decision
    from flgd.learning.replay import Transition
    from flgd.perception import Heightmaps

__all__ = ["CycleAgent", "CycleStore", "CycleReplay", "CycleLearner"]


class CycleAgent(Protocol):
    """Decides on a heightmap and learns what its action did (``flgd.learning.agent.Agent``)."""

    def decide(self, heightmaps: Heightmaps, step: int) -> Decision | None:
        """The next action on ``heightmaps``; None when nothing is left to try (``stuck_reason`` says why)."""
        ...

    def record_outcome(self, action: Action, grasp_success: bool | None, *, move_changed: bool | None = None,
                       height_after: np.ndarray | None = None, kind: str | None = None) -> None:
        ...

    def maybe_swap_weights(self) -> bool:
        """Act with the newest weights handed over, if any (True when it changed)."""
        ...

    def reset_episode(self) -> None:
        """A new scene: forget what was learned about the last one."""
        ...

    def stuck_reason(self) -> str:
        """Why the cell should give up on this scene ('' = it should not)."""
        ...

    def outcome_state(self) -> object:
        """What ``record_outcome`` changes, copied, so that a provisional outcome can be taken back."""
        ...

    def restore_outcome_state(self, state: object) -> None:
        ...


class CycleStore(Protocol):
    """Where a cycle's action and transition are recorded (``flgd.store.Store``)."""

    def check_space(self) -> None:
        """Raise (a StoreError) before any motion if the cycle's writes would not fit."""
        ...

    def record_intent(self, row: dict) -> None:
        """The decided action, written before the cell moves."""
        ...

    def commit_cycle(self, row: dict, transition: Transition | None = None,
                     priority: float | None = None) -> int | None:
        """The finished cycle's row and transition; the transition's id where it has one."""
        ...

    def note_store_time(self, step: int, seconds: float) -> None:
        ...

    def forget_last_state(self) -> None:
        """The next transition starts from a fresh capture (its state is not the last one's next state)."""
        ...

    def record_event(self, kind: str, message: str) -> None:
        ...


class CycleReplay(Protocol):
    """Where a stored transition is sampled from (``flgd.learning.replay.PrioritizedReplay``)."""

    def add(self, transition: Transition, priority: float | None = None, tag: int | None = None) -> int:
        """Keep ``transition`` (``tag``: its id in the store); its slot."""
        ...


class CycleLearner(Protocol):
    """What the cycle tells the learner (``flgd.learning.learner.Learner``)."""

    def notify_new_transition(self) -> None:
        """A transition went into the replay: schedule its updates."""
        ...

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Return once the scheduled updates ran (``learning.wait_for_updates``)."""
        ...

    def note_decision(self, state: Heightmaps, decision: Decision, weights_version: int) -> None:
        """The greedy a' the decision found on ``state``, for the targets of the transitions that end there."""
        ...
