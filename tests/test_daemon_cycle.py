"""The one cycle on the real simulated cell, the real agent and the store, with injected faults.

``FaultInjectingCell`` wraps a real SimCell and, on request, makes one
execution fail the way a cell can fail (unstable physics, a CellFault); it
also counts captures.  ``ScriptedAgent`` wraps the real Agent and replaces
the decision of chosen steps (to force a refused plan or a push).
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np
import pytest

from flgd.actions import Action
from flgd.cell import STOPPED_ON_REQUEST, Cell, CellFault, ContactStop, ExecutionResult, make_cell
from flgd.clutter import judge_move
from flgd.config import load_config
from flgd.geometry import ToolPose
from flgd.plans import MoveL, Plan
from flgd.safety import check_plan
from flgd.cycle import CycleRunner
from flgd.learning.agent import Agent
from flgd.learning.networks import build_network
from flgd.learning.replay import PrioritizedReplay
from flgd.store import Store

REPO = Path(__file__).resolve().parents[1]


class FaultInjectingCell(Cell):
    """A real SimCell behind a wrapper that can fail the next execution (a fake of the failure modes only)."""

    def __init__(self, inner: Cell):
        super().__init__(inner.config)
        self.inner = inner
        self.captures = 0
        self.executions = 0
        self.resets = 0
        # "unstable", "fault", "stop-mid-motion", "stop-after-motion" or "contact-stop" (the descent
        # of the real execution is reported as stopped 12.34 mm short)
        self.fail_next: str | None = None
        self.stop_during: CycleRunner | None = None  # whose request_stop a "stop-*" mode calls
        self.stop_motion_calls = 0

    def capture(self):
        self.captures += 1
        return self.inner.capture()

    def execute(self, plan):
        self.executions += 1
        mode, self.fail_next = self.fail_next, None
        if mode == "fault":
            raise CellFault("protective stop (injected)")
        if mode == "stop-mid-motion":  # SIGTERM arrives during the motion; the arm halts where it is
            self.stop_during.request_stop()
            return ExecutionResult(completed=False, widths=[], failure=f"step 2 (descend): {STOPPED_ON_REQUEST}")
        result = self.inner.execute(plan)
        if mode == "stop-after-motion":  # SIGTERM arrives just as the plan completed
            self.stop_during.request_stop()
        if mode == "contact-stop":
            return dataclasses.replace(result, contact_stops=[ContactStop("descend", 0.01234)])
        if mode == "unstable":
            return ExecutionResult(completed=False, widths=result.widths,
                                   failure="unstable simulation (injected)", duration=result.duration)
        return result

    def gripper_width(self):
        return self.inner.gripper_width()

    def stop_motion(self):
        self.stop_motion_calls += 1

    def reset_scene(self):
        self.resets += 1
        self.inner.reset_scene()

    def recover(self):
        self.inner.recover()

    def workspace_empty_hint(self):
        return self.inner.workspace_empty_hint()

    def close(self):
        self.inner.close()


class ScriptedAgent:
    """The real agent, except that ``script[step]`` builds the action of that step from the heightmap."""

    def __init__(self, agent: Agent, script: dict):
        self.agent = agent
        self.script = script

    def decide(self, heightmaps, step):
        d = self.agent.decide(heightmaps, step)
        if d is not None and step in self.script:
            d = dataclasses.replace(d, action=self.script[step](heightmaps), rule="scripted")
        return d

    def record_outcome(self, action, grasp_success, **outcome):
        self.agent.record_outcome(action, grasp_success)

    def maybe_swap_weights(self):
        return self.agent.maybe_swap_weights()

    def reset_episode(self):
        self.agent.reset_episode()

    def stuck_reason(self):
        return ""  # these tests end their scenes themselves

    def outcome_state(self):
        return self.agent.outcome_state()

    def restore_outcome_state(self, state):
        self.agent.restore_outcome_state(state)


def _setup(tmp_path, objects=3, script=None):
    cfg = load_config(REPO / "cell_config" / "sim.yaml")
    cfg = dataclasses.replace(cfg, state_dir=str(tmp_path), sim=dataclasses.replace(cfg.sim, objects=objects, seed=3))
    cell = FaultInjectingCell(make_cell(cfg))
    agent = Agent(cfg, build_network(cfg.learning.network, rotations=16, seed=0), seed=0)
    store = Store(tmp_path)
    replay = PrioritizedReplay.from_config(cfg.learning)
    runner = CycleRunner(cfg, cell, ScriptedAgent(agent, script or {}), store=store, replay=replay,
                         decide_while_placing=False)   # each cycle whole: the tests count its captures and moves
    return cfg, cell, store, replay, runner


def _object_pixel(hm) -> tuple[int, int]:
    rows, cols = np.nonzero(hm.height > 0.02)
    k = len(rows) // 2
    return int(rows[k]), int(cols[k])


def test_cycles_chain_states_with_one_capture_each(tmp_path):
    cfg, cell, store, replay, runner = _setup(tmp_path)
    try:
        records = [runner.run_once() for _ in range(5)]
    finally:
        cell.close()
    executed = [r for r in records if r.outcome == "executed"]
    assert executed, [r.outcome for r in records]
    for r in executed:
        assert set(r.timings) >= {"capture", "perceive", "decide", "plan", "execute", "judge", "store"}
        assert r.reward in (0.0, 0.5, 1.0) and r.step is not None
    # one capture per executed cycle (its "after", which the next cycle decides on), plus one fresh
    # capture for the first cycle and after each scene reset
    fresh = 1 + sum(1 for r in records[:-1] if r.done or r.outcome in ("empty", "discarded"))
    assert cell.captures == fresh + len(executed)
    assert len(replay) == store.transition_count() == len(executed)
    rows = store.query("SELECT state_id, next_state_id, done FROM transitions ORDER BY id")
    for (s0, n0, done), (s1, _, _) in zip(rows, rows[1:]):
        if not done:
            assert n0 == s1  # the next state of t is the state of t+1, stored once
    log = store.action_log()
    assert [r["step"] for r in log] == [r.step for r in records if r.step is not None]


def test_refused_plan_is_recorded_and_never_sent(tmp_path):
    off_map = lambda hm: Action("grasp", -5, 10, 0)  # noqa: E731  (outside the heightmap)
    cfg, cell, store, replay, runner = _setup(tmp_path, script={1: off_map})
    try:
        first = runner.run_once()
        executions = cell.executions
        rec = runner.run_once()
    finally:
        cell.close()
    assert first.outcome == "executed"
    assert rec.outcome == "refused" and "outside" in rec.refused and rec.reward == 0.0
    assert cell.executions == executions  # nothing reached the cell
    t = list(store.iter_transitions())[-1]
    assert t.next_state is t.state and t.reward == 0.0  # taught as a no-op failure
    assert store.action_log()[-1]["refused"] == rec.refused


def test_push_is_judged_between_this_frame_and_the_next(tmp_path):
    def push_at_object(hm):
        r, c = _object_pixel(hm)
        return Action("push", r, max(c - 20, 0), 0)
    cfg, cell, store, replay, runner = _setup(tmp_path, script={0: push_at_object})
    try:
        rec = runner.run_once()
    finally:
        cell.close()
    assert rec.outcome == "executed" and rec.kind in ("push", "shift")
    t = list(store.iter_transitions())[0]
    j = judge_move(t.state.height, t.next_state.height, cfg.rewards)
    # the stored heights are quantized to 0.1 mm; the judgement on them agrees with the live one
    assert (j.mu, j.eta, j.reward) == pytest.approx((rec.mu, rec.eta, rec.reward), abs=3)
    assert rec.reward == j.reward


def test_unstable_execution_is_discarded_and_the_scene_reset(tmp_path):
    cfg, cell, store, replay, runner = _setup(tmp_path)
    try:
        runner.run_once()
        n_before, resets = store.transition_count(), cell.resets
        cell.fail_next = "unstable"
        rec = runner.run_once()
        assert rec.outcome == "discarded" and "unstable" in rec.failure
        assert store.transition_count() == n_before and len(replay) == n_before  # never learned from
        assert cell.resets == resets + 1 and runner.current is None
        captures = cell.captures
        runner.run_once()
        assert cell.captures >= captures + 1  # a fresh capture after the reset
    finally:
        cell.close()
    assert store.action_log()[1]["outcome"] == "discarded"


@pytest.mark.parametrize("how", ["unstable", "empty"])
def test_a_new_scene_clears_the_agents_streak_and_previous_location(tmp_path, how):
    """Sec. IV-A's "two failed grasps, then move" and Sec. III-D's "not the same place again" are about
    one scene: a streak left over from the last scene forced a move after one failure in the next."""
    cfg, cell, store, replay, runner = _setup(tmp_path, objects=3 if how == "unstable" else 0)
    agent = runner.agent.agent
    try:
        agent.failed_grasps = 1
        agent.previous = Action("grasp", 100, 100, 3)
        if how == "unstable":
            runner.current = runner.perceive_now()
            cell.fail_next = "unstable"
        rec = runner.run_once()
    finally:
        cell.close()
    assert rec.outcome == ("discarded" if how == "unstable" else "empty") and cell.resets == 1
    assert agent.failed_grasps == 0 and agent.previous is None


def test_a_contact_stop_of_the_descent_goes_into_the_action_log(tmp_path):
    cfg, cell, store, replay, runner = _setup(tmp_path)
    try:
        first = runner.run_once()
        cell.fail_next = "contact-stop"
        second = runner.run_once()
    finally:
        cell.close()
    assert first.contact_stop_mm is None or first.contact_stop_mm > 0
    assert second.outcome == "executed" and second.contact_stop_mm == 12.3
    assert store.action_log()[-1]["contact_stop_mm"] == 12.3


def test_cell_fault_is_logged_and_propagated_without_a_transition(tmp_path):
    cfg, cell, store, replay, runner = _setup(tmp_path)
    try:
        runner.current = runner.perceive_now()  # already home and looking: the fault hits the action
        cell.fail_next = "fault"
        with pytest.raises(CellFault, match="protective stop"):
            runner.run_once()
    finally:
        cell.close()
    log = store.action_log()
    assert len(log) == 1 and log[0]["outcome"] == "fault" and "protective stop" in log[0]["failure"]
    assert store.transition_count() == 0 and len(replay) == 0 and runner.current is None


def test_empty_workspace_resets_the_scene_without_a_step(tmp_path):
    cfg, cell, store, replay, runner = _setup(tmp_path, objects=0)
    try:
        rec = runner.run_once()
    finally:
        cell.close()
    assert rec.outcome == "empty" and rec.step is None and runner.step == 0
    assert cell.resets == 1 and store.action_log() == []
    assert not rec.refill_needed  # the simulation lays out a new scene itself: the daemon cycles on


@pytest.mark.parametrize("mode", ["stop-mid-motion", "stop-after-motion"])
def test_a_stop_request_halts_the_action_and_sends_nothing_more(tmp_path, mode):
    """SIGTERM during (or right after) a grasp: no release, no home, nothing learned, the action logged."""
    def grasp_object(hm):
        r, c = _object_pixel(hm)
        return Action("grasp", r, c, 0)
    cfg, cell, store, replay, runner = _setup(tmp_path, script={0: grasp_object, 1: grasp_object})
    try:
        runner.current = runner.perceive_now()  # already home and looking: the stop hits the grasp
        cell.stop_during, cell.fail_next = runner, mode
        rec = runner.run_once()
        assert rec.outcome == "stopped" and STOPPED_ON_REQUEST in rec.failure
        assert cell.executions == 1 and cell.stop_motion_calls == 1  # the grasp only: no release, no home
        assert store.transition_count() == 0 and len(replay) == 0 and runner.current is None
        assert store.action_log()[-1]["outcome"] == "stopped"
        # Once stopped, a further cycle sends nothing either.
        again = runner.run_once()
        assert again.outcome == "stopped" and cell.executions == 1
    finally:
        cell.close()


def test_a_fresh_runner_homes_the_arm_before_its_first_capture(tmp_path):
    """At start (or after a reset or a stop mid-motion) the arm may stand in the camera's view."""
    cfg, cell, store, replay, runner = _setup(tmp_path)
    order = []
    inner_execute, inner_capture = cell.execute, cell.capture
    cell.execute = lambda plan: order.append(("execute", plan.plan.primitive)) or inner_execute(plan)
    cell.capture = lambda: order.append(("capture", None)) or inner_capture()
    try:
        # put the arm over the table first, as a stop mid-motion leaves it
        low = Plan("push", (MoveL(ToolPose.top_down(-0.50, 0.0, 0.05, 0.0), 0.2, 1.0, "down"),), target=(-0.5, 0.0, 0.05))
        assert inner_execute(check_plan(low, cfg)).completed
        rec = runner.run_once()
        assert rec.step == 0
        assert order[:2] == [("execute", "home"), ("capture", None)]
        # the runner keeps its state: the next cycle starts with its action, not with a home
        mark = len(order)
        runner.run_once()
        assert order[mark][0] == "execute" and order[mark][1] != "home"
    finally:
        cell.close()


