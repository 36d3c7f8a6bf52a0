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
home pose after the lift and at the place pose before they open (``plan_release``): an object dropped
on the way is a failed grasp in the record, the stored transition and every report, and the record's
``failure`` says it was dropped.

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

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from flgd.actions import Action
from flgd.cell import STOPPED_ON_REQUEST, Cell, CellFault, ExecutionResult
from flgd.clutter import grasp_mask, grasp_reward, judge_move
from flgd.config import CellConfig
from flgd.perception import Heightmaps, frame_heightmaps
from flgd.plans import plan_action, plan_home, plan_release
from flgd.safety import PlanRefused, check_plan

__all__ = ["CycleRecord", "CycleRunner", "UNSTABLE_MARK"]

# learning.wait_for_updates: the longest a cycle waits for the learner's scheduled updates, in seconds
LEARNER_WAIT_LIMIT = 600.0
# ExecutionResult.failure containing this word means the simulation blew up: never learn from it.
UNSTABLE_MARK = "unstable"


@dataclass
class CycleRecord:
    """What one cycle did; ``row()`` is its action-log row."""

    outcome: str
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
            "step": self.step, "time": self.time, "backend": self.backend, "outcome": self.outcome,
            "primitive": None if a is None else a.primitive, "kind": self.kind,
            "row": None if a is None else a.row, "col": None if a is None else a.col,
            "rotation": None if a is None else a.rotation, "reward": self.reward,
            "success": None if self.success is None else int(self.success),
            "mu": self.mu, "eta": self.eta, "rule": self.rule, "epsilon": self.epsilon,
            "q_value": self.q_value, "refused": self.refused, "failure": self.failure,
            "contact_stop_mm": self.contact_stop_mm,
            "done": int(self.done), "duration": self.duration, "policy": self.policy, "cell_time": self.cell_time,
            "gripper_time": self.gripper_time,
        }
        for phase, seconds in self.timings.items():
            if phase != "store":
                out[f"t_{phase}"] = seconds
        return out


def _on_cell_clock(record: CycleRecord, result: ExecutionResult) -> ExecutionResult:
    """Add a plan's time on the cell's own clock (``ExecutionResult.duration``, its gripper's part) to the cycle's."""
    record.cell_time = (record.cell_time or 0.0) + result.duration
    record.gripper_time = (record.gripper_time or 0.0) + result.gripper_time
    return result


class _Timer:
    def __init__(self, timings: dict[str, float], on_phase: Callable[[str], None] | None):
        self.timings = timings
        self.on_phase = on_phase

    def phase(self, name: str) -> "_Phase":
        return _Phase(self, name)


class _Phase:
    def __init__(self, timer: _Timer, name: str):
        self.timer, self.name = timer, name

    def __enter__(self) -> None:
        self.t0 = time.perf_counter()

    def __exit__(self, *exc: Any) -> None:
        t = self.timer.timings
        t[self.name] = t.get(self.name, 0.0) + time.perf_counter() - self.t0
        if self.timer.on_phase is not None:
            self.timer.on_phase(self.name)


def _make_transition(state: Heightmaps, action: Action, reward: float, next_state: Heightmaps | None,
                     done: bool) -> Any:
    from flgd.learning.replay import Transition
    return Transition(state=state, action=action, reward=reward, next_state=next_state, done=done)


