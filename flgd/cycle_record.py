"""What one cycle did (``CycleRecord``, its action-log row) and how a cell's result is read into it."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Callable

import numpy as np

from flgd.actions import Action
from flgd.cell import STOPPED_ON_REQUEST, ExecutionResult
from flgd.clutter import grasp_reward
from flgd.config import CellConfig
from flgd.plans import place_is_home

__all__ = ["CycleOutcome", "CycleRecord", "PhaseTimer", "UNSTABLE_MARK", "on_cell_clock", "held_at_place", "was_stopped", "unstable_failure",
           "float_or_none"]

# ExecutionResult.failure containing this word means the simulation blew up: never learn from it.
UNSTABLE_MARK = "unstable"


class CycleOutcome(StrEnum):
    """How a cycle ended; the value is what the action log's ``outcome`` column holds."""

    EXECUTED = "executed"    # the action ran (it may have failed: ``success``, ``failure``)
    REFUSED = "refused"      # the safety envelope refused its plan: nothing moved
    FAULT = "fault"          # the cell faulted during it
    DISCARDED = "discarded"  # the simulation blew up: nothing learned, a new scene
    STOPPED = "stopped"      # a stop request interrupted it
    STUCK = "stuck"          # the agent gave up on the scene
    EMPTY = "empty"          # nothing to act on: the workspace is clear


@dataclass
class CycleRecord:
    """What one cycle did; ``row()`` is its action-log row."""

    outcome: CycleOutcome
    step: int | None = None
    time: float = 0.0
    backend: str = ""
    action: Action | None = None
    kind: str | None = None          # grasp / push / shift as executed
    reward: float | None = None
    success: bool | None = None      # grasps only
    mu: int | None = None
    eta: int | None = None
    rule: str = ""
    epsilon: float | None = None
    q_value: float | None = None
    refused: str = ""
    failure: str = ""
    contact_stop_mm: float | None = None  # a guarded move of the action stopped this far short of its pose
    done: bool = False
    duration: float = 0.0
    cell_time: float | None = None   # the cycle's plans on the cell's own clock (s); None: nothing executed
    gripper_time: float | None = None   # the part of ``cell_time`` the gripper's steps took
    decide_hidden: float | None = None  # seconds of this action's decision made while the arm placed the last pick
    timings: dict[str, float] = field(default_factory=dict)
    transition_id: int | None = None
    refill_needed: bool = False      # "empty" on a cell that cannot reset its own scene
    relaid: bool = False             # "stuck" on a cell that laid out a new scene by itself
    policy: int | None = None        # the gate's id of the policy credited (None: epsilon-random, no gate)

    @property
    def primitive(self) -> str | None:
        return None if self.action is None else self.action.primitive

    def row(self) -> dict[str, Any]:
        a = self.action
        out: dict[str, Any] = {
            "step": self.step, "time": self.time, "backend": self.backend, "outcome": str(self.outcome),
            "primitive": None if a is None else a.primitive, "kind": self.kind,
            "row": None if a is None else a.row, "col": None if a is None else a.col,
            "rotation": None if a is None else a.rotation, "reward": self.reward,
            "success": None if self.success is None else int(self.success),
            "mu": self.mu, "eta": self.eta, "rule": self.rule, "epsilon": self.epsilon,
            "q_value": self.q_value, "refused": self.refused, "failure": self.failure,
            "contact_stop_mm": self.contact_stop_mm,
            "done": int(self.done), "duration": self.duration, "policy": self.policy, "cell_time": self.cell_time,
            "gripper_time": self.gripper_time, "decide_hidden": self.decide_hidden,
        }
        for phase, seconds in self.timings.items():
            if phase != "store":
                out[f"t_{phase}"] = seconds
        return out


def on_cell_clock(record: CycleRecord, result: ExecutionResult) -> ExecutionResult:
    """Add a plan's time on the cell's own clock (``ExecutionResult.duration``, its gripper's part) to the cycle's."""
    record.cell_time = (record.cell_time or 0.0) + result.duration
    record.gripper_time = (record.gripper_time or 0.0) + result.gripper_time
    return result


def held_at_place(released: ExecutionResult, grasped: ExecutionResult, config: CellConfig) -> tuple[bool, str]:
    """Whether the object measured as held at home was still held at the place pose, before the fingers
    opened (the width read at ``flgd.plans.PLACE_CHECK_LABEL``), and if not, the failure text saying so.

    Why: the width at home says the object was lifted; only the width at the place says it was picked.  A
    place plan that reported no width proves nothing held.  With the place at home (``place_is_home``) the
    grasp plan ``grasped`` read it there, over the bin, and the place plan reads none."""
    widths = grasped.widths if place_is_home(config) else released.widths
    width = float(widths[-1]) if widths else math.nan
    if grasp_reward(width, config.gripper) > 0:
        return True, ""
    shown = f"{width * 1000:.1f} mm" if math.isfinite(width) else "no reading"
    return False, (f"dropped: the object slipped out of the gripper between the home and the place pose "
                   f"(width at the place pose {shown})")


def was_stopped(result: ExecutionResult) -> bool:
    return not result.completed and STOPPED_ON_REQUEST in result.failure


def unstable_failure(result: ExecutionResult) -> str:
    """The failure text if the cell reported an unstable simulation, else ''."""
    return result.failure if not result.completed and UNSTABLE_MARK in result.failure.lower() else ""


def float_or_none(v: Any) -> float | None:
    if v is None:
        return None
    try:
        f = float(np.asarray(v))
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


class PhaseTimer:
    """The cycle's phases timed on the wall clock (``CycleRecord.timings``), each reported to ``on_phase``."""

    def __init__(self, timings: dict[str, float], on_phase: Callable[[str], None] | None):
        self.timings = timings
        self.on_phase = on_phase

    def phase(self, name: str) -> "_Phase":
        return _Phase(self, name)

    def discount(self, name: str, seconds: float) -> None:
        """Take ``seconds`` out of phase ``name``: time inside it that the cell stood waiting for the controller
        (it stays in the cycle's duration, as the controller's own time)."""
        self.timings[name] = self.timings.get(name, 0.0) - seconds


class _Phase:
    def __init__(self, timer: PhaseTimer, name: str):
        self.timer, self.name = timer, name

    def __enter__(self) -> None:
        self.t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        t = self.timer.timings
        t[self.name] = t.get(self.name, 0.0) + time.perf_counter() - self.t0
        if self.timer.on_phase is not None:
            self.timer.on_phase(self.name)