def test_a_fault_while_homing_is_raised_before_anything_is_captured(tmp_path):
    cfg, cell, store, replay, runner = _setup(tmp_path)
    try:
        cell.fail_next = "fault"
        with pytest.raises(CellFault, match="protective stop"):
            runner.run_once()
        assert cell.captures == 0 and runner.current is None and runner.step == 0
        assert store.transition_count() == 0
    finally:
        cell.close()


@pytest.mark.slow
def test_learned_priorities_are_written_to_the_store_and_come_back_after_a_restart(tmp_path):
    from flgd.learning.learner import Learner
    from flgd.wiring import rebuild_replay

    cfg, cell, store, replay, runner = _setup(tmp_path)
    learner = Learner(cfg, runner.agent.agent.network, replay, priority_sink=store.save_priorities)
    runner.learner = learner
    try:
        for _ in range(4):
            runner.run_once()
            learner.update_pending()
    finally:
        cell.close()
    ids = [r[0] for r in store.query("SELECT id FROM transitions ORDER BY id")]
    assert len(ids) == len(replay) >= 3
    stored = dict(store.query("SELECT id, priority FROM transitions"))
    live = {replay.tag(i): replay.priority(i) for i in range(len(replay))}
    assert set(live) == set(ids)
    sampled = {tid for tid, p in stored.items() if p is not None}
    assert sampled, "the learner's updates set priorities"
    for tid in sampled:
        assert stored[tid] == pytest.approx(live[tid], rel=1e-12)
    # a restart (power cut) rebuilds the replay with exactly these priorities
    rebuilt, problem = rebuild_replay(cfg, store)
    assert problem == "" and len(rebuilt) == len(replay)
    for i in range(len(rebuilt)):
        assert rebuilt.tag(i) == replay.tag(i)
        if replay.tag(i) in sampled:
            assert rebuilt.priority(i) == pytest.approx(replay.priority(i), rel=1e-12)
    store.close()