class CycleRunner:
    """Runs cycles on one cell with one agent; optional store, replay and learner.

    ``store``   -- a ``flgd.store.Store`` (anything with ``commit_cycle``,
                   ``note_store_time``, ``forget_last_state``; ``check_space``
                   and ``record_intent`` where it has them); None = not persisted.
    ``replay``  -- gets every stored transition (``add``); None = no learning.
    ``learner`` -- told about each new transition (``notify_new_transition``).
    ``on_phase``-- called after each phase (the daemon pings its watchdog there).
    """

    def __init__(self, config: CellConfig, cell: Cell, agent: Any, *, store: Any = None, replay: Any = None,
                 learner: Any = None, step: int = 0, backend: str | None = None,
                 on_phase: Callable[[str], None] | None = None):
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
        self.last_frame: Any = None  # the newest captured frame (the calibration watch fits the table in it)
        # (heightmaps, decision, step) of the newest decision, replaced as one object so another
        # thread (a snapshot request) never pairs a decision with the wrong heightmaps
        self.last_decided: tuple[Heightmaps, Any, int] | None = None
        self._stop = threading.Event()

    # ------------------------------------------------------------------ helpers
    def request_stop(self) -> None:
        """Halt the motion in flight and send nothing more (any thread, signal handlers too)."""
        self._stop.set()
        self.cell.stop_motion()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    def forget_state(self) -> None:
        """The next cycle starts from a fresh capture (after a reset, a swap of cell or agent)."""
        self.current = None
        if self.store is not None:
            self.store.forget_last_state()

    def perceive(self, timer: _Timer) -> Heightmaps:
        with timer.phase("capture"):
            frame = self.cell.capture()
        self.last_frame = frame
        with timer.phase("perceive"):
            cam = self.config.camera
            return frame_heightmaps(frame, self.config.workspace, cam.depth_range, cam.depth_fill)

    def perceive_now(self) -> Heightmaps:
        """A fresh capture and its heightmaps, outside any cycle (for snapshots); keeps the cycle's state."""
        return self.perceive(_Timer({}, None))

    def _reset_scene(self, timer: _Timer, record: CycleRecord) -> None:
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

    def _run_checked(self, plan: Any, what: str) -> ExecutionResult:
        """Check and run a follow-up plan (release, home); a refusal here is a cell fault."""
        if self._stop.is_set():
            return ExecutionResult(False, [], f"{what}: {STOPPED_ON_REQUEST}")
        try:
            checked = check_plan(plan, self.config)
        except PlanRefused as exc:
            raise CellFault(f"{what} plan refused by the safety envelope: {exc}") from exc
        return self.cell.execute(checked)

    def _empty(self, hm: Heightmaps) -> bool:
        hint = self.cell.workspace_empty_hint()
        if hint is True:
            return True
        return not bool(grasp_mask(hm.height, self.config.rewards, self.config.workspace.resolution).any())

    def _check_space(self) -> None:
        """Before any motion of a cycle: StoreError if the state directory cannot take the cycle's writes."""
        check = getattr(self.store, "check_space", None)
        if check is not None:
            check()

    def _record_intent(self, record: CycleRecord) -> None:
        """Write-ahead: the decided action is in the action log before the cell is told to move.

        Its time is in the cycle's duration and no phase's (``t_store`` is the outcome's commit), so the
        controller's own time (flgctl stats: the cycle minus execution) includes it once."""
        write = getattr(self.store, "record_intent", None)
        if write is not None:
            write(record.row())

    def _commit(self, record: CycleRecord, transition: Any, timer: _Timer) -> None:
        t0 = time.perf_counter()
        if self.store is not None:
            record.transition_id = self.store.commit_cycle(record.row(), transition)
        if transition is not None and self.replay is not None:
            self.replay.add(transition, tag=record.transition_id)
            if self.learner is not None:
                self.learner.notify_new_transition()
        record.timings["store"] = time.perf_counter() - t0
        if self.store is not None:
            self.store.note_store_time(record.step, record.timings["store"])
        if timer.on_phase is not None:
            timer.on_phase("store")

    def _stopped(self, record: CycleRecord, why: str, finish: Callable[[], CycleRecord],
                 timer: _Timer) -> CycleRecord:
        """A stop request interrupted the action: log it, learn nothing, forget the (moved) scene."""
        record.outcome = "stopped"
        record.failure = why if STOPPED_ON_REQUEST in why else f"{why}: {STOPPED_ON_REQUEST}"
        self.forget_state()
        self._commit(finish(), None, timer)
        return finish()

    def wait_for_learner(self) -> None:
        """With ``learning.wait_for_updates``: block until the learner ran the updates scheduled so far.

        The time a real cell's slow cycle gives the learner.  Called before each decision, and by the daemon
        before the gate takes a hand-over, so that which weights act and when a challenger comes depend on
        the number of updates, never on thread timing (a paced run is reproducible from its seeds)."""
        if self.learner is not None and self.config.learning.wait_for_updates and hasattr(self.learner, "wait_idle"):
            self.learner.wait_idle(LEARNER_WAIT_LIMIT)

    # ------------------------------------------------------------------ the cycle
    def run_once(self) -> CycleRecord:
        """One cycle.  Raises CellFault (after logging the action) and store errors."""
        self._check_space()
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        timer = _Timer(timings, self.on_phase)
        record = CycleRecord(outcome="empty", time=time.time(), backend=self.backend, timings=timings)

        def finish() -> CycleRecord:
            record.duration = time.perf_counter() - t_start
            return record

        if self.current is None:
            # The arm may stand anywhere (daemon start, a stop mid-motion, a reset, another cell):
            # send it home, out of the camera's view, before taking the picture a decision rests on.
            with timer.phase("execute"):
                home = _on_cell_clock(record, self._run_checked(plan_home(self.config), "home before capture"))
            if _was_stopped(home) or self._stop.is_set():
                record.outcome = "stopped"
                record.failure = home.failure or STOPPED_ON_REQUEST
                return finish()
            if not home.completed and not _unstable(home):
                raise CellFault(f"could not go home before capturing: {home.failure}")
            self.current = self.perceive(timer)
        state = self.current

        self.wait_for_learner()
        with timer.phase("decide"):
            if hasattr(self.agent, "maybe_swap_weights"):
                self.agent.maybe_swap_weights()
            stuck = _stuck_reason(self.agent)
            decision = None if stuck else self.agent.decide(state, self.step)
            if decision is None and not stuck:
                stuck = _stuck_reason(self.agent)  # the decision found nothing left to try
        if stuck:
            record.outcome = "stuck"
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
        if self.learner is not None and hasattr(self.learner, "note_decision"):
            self.learner.note_decision(state, decision, getattr(decision, "weights_version", -1))
        action: Action = decision.action
        record.step = self.step
        record.action = action
        record.rule = str(getattr(decision, "rule", "") or "")
        record.epsilon = _float_or_none(getattr(decision, "epsilon", None))
        record.q_value = _float_or_none(getattr(decision, "q_value", None))
        record.policy = getattr(decision, "policy_id", None)
        self.step += 1

        with timer.phase("plan"):
            plan = plan_action(action, state.height, self.config)
            record.kind = plan.primitive
            try:
                checked = check_plan(plan, self.config)
            except PlanRefused as exc:
                checked = None
                # check_plan reports an empty refused plan as "no steps"; the builder's reason says more
                record.refused = str(exc)
        if checked is None:
            record.outcome = "refused"
            record.reward = 0.0
            if action.primitive == "grasp":
                record.success = False
            _record_outcome(self.agent, action, False if action.primitive == "grasp" else None, False,
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
        try:
            with timer.phase("execute"):
                result = _on_cell_clock(record, self.cell.execute(checked))
                if result.contact_stops:
                    record.contact_stop_mm = round(1000.0 * result.contact_stops[0].short_by, 1)
                if _was_stopped(result) or self._stop.is_set():
                    return self._stopped(record, result.failure or "after execution", finish, timer)
                held = False
                if action.primitive == "grasp" and result.completed:
                    width = float(result.widths[-1]) if result.widths else math.nan
                    held = grasp_reward(width, self.config.gripper) > 0
                unstable = _unstable(result)
                if not unstable and action.primitive == "grasp":
                    released = _on_cell_clock(record, self._run_checked(plan_release(held, self.config), "release"))
                    if _was_stopped(released):
                        return self._stopped(record, released.failure, finish, timer)
                    unstable = _unstable(released)
                    if not released.completed and not unstable:
                        raise CellFault(f"could not release after the grasp: {released.failure}")
                    if held and not unstable:
                        held, dropped = _held_at_place(released, self.config)
                        if dropped:
                            record.failure = dropped
                if not unstable and not result.completed:
                    home = _on_cell_clock(record, self._run_checked(plan_home(self.config), "home"))
                    if _was_stopped(home):
                        return self._stopped(record, home.failure, finish, timer)
                    unstable = _unstable(home)
                    if not home.completed and not unstable:
                        raise CellFault(f"could not return home after a failed {record.kind}: {home.failure}")
        except CellFault as exc:
            record.outcome = "fault"
            record.failure = str(exc)
            record.cell_time = record.gripper_time = None   # no time on the cell's clock: count the wall clock's
            self.forget_state()
            if self.store is not None:
                try:
                    self.store.commit_cycle(finish().row(), None)
                except Exception:  # the fault is what matters; the log row is best effort
                    pass
            raise

        if unstable:
            record.outcome = "discarded"
            record.failure = unstable
            self._reset_scene(timer, record)
            self._commit(finish(), None, timer)
            return finish()

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
            _record_outcome(self.agent, action, record.success if action.primitive == "grasp" else None,
                            bool(record.reward), after.height, record.kind)
        record.outcome = "executed"
        transition = _make_transition(state, action, float(record.reward),
                                      None if record.done else after, record.done)
        self._commit(finish(), transition, timer)
        if record.done:
            self._reset_scene(timer, record)
        else:
            self.current = after
        return finish()


def _stuck_reason(agent: Any) -> str:
    """The agent's reason to give up on this scene ('' = none; agents without a ladder never give up)."""
    reason = getattr(agent, "stuck_reason", None)
    return str(reason() or "") if callable(reason) else ""


def _record_outcome(agent: Any, action: Action, grasp_success: bool | None, move_changed: bool,
                    height_after: np.ndarray, kind: str | None) -> None:
    """Tell the agent what its action did, and the heightmap that was judged (for its failure memory)."""
    agent.record_outcome(action, grasp_success, move_changed=move_changed, height_after=height_after, kind=kind)


def _held_at_place(released: ExecutionResult, config: CellConfig) -> tuple[bool, str]:
    """Whether the object measured as held at home was still held at the place pose, before the fingers
    opened (the width read at ``flgd.plans.PLACE_CHECK_LABEL``), and if not, the failure text saying so.

    Why: the width at home says the object was lifted; only the width at the place says it was picked.  A
    place plan that reported no width proves nothing held."""
    width = float(released.widths[-1]) if released.widths else math.nan
    if grasp_reward(width, config.gripper) > 0:
        return True, ""
    shown = f"{width * 1000:.1f} mm" if math.isfinite(width) else "no reading"
    return False, (f"dropped: the object slipped out of the gripper between the home and the place pose "
                   f"(width at the place pose {shown})")


def _was_stopped(result: ExecutionResult) -> bool:
    return not result.completed and STOPPED_ON_REQUEST in result.failure


def _unstable(result: ExecutionResult) -> str:
    """The failure text if the cell reported an unstable simulation, else ''."""
    return result.failure if not result.completed and UNSTABLE_MARK in result.failure.lower() else ""


def _float_or_none(v: Any) -> float | None:
    if v is None:
        return None
    try:
        f = float(np.asarray(v))
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None
