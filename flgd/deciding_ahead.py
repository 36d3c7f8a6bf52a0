"""Deciding while the arm moves (``robot.decide_while_placing``): the next decision made on a picture taken on the
way home once the arm is out of the camera's view, or, from a cell that cannot take one while its arm moves, on a
picture taken at home while the arm places.

Why: the picture, the heightmaps and the decision then overlap the arm's motion instead of following it (a real
cell's picks per hour).  A decision made ahead rests on the pick's outcome recorded as held before the width at
home (or at the place) confirmed it; each path that finds otherwise takes that outcome back
(``CycleAgent.restore_outcome_state``) and the cycle goes on as it would have without deciding ahead.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol

import numpy as np

from flgd.actions import Action
from flgd.cell import STOPPED_ON_REQUEST, Cell, CellFault, ExecutionResult, Frame, FrameOnTheWay
from flgd.clutter import grasp_reward
from flgd.config import CellConfig
from flgd.cycle_parts import CycleAgent
from flgd.cycle_record import CycleRecord, PhaseTimer, on_cell_clock, unstable_failure
from flgd.perception import Heightmaps
from flgd.plans import Plan, plan_release
from flgd.safety import CheckedPlan, PlanRefused, check_plan

if TYPE_CHECKING:
    from flgd.learning.agent import Decision

__all__ = ["Ahead", "Thought", "DecidingAhead", "ToolInView", "last_width", "record_outcome"]

log = logging.getLogger("flgd.cycle")


class ToolInView(CellFault):
    """A frame was taken with the tool between the camera and the workspace (``flgd.camera_view``): never used."""


@dataclass(frozen=True)
class Ahead:
    """The next decision, made on ``state`` while the arm carried the last pick home or placed it."""

    state: Heightmaps
    decision: Decision | None
    stuck: str
    seconds: float   # what deciding took
    hidden: float    # the part of it the arm's motion covered


@dataclass(frozen=True)
class Thought:
    """What was thought while the arm carried a pick home and placed it: the picture taken on the way (``state``)
    and, unless it shows nothing left to grasp (``done``), the next decision, made after the pick's outcome was
    recorded as held (``provisional``: the agent before that, to take it back)."""

    state: Heightmaps
    done: bool
    decision: Decision | None = None
    stuck: str = ""
    seconds: float = 0.0   # what deciding took
    hidden: float = 0.0    # the part of it the carry and the place covered
    provisional: object | None = None


class _Cycle(Protocol):
    """What deciding ahead uses of the cycle it is part of (``flgd.cycle.CycleRunner``)."""

    config: CellConfig
    cell: Cell
    agent: CycleAgent
    last_frame: Frame | None
    _stop: threading.Event
    _ahead: Ahead | None
    _wrist_yaw: float | None

    def perceive(self, timer: PhaseTimer) -> Heightmaps: ...
    def _heightmaps(self, frame: Frame, timer: PhaseTimer) -> Heightmaps: ...
    def _execute(self, checked: CheckedPlan, on_frame: FrameOnTheWay | None = None) -> ExecutionResult: ...
    def _run_checked(self, plan: Plan, what: str) -> ExecutionResult: ...
    def _decide(self, state: Heightmaps) -> tuple[Decision | None, str]: ...
    def wait_for_learner(self) -> None: ...
    def _empty(self, hm: Heightmaps) -> bool: ...
    def _nothing_to_grasp(self, hm: Heightmaps) -> bool: ...
    def _think(self, record: CycleRecord, action: Action, frame: Frame, timer: PhaseTimer,
               perceived: Callable[[], None] = ...) -> Thought | None: ...
    def _held(self, action: Action, result: ExecutionResult) -> bool: ...


class DecidingAhead:
    """The cycle's methods that decide while the arm moves (a part of ``flgd.cycle.CycleRunner``)."""

    _ahead: Ahead | None   # the next decision, made ahead on the picture the next cycle starts from

    def _capture_at_home(self: _Cycle, timer: PhaseTimer) -> Heightmaps | None:
        """The next picture, taken at home with the picked object held (the arm out of view), or None when this
        cell cannot show where the tool was (``Frame.tool_position``) or showed it in view: then the arm places
        first and the picture is taken after, as without ``decide_while_placing``."""
        try:
            after = self.perceive(timer)
        except CellFault as exc:   # the tool in view, or a camera fault: place the pick first, capture after
            log.warning("decide while placing: %s", exc)
            return None
        return after if self.last_frame is not None and self.last_frame.tool_position is not None else None

    def _place_and_decide(self: _Cycle, record: CycleRecord, action: Action, after: Heightmaps,
                          timer: PhaseTimer, width: float | None = None) -> tuple[ExecutionResult, object | None]:
        """Place the picked object in a thread of its own while the next decision is made on ``after``.

        The decision rests on the outcome measured at home (held), recorded first; the agent as it was before is
        returned, so a drop found at the place can take that outcome back.  The arm stays at the place when a
        decision follows (the next plan starts there) and goes home when the workspace is empty."""
        done = self._empty(after)
        plan = plan_release(True, self.config, home=done, carry_yaw=self._wrist_yaw, width=width)
        if self._stop.is_set():
            return ExecutionResult(False, [], f"release: {STOPPED_ON_REQUEST}"), None
        try:
            checked = check_plan(plan, self.config)
        except PlanRefused as exc:
            raise CellFault(f"release plan refused by the safety envelope: {exc}") from exc
        outcome: dict[str, Any] = {}

        def place() -> None:
            try:
                outcome["result"] = self._execute(checked)
            except BaseException as exc:   # re-raised in the cycle's thread, after the decision
                outcome["error"] = exc

        mover = threading.Thread(target=place, name="flgd-place", daemon=True)
        mover.start()
        provisional: object | None = None  # the agent's outcome state, opaque here
        decided: tuple[Any, ...] | None = None
        failed: BaseException | None = None
        try:
            if not done and not self._stop.is_set():
                busy_from = time.perf_counter()
                provisional = self.agent.outcome_state()
                record_outcome(self.agent, action, True, True, after.height, record.kind)
                self.wait_for_learner()
                if not self._stop.is_set():
                    started = time.perf_counter()
                    decision, stuck = self._decide(after)
                    decided = (decision, stuck, time.perf_counter() - started, time.perf_counter() - busy_from)
        except BaseException as exc:   # raised once the arm has placed (or failed to): the cell's fault first
            failed = exc
        finally:
            mover.join()
        if "error" in outcome or failed is not None:
            if provisional is not None:
                self.agent.restore_outcome_state(provisional)
            if "error" in outcome and failed is not None:
                log.error("deciding while placing failed too: %r", failed)
            first = outcome["error"] if "error" in outcome else failed
            assert isinstance(first, BaseException)
            raise first
        released = on_cell_clock(record, outcome["result"])
        if decided is not None:
            decision, stuck, seconds, busy = decided
            before = busy - seconds   # the outcome and the learner's wait came first, the decision last
            hidden = min(seconds, max(0.0, released.duration - before))
            # the arm waited at the place for what the motion did not cover: the controller's time, not the cell's
            timer.discount("execute", max(0.0, busy - released.duration))
            self._ahead = Ahead(after, decision, stuck, seconds, hidden)
        return released, provisional

    def _grasp_and_think(self: _Cycle, record: CycleRecord, action: Action, checked: CheckedPlan,
                         timer: PhaseTimer) -> tuple[ExecutionResult, Thought | None, ExecutionResult | None]:
        """Run the grasp plan in a thread of its own and think while it carries the pick home and on to the place.

        A cell that can (``Cell.execute_and_capture``) hands over a picture taken on the way home once the arm is
        out of view; it is perceived and the next action decided on it while the arm moves on.  Once the picture
        is accepted and the width at home says held (and no stop was asked for), the same thread goes on to the
        place (``plan_release``, staying there) without waiting for the decision, which needs nothing of that
        move: the third result, None when it did not run.  The thought is returned only when the pick was held and
        placed that way; otherwise the outcome recorded ahead is taken back (and the cycle goes on as without
        it, or re-raises what was raised).  The arm waits only for what its motion, home and on to the place, did
        not cover: the controller's time, not the cell's."""
        frames: queue.Queue[tuple[Frame, float] | None] = queue.Queue()
        outcome: dict[str, Any] = {}
        handed_over, seen, judged = threading.Event(), threading.Event(), threading.Event()
        stood = 0.0   # wall seconds the arm stood at home for the picture to be accepted or refused

        def hand_over(frame: Frame, at: float) -> None:
            handed_over.set()
            frames.put((frame, at))

        def carry() -> None:
            nonlocal stood
            try:
                result = outcome["result"] = self._execute(checked, on_frame=hand_over)
                if handed_over.is_set():   # a refused picture is taken again where the arm stands now
                    waiting_from = time.perf_counter()
                    judged.wait()
                    stood = time.perf_counter() - waiting_from
                if (seen.is_set() and self._held(action, result) and not unstable_failure(result)
                        and not self._stop.is_set()):
                    outcome["placed"] = self._run_checked(
                        plan_release(True, self.config, home=False, carry_yaw=self._wrist_yaw,
                                     width=last_width(result)), "release")
            except BaseException as exc:   # re-raised in the cycle's thread once the thought is over
                outcome["error"] = exc
            finally:
                frames.put(None)

        mover = threading.Thread(target=carry, name="flgd-carry", daemon=True)
        mover.start()
        thought: Thought | None = None
        failed: BaseException | None = None
        at = busy = 0.0
        try:
            item = frames.get()
            if item is not None and not self._stop.is_set():
                arrived = time.perf_counter()

                def perceived() -> None:
                    seen.set()
                    judged.set()

                thought, at = self._think(record, action, item[0], timer, perceived), item[1]
                busy = time.perf_counter() - arrived
        except Exception as exc:   # the agent's or the perception's: the arm goes on; decided again at the place
            log.error("deciding on the way home failed: %r; the cycle goes on as without it", exc)
        except BaseException as exc:
            failed = exc
        finally:
            judged.set()
            mover.join()
        result: ExecutionResult | None = outcome.get("result")
        placed: ExecutionResult | None = outcome.get("placed")
        if (result is None or placed is None or failed is not None or "error" in outcome
                or not self._held(action, result) or unstable_failure(result)):
            if thought is not None and thought.provisional is not None:
                self.agent.restore_outcome_state(thought.provisional)
            thought = None
        if "error" in outcome or failed is not None:
            if "error" in outcome and failed is not None:
                log.error("thinking on the way home failed too: %r", failed)
            first = outcome["error"] if "error" in outcome else failed
            assert isinstance(first, BaseException)
            raise first
        assert result is not None
        # of the carry and the place, on the cell's clock, after the frame was there
        remaining = max(0.0, result.duration + (placed.duration if placed is not None else 0.0) - at)
        timer.discount("execute", max(stood, busy - remaining))
        if thought is not None and not thought.done:
            before = busy - thought.seconds
            thought = dataclasses.replace(thought, hidden=min(thought.seconds, max(0.0, remaining - before)))
        return result, thought, placed

    def _think(self: _Cycle, record: CycleRecord, action: Action, frame: Frame, timer: PhaseTimer,
               perceived: Callable[[], None] = lambda: None) -> Thought | None:
        """Perceive a frame taken on the way home and decide on it, the pick recorded as held first; None when the
        frame does not show where the tool was or is refused (the tool in view).  ``perceived`` is called once the
        picture is accepted, before the decision."""
        if frame.tool_position is None:
            return None
        try:
            state = self._heightmaps(frame, timer)
        except ToolInView as exc:
            log.warning("a picture taken on the way home: %s", exc)
            return None
        perceived()
        if self._nothing_to_grasp(state):
            return Thought(state, done=True)
        provisional = self.agent.outcome_state()
        try:
            record_outcome(self.agent, action, True, True, state.height, record.kind)
            self.wait_for_learner()
            if self._stop.is_set():
                self.agent.restore_outcome_state(provisional)
                return None
            started = time.perf_counter()
            decision, stuck = self._decide(state)
        except BaseException:
            self.agent.restore_outcome_state(provisional)
            raise
        return Thought(state, False, decision, stuck, time.perf_counter() - started, provisional=provisional)

    def _held(self: _Cycle, action: Action, result: ExecutionResult) -> bool:
        """Whether a completed grasp plan measured an object between the fingers at home."""
        if action.primitive != "grasp" or not result.completed:
            return False
        width = float(result.widths[-1]) if result.widths else math.nan
        return grasp_reward(width, self.config.gripper) > 0


def last_width(result: ExecutionResult) -> float | None:
    """The last width a plan measured (a grasp's: at home), None when it measured none."""
    return float(result.widths[-1]) if result.widths else None


def record_outcome(agent: CycleAgent, action: Action, grasp_success: bool | None, move_changed: bool,
                    height_after: np.ndarray, kind: str | None) -> None:
    """Tell the agent what its action did, and the heightmap that was judged (for its failure memory)."""
    agent.record_outcome(action, grasp_success, move_changed=move_changed, height_after=height_after, kind=kind)