@pytest.mark.slow
@pytest.mark.parametrize("wait", [True, False])
def test_with_wait_for_updates_each_decision_waits_for_the_learners_scheduled_updates(tmp_path, wait):
    from flgd.learning.learner import Learner

    cfg, cell, store, replay, runner = _setup(tmp_path)
    cfg = dataclasses.replace(cfg, learning=dataclasses.replace(cfg.learning, wait_for_updates=wait, batch_size=2,
                                                                updates_per_action=3, max_backlog=0))
    learner = Learner(cfg, runner.agent.agent.network, replay, thread_nice=0)
    backlog_at_decision = []
    decide = runner.agent.decide

    def noting_decide(hm, step):
        backlog_at_decision.append(learner.pending)
        return decide(hm, step)
    runner.agent.decide = noting_decide
    runner.config, runner.learner = cfg, learner
    update = learner.update
    # Without waiting, no update may finish while the cycles run (so the backlog they leave is certain, not a
    # race); with waiting, updates run as they come (a held one would hold the cycle, which is the point).
    release = threading.Event()
    if wait:
        release.set()

    def held_update():
        release.wait(120)
        return update()
    learner.update = held_update
    learner.start()
    try:
        for _ in range(4):
            runner.run_once()
    finally:
        release.set()
        learner.stop(timeout=120)
        cell.close()
    assert len(backlog_at_decision) == 4
    if wait:
        assert backlog_at_decision == [0, 0, 0, 0]
    else:
        assert min(backlog_at_decision[1:]) > 0  # without waiting the cycle goes on with updates still to run
