"""Scripted agents for the cycle's tests: they choose the action a test wants and implement the rest of the
cycle's agent protocol (``flgd.cycle_parts.CycleAgent``) as a plain agent would."""

from __future__ import annotations

import numpy as np

from flgd.actions import Action
from flgd.learning.agent import Decision
from flgd.perception import Heightmaps


def scripted_decision(action: Action, heightmaps: Heightmaps, rule: str = "scripted") -> Decision:
    """A decision for ``action`` on ``heightmaps`` with flat Q-maps and open masks (what the cycle logs of it)."""
    h, w = np.asarray(heightmaps.height).shape
    ones = np.ones((h, w), np.uint8)
    return Decision(action, np.zeros((action.rotations, 2, h, w), np.float32), ones, ones, 0.0, rule, 0.0)


class ScriptedAgentBase:
    """Keeps the outcomes it is told (``outcomes``), never swaps weights and never gives up; a subclass decides."""

    def __init__(self) -> None:
        self.outcomes: list[bool | None] = []

    def decide(self, heightmaps: Heightmaps, step: int) -> Decision | None:
        raise NotImplementedError

    def record_outcome(self, action: Action, grasp_success: bool | None, **outcome) -> None:
        self.outcomes.append(grasp_success)

    def maybe_swap_weights(self) -> bool:
        return False

    def reset_episode(self) -> None:
        pass

    def stuck_reason(self) -> str:
        return ""

    def outcome_state(self):
        return list(self.outcomes)

    def restore_outcome_state(self, state) -> None:
        self.outcomes = list(state)
