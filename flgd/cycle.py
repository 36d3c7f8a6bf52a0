"""The one FLG cycle: capture -> perceive -> decide -> plan -> check -> execute -> judge -> store -> learn.

The daemon, ``flgd train`` and ``flgd eval`` all run this class, so there is a
single definition of what an action, a reward and a transition are.  It knows
nothing about sockets, states or systemd; the caller decides when to run a
cycle and what to do with the record and with exceptions.

Nothing moves unrecorded.  With a store, a cycle first checks that the state
directory can take its writes (``Store.check_space``: free space above
``storage.min_free_bytes``, a writable filesystem) and raises StoreError
before any motion when it cannot; and a decided action is written to the
action log as an intent (outcome ``pending``) before the cell is told to move,
then completed with its outcome.  An intent that cannot be written stops the
cycle before the motion; a completion that cannot be written leaves the intent,
which the store marks ``interrupted`` (flgd/store/).

One capture per cycle: the frame taken after an action is both the "after" of
its move judgement and the state the next decision is made on (the next state
of the stored transition).  A fresh capture is needed only after a scene
reset, a discarded action, a stop or when the runner is new; each of those
first sends the arm home (``plan_home``, checked like any plan), since it may
stand in the camera's view -- a real arm halted mid-motion does.

A grasp succeeded (reward 1) only when the width says an object is between the fingers both at the
home pose after the lift and at the place pose before they open (``plan_release``; with home at the place,
``place_is_home``, the reading at home is both): an object dropped on the way is a failed grasp in the record,
the stored transition and every report, and the record's ``failure`` says it was dropped.

Outcomes of a cycle (``CycleRecord.outcome``):
  * ``executed``  -- the plan ran; a transition was stored and learned from.
  * ``refused``   -- the safety envelope refused the plan; nothing was sent to
    the cell; the action is stored with reward 0 and an unchanged next state,
    so the learner is taught not to choose it again.
  * ``discarded`` -- the cell reported the physics unstable: the scene is reset
    and nothing is learned.
  * ``fault``     -- the cell raised CellFault: the action is logged, its
    transition dropped, and the CellFault re-raised for the caller.
  * ``pending`` / ``interrupted`` -- never a CycleRecord's outcome, only an
    action-log row's: the intent written before the motion, and one whose
    completion was never written (a kill, a power cut, a full disk mid-action).
  * ``empty``     -- there was nothing to act on; no step.  A cell that can lay out
    a new scene (the simulation) did so; on any other cell nothing was done and
    ``CycleRecord.refill_needed`` is set: a person must refill the table, and the
    caller must not cycle on (each cycle would home the arm and capture again).
  * ``stopped``   -- ``request_stop`` interrupted the action: the arm was halted
    where it was, nothing more is sent, the action is logged and not learned from.
  * ``stuck``     -- the agent's escalation ladder gave up on this scene
    (``exploration.stuck_after`` actions without a successful grasp, or every
    allowed action suppressed by the failure memory): nothing was done and no
    step taken; ``CycleRecord.failure`` holds the evidence.  A cell that can lay
    out a new scene did so (``CycleRecord.relaid``); on any other cell the
    scene's memory is cleared and the caller decides whether to pause for a
    person (``exploration.stuck_action``).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any, Callable


from flgd.actions import Action
from flgd.camera_view import in_view_on_the_way, tool_in_view
from flgd.cell import STOPPED_ON_REQUEST, Cell, CellFault, ExecutionResult, Frame, FrameOnTheWay
from flgd.clutter import grasp_mask, judge_move
from flgd.config import CellConfig
from flgd.cycle_record import (UNSTABLE_MARK, CycleOutcome, CycleRecord, PhaseTimer, float_or_none, held_at_place,
                                on_cell_clock, unstable_failure, was_stopped)
from flgd.deciding_ahead import Ahead, DecidingAhead, Thought, ToolInView, last_width, record_outcome
from flgd.perception import Heightmaps, frame_heightmaps
from flgd.plans import end_yaw, plan_action, plan_home, plan_release
from flgd.cycle_commit import commit_cycle
from flgd.cycle_parts import CycleAgent, CycleLearner, CycleStore
from flgd.safety import CheckedPlan, PlanRefused, check_plan

if TYPE_CHECKING:
    from flgd.plans import Plan
    from flgd.learning.agent import Decision
    from flgd.learning.replay import PrioritizedReplay, Transition

__all__ = ["CycleRecord", "CycleRunner", "ToolInView", "UNSTABLE_MARK"]

log = logging.getLogger("flgd.cycle")

# learning.wait_for_updates: the longest a cycle waits for the learner's scheduled updates, in seconds
LEARNER_WAIT_LIMIT = 600.0


def _make_transition(state: Heightmaps, action: Action, reward: float, next_state: Heightmaps | None,
                     done: bool) -> Any:
    from flgd.learning.replay import Transition
    return Transition(state=state, action=action, reward=reward, next_state=next_state, done=done)


class CycleRunner(DecidingAhead):
    """Runs cycles on one cell with one agent; optional store, replay and learner.

    ``agent``   -- decides and learns outcomes (``flgd.cycle_parts.CycleAgent``).
    ``store``   -- records each cycle (``CycleStore``: a ``flgd.store.Store``, or a
                   training worker's collecting stand-in); None = not persisted.
    ``replay``  -- gets every stored transition (``add``); None = no learning.
    ``learner`` -- told about each new transition and decision (``CycleLearner``).
    ``on_phase``-- called after each phase (the daemon pings its watchdog there).
    """

    def __init__(self, config: CellConfig, cell: Cell, agent: CycleAgent, *, store: CycleStore | None = None,
                 replay: PrioritizedReplay | None = None, learner: CycleLearner | None = None, step: int = 0,
                 backend: str | None = None,
                 on_phase: Callable[[str], None] | None = None, decide_while_placing: bool | None = None):
        self.config = config
        self.cell = cell
        self.agent = agent
        self.store = store
        self.replay = replay
        self.learner = learner
        self.step = int(step)
        self.backend = backend or config.backend
        self.on_phase = on_phase
        self.current: Heightmaps | None = None
        self.last_frame: Frame | None = None  # the newest captured frame (the calibration watch fits the table in it)
        # (heightmaps, decision, step) of the newest decision, replaced as one object so another
        # thread (a snapshot request) never pairs a decision with the wrong heightmaps
        self.last_decided: tuple[Heightmaps, Decision, int] | None = None
        self._stop = threading.Event()
        self.decide_while_placing = (config.robot.decide_while_placing if decide_while_placing is None
                                     else bool(decide_while_placing))
        self._ahead: Ahead | None = None
        if self.decide_while_placing and config.robot.capture_on_the_way:
            why = in_view_on_the_way(config.robot.home.position, config)
            if why:
                log.warning("robot.capture_on_the_way in %s: at the home pose %s; no picture can be taken on the way "
                            "home, so every one is taken at home", config.source, why)
        self.frames_refused = 0   # frames taken with the tool in view, never used
        # the tool's yaw where the last plan left it (None: not known, as after a plan cut short; a new state
        # starts with the arm sent home): the next plan turns the wrist from there (``flgd.plans.tool_yaw``)
        self._wrist_yaw: float | None = None

    # ------------------------------------------------------------------ helpers
    def request_stop(self) -> None:
        """Halt the motion in flight and send nothing more (any thread, signal handlers too)."""
        self._stop.set()
        self.cell.stop_motion()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    def use_cell(self, cell: Cell, backend: str) -> None:
        """Act on ``cell`` (registered as ``backend``) from the next cycle on, starting from a fresh capture."""
        self.cell, self.backend = cell, backend
        self.forget_state()

    def use_learning(self, agent: CycleAgent, store: CycleStore | None, replay: PrioritizedReplay | None,
                     learner: CycleLearner | None) -> None:
        """Act and learn with these parts from the next cycle on (a learning stack rebuilt on a reopened store)."""
        self.agent, self.store, self.replay, self.learner = agent, store, replay, learner

    def forget_state(self) -> None:
        """The next cycle starts from a fresh capture (after a reset, a swap of cell or agent)."""
        self.current = None
        self._ahead = None
        self._wrist_yaw = None
        if self.store is not None:
            self.store.forget_last_state()

    def perceive(self, timer: PhaseTimer) -> Heightmaps:
        """Capture and heightmaps; ToolInView (a CellFault) for a frame the cell took with the tool in view."""
        with timer.phase("capture"):
            frame = self.cell.capture()
        return self._heightmaps(frame, timer)

    def _heightmaps(self, frame: Frame, timer: PhaseTimer) -> Heightmaps:
        """The heightmaps of ``frame``; ToolInView for a frame taken with the tool in view."""
        why = "" if frame.tool_position is None else tool_in_view(frame.tool_position, self.config)
        if why:
            self.frames_refused += 1
            if self.store is not None:
                self.store.record_event("frame_refused", why)
            raise ToolInView(f"frame refused: {why}; a picture is taken only with the arm out of view (robot.home "
                             f"in {self.config.source})")
        self.last_frame = frame
        with timer.phase("perceive"):
            cam = self.config.camera
            return frame_heightmaps(frame, self.config.workspace, cam.depth_range, cam.depth_fill)

    def perceive_now(self) -> Heightmaps:
        """A fresh capture and its heightmaps, outside any cycle (for snapshots); keeps the cycle's state."""
        return self.perceive(PhaseTimer({}, None))

    def _reset_scene(self, timer: PhaseTimer, record: CycleRecord) -> None:
        """A new scene laid out by the cell; its time counts in ``cell_time`` as the PC spent it (a scene reset
        has no motion on the cell's clock)."""
        started = time.perf_counter()
        with timer.phase("execute"):
            self.cell.reset_scene()
        record.cell_time = (record.cell_time or 0.0) + time.perf_counter() - started
        self._new_scene()

    def _new_scene(self) -> None:
        """A new scene: a fresh capture, and the agent's failed-grasp streak and previous location, which
        are about the scene they happened in, are forgotten."""
        self.forget_state()
        self.agent.reset_episode()

    def _run_checked(self, plan: Plan, what: str) -> ExecutionResult:
        """Check and run a follow-up plan (release, home); a refusal here is a cell fault."""
        if self._stop.is_set():
            return ExecutionResult(False, [], f"{what}: {STOPPED_ON_REQUEST}")
        try:
            checked = check_plan(plan, self.config)
        except PlanRefused as exc:
            raise CellFault(f"{what} plan refused by the safety envelope: {exc}") from exc
        return self._execute(checked)

    def _execute(self, checked: CheckedPlan, on_frame: FrameOnTheWay | None = None) -> ExecutionResult:
        """Run a checked plan on the cell (``on_frame``: with a picture taken on its last move once the arm is out
        of view) and note the wrist yaw it left the tool at (a plan without moves leaves it where it was; one cut
        short, unknown)."""
        run = self.cell.execute if on_frame is None else (lambda c: self.cell.execute_and_capture(c, on_frame))
        if not checked.plan.poses:
            return run(checked)
        self._wrist_yaw = None   # until the plan is known to have ended where it meant to
        result = run(checked)
        if result.completed:
            self._wrist_yaw = end_yaw(checked.plan, self.config)
        return result

    def _empty(self, hm: Heightmaps) -> bool:
        hint = self.cell.workspace_empty_hint()
        if hint is True:
            return True
        return self._nothing_to_grasp(hm)

    def _nothing_to_grasp(self, hm: Heightmaps) -> bool:
        return not bool(grasp_mask(hm.height, self.config.rewards, self.config.workspace.resolution).any())

    def _check_space(self) -> None:
        """Before any motion of a cycle: StoreError if the state directory cannot take the cycle's writes."""
        if self.store is not None:
            self.store.check_space()

    def _record_intent(self, record: CycleRecord) -> None:
        """Write-ahead: the decided action is in the action log before the cell is told to move.

        Its time is in the cycle's duration and no phase's (``t_store`` is the outcome's commit), so the
        controller's own time (flgctl stats: the cycle minus execution) includes it once."""
        if self.store is not None:
            self.store.record_intent(record.row())

    def _commit(self, record: CycleRecord, transition: Transition | None, timer: PhaseTimer) -> None:
        committed = commit_cycle(record.row(), transition, store=self.store, replay=self.replay, learner=self.learner)
        record.transition_id, record.timings["store"] = committed.transition_id, committed.seconds
        if timer.on_phase is not None:
            timer.on_phase("store")

    def _stopped(self, record: CycleRecord, why: str, finish: Callable[[], CycleRecord],
                 timer: PhaseTimer) -> CycleRecord:
        """A stop request interrupted the action: log it, learn nothing, forget the (moved) scene."""
        record.outcome = CycleOutcome.STOPPED
        record.failure = why if STOPPED_ON_REQUEST in why else f"{why}: {STOPPED_ON_REQUEST}"
        self.forget_state()
        self._commit(finish(), None, timer)
        return finish()

    def wait_for_learner(self) -> None:
        """With ``learning.wait_for_updates``: block until the learner ran the updates scheduled so far.

        The time a real cell's slow cycle gives the learner.  Called before each decision, and by the daemon
        before the gate takes a hand-over, so that which weights act and when a challenger comes depend on
        the number of updates, never on thread timing (a paced run is reproducible from its seeds)."""
        if self.learner is not None and self.config.learning.wait_for_updates:
            self.learner.wait_idle(LEARNER_WAIT_LIMIT)

    def _decide(self, state: Heightmaps) -> tuple[Decision | None, str]:
        """The agent's decision on ``state`` (None when it found nothing), and its reason to give up ('' = none)."""
        self.agent.maybe_swap_weights()
        stuck = self.agent.stuck_reason()
        decision = None if stuck else self.agent.decide(state, self.step)
        if decision is None and not stuck:
            stuck = self.agent.stuck_reason()  # the decision found nothing left to try
        return decision, stuck

    # ------------------------------------------------------------------ the cycle
    def run_once(self) -> CycleRecord:
        """One cycle.  Raises CellFault (after logging the action) and store errors."""
        self._check_space()
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        timer = PhaseTimer(timings, self.on_phase)
        record = CycleRecord(outcome=CycleOutcome.EMPTY, time=time.time(), backend=self.backend, timings=timings)

        def finish() -> CycleRecord:
            record.duration = time.perf_counter() - t_start
            return record

        if self.current is None:
            # The arm may stand anywhere (daemon start, a stop mid-motion, a reset, another cell):
            # send it home, out of the camera's view, before taking the picture a decision rests on.
            with timer.phase("execute"):
                home = on_cell_clock(record, self._run_checked(plan_home(self.config), "home before capture"))
            if was_stopped(home) or self._stop.is_set():
                record.outcome = CycleOutcome.STOPPED
                record.failure = home.failure or STOPPED_ON_REQUEST
                return finish()
            if not home.completed and not unstable_failure(home):
                raise CellFault(f"could not go home before capturing: {home.failure}")
            self.current = self.perceive(timer)
        state = self.current

        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead.state is state:
            decision, stuck = ahead.decision, ahead.stuck   # made while the arm placed the last pick
            timings["decide"] = ahead.seconds
            record.decide_hidden = ahead.hidden
        else:
            self.wait_for_learner()
            with timer.phase("decide"):
                decision, stuck = self._decide(state)
        if stuck:
            record.outcome = CycleOutcome.STUCK
            record.failure = stuck
            if self.cell.can_reset_scene():
                self._reset_scene(timer, record)
                record.relaid = True
            else:
                self._new_scene()
            return finish()
        if decision is None:
            if self.cell.can_reset_scene():
                self._reset_scene(timer, record)
            else:
                record.refill_needed = True
                self._new_scene()  # after the refill the next cycle starts with a fresh picture
            return finish()
        self.last_decided = (state, decision, self.step)
        if self.learner is not None:
            self.learner.note_decision(state, decision, decision.weights_version)
        action: Action = decision.action
        record.step = self.step
        record.action = action
        record.rule = decision.rule
        record.epsilon = float_or_none(decision.epsilon)
        record.q_value = float_or_none(decision.q_value)
        record.policy = decision.policy_id
        self.step += 1

        with timer.phase("plan"):
            plan = plan_action(action, state.height, self.config, wrist_yaw=self._wrist_yaw)
            record.kind = plan.primitive
            try:
                checked = check_plan(plan, self.config)
            except PlanRefused as exc:
                checked = None
                # check_plan reports an empty refused plan as "no steps"; the builder's reason says more
                record.refused = str(exc)
        if checked is None:
            record.outcome = CycleOutcome.REFUSED
            record.reward = 0.0
            if action.primitive == "grasp":
                record.success = False
            record_outcome(self.agent, action, False if action.primitive == "grasp" else None, False,
                            state.height, record.kind)
            self._commit(finish(), _make_transition(state, action, 0.0, state, False), timer)
            return finish()

        if self._stop.is_set():
            return self._stopped(record, "before execution", finish, timer)
        try:
            self._record_intent(finish())
        except Exception:
            self.step -= 1  # nothing moved and nothing is logged: the next cycle decides this step again
            raise
        after: Heightmaps | None = None   # the picture the action is judged on
        provisional = None   # the agent before the outcome measured at home was recorded (decided ahead on it)
        thought: Thought | None = None   # made while the arm carried the pick home
        placed: ExecutionResult | None = None   # the place, run on from the grasp plan while the thought went on
        park = False   # home after that place: the thought found nothing left to pick
        try:
            with timer.phase("execute"):
                if action.primitive == "grasp" and self.decide_while_placing and self.config.robot.capture_on_the_way:
                    result, thought, placed = self._grasp_and_think(record, action, checked, timer)
                else:
                    result = self._execute(checked)
                on_cell_clock(record, result)
                if result.contact_stops:
                    record.contact_stop_mm = round(1000.0 * result.contact_stops[0].short_by, 1)
                if was_stopped(result) or self._stop.is_set():
                    if thought is not None and thought.provisional is not None:
                        self.agent.restore_outcome_state(thought.provisional)
                    if placed is not None:   # the carry went on to the place: its time, and its stop if it was that
                        on_cell_clock(record, placed)
                        if was_stopped(placed):
                            return self._stopped(record, placed.failure, finish, timer)
                    return self._stopped(record, result.failure or "after execution", finish, timer)
                held = self._held(action, result)
                unstable = unstable_failure(result)
            if held and not unstable and self.decide_while_placing and thought is None and placed is None:
                after = self._capture_at_home(timer)
            with timer.phase("execute"):
                if not unstable and action.primitive == "grasp":
                    if thought is not None:
                        after, provisional = thought.state, thought.provisional
                        done = thought.done or self.cell.workspace_empty_hint() is True
                        if done and provisional is not None:   # nothing left to decide on: recorded at the judge
                            self.agent.restore_outcome_state(provisional)
                            provisional = None
                        elif not done:
                            self._ahead = Ahead(after, thought.decision, thought.stuck, thought.seconds,
                                                 thought.hidden)
                        park = done   # the carry placed it and stays there: with nothing left, home after
                    if placed is not None:   # (without a thought: it failed; the next picture is taken there)
                        if thought is None:
                            park = self.cell.workspace_empty_hint() is True
                        released = on_cell_clock(record, placed)
                        if provisional is not None and not released.completed:   # no outcome: take it back
                            self.agent.restore_outcome_state(provisional)
                            provisional, self._ahead = None, None
                    elif after is not None:
                        released, provisional = self._place_and_decide(record, action, after, timer,
                                                                       last_width(result))
                        if provisional is not None and not released.completed:   # no outcome: take it back
                            self.agent.restore_outcome_state(provisional)
                            provisional, self._ahead = None, None
                    else:
                        release = plan_release(held, self.config, carry_yaw=self._wrist_yaw,
                                               width=last_width(result))
                        released = on_cell_clock(record, self._run_checked(release, "release"))
                    if was_stopped(released):
                        return self._stopped(record, released.failure, finish, timer)
                    unstable = unstable_failure(released)
                    if not released.completed and not unstable:
                        raise CellFault(f"could not release after the grasp: {released.failure}")
                    if held and not unstable:
                        held, dropped = held_at_place(released, result, self.config)
                        if dropped:
                            record.failure = dropped
                            after = None   # taken before the drop: the object may have fallen into view since
                            if provisional is not None:   # decided on "held": take it back, as if it had waited
                                self.agent.restore_outcome_state(provisional)
                                provisional, self._ahead = None, None
                if not unstable and (not result.completed or park):
                    home = on_cell_clock(record, self._run_checked(plan_home(self.config), "home"))
                    if was_stopped(home):
                        return self._stopped(record, home.failure, finish, timer)
                    unstable = unstable_failure(home)
                    if not home.completed and not unstable:
                        after_what = "the place" if park else f"a failed {record.kind}"
                        raise CellFault(f"could not return home after {after_what}: {home.failure}")
        except CellFault as exc:
            record.outcome = CycleOutcome.FAULT
            record.failure = str(exc)
            record.cell_time = record.gripper_time = None   # no time on the cell's clock: count the wall clock's
            self.forget_state()
            try:
                commit_cycle(finish().row(), None, store=self.store, replay=None, learner=None)
            except Exception:  # the fault is what matters; the log row is best effort
                pass
            raise

        if unstable:
            record.outcome = CycleOutcome.DISCARDED
            record.failure = unstable
            self._reset_scene(timer, record)
            self._commit(finish(), None, timer)
            return finish()

        if after is None:
            after = self.perceive(timer)
        with timer.phase("judge"):
            if action.primitive == "grasp":
                record.success = held
                record.reward = 1.0 if held else 0.0
            else:
                judgement = judge_move(state.height, after.height, self.config.rewards,
                                       self.config.workspace.resolution)
                record.reward, record.mu, record.eta = judgement.reward, judgement.mu, judgement.eta
            if not result.completed:
                record.failure = result.failure
            record.done = self._empty(after)
            if provisional is None:   # else recorded before deciding ahead, and the place confirmed it
                record_outcome(self.agent, action, record.success if action.primitive == "grasp" else None,
                                bool(record.reward), after.height, record.kind)
        record.outcome = CycleOutcome.EXECUTED
        transition = _make_transition(state, action, float(record.reward),
                                      None if record.done else after, record.done)
        self._commit(finish(), transition, timer)
        if record.done:
            self._reset_scene(timer, record)
        else:
            self.current = after
        return finish()
