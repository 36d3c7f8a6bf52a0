"""The cycle decides while the arm carries a pick home and places it: the picture is taken on the way home once the
arm is out of view (or at home, by a cell that cannot take one while its arm moves), never with the tool in view."""

from __future__ import annotations

import dataclasses
import math
import time
from types import SimpleNamespace

import numpy as np
import pybullet as p
import pytest

from flgd.actions import Action
from flgd.camera_view import tool_in_view
from flgd.cell import CellFault
from flgd.cycle import CycleRunner, ToolInView
from flgd.daemon.metrics import compute_stats
from flgd.geometry import ToolPose
from flgd.perception import base_to_pixel
from flgd.plans import PRESHAPE_LABEL, GripperCommand, MoveL, Plan
from flgd.safety import check_plan
from flgd.store import Store
import sim_cell.cell
from sim_cell.cell import SimCell
from tests.fakes.agents import ScriptedAgentBase, scripted_decision
from tests.fakes.sim import cube_at, make_config


class _Scripted(ScriptedAgentBase):
    """Grasps at the given pixels in turn; can take a provisional outcome back, as the real agent can."""

    def __init__(self, actions: list[Action]):
        super().__init__()
        self.actions = actions
        self.decisions: list[tuple[float, object]] = []   # (when, heightmaps decided on)
        self.decided: list[float] = []   # when each decision was over
        self.taken = 0
        self.thinking = 0.0   # seconds each decision takes

    def decide(self, heightmaps, step):
        self.decisions.append((time.perf_counter(), heightmaps))
        time.sleep(self.thinking)
        self.decided.append(time.perf_counter())
        action = self.actions[min(self.taken, len(self.actions) - 1)]
        self.taken += 1
        return scripted_decision(action, heightmaps)

    def outcome_state(self):
        return list(self.outcomes), self.taken

    def restore_outcome_state(self, saved):
        self.outcomes, self.taken = list(saved[0]), saved[1]


class _Watched(SimCell):
    """The simulated cell, keeping when each plan ran, what it was and where the tool stood as it began.

    ``on_the_way`` False: a cell that cannot take a picture while its arm moves (``Cell.execute_and_capture``'s
    default), so the cycle takes it at home."""

    grip_gives_way = False
    on_the_way = False

    def execute_and_capture(self, plan, on_frame):
        return super().execute_and_capture(plan, on_frame) if self.on_the_way else self.execute(plan)

    def __init__(self, cfg):
        super().__init__(cfg)
        self.plans: list[tuple[str, tuple[str, ...], float, float, np.ndarray]] = []

    def execute(self, plan):
        if self.grip_gives_way and plan.plan.primitive == "place":
            for body in self._world.held:   # 20 kg: five times what the pads hold by friction
                p.changeDynamics(body, -1, mass=20.0, physicsClientId=self._client)
        start, where = time.perf_counter(), self._tcp()[:3, 3].copy()
        result = super().execute(plan)
        self.plans.append((plan.plan.primitive, tuple(s.label for s in plan.plan.steps), start, time.perf_counter(),
                           where))
        return result


def _cell_and_agent(tmp_path, cls=_Watched):
    cfg = dataclasses.replace(make_config(objects=0, depth_noise=False, domain_randomization=False),
                              state_dir=str(tmp_path))
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, capture_on_the_way=cls.on_the_way))
    cell = cls(cfg)
    cube_at(cell, -0.50, 0.05, size=(0.04, 0.04, 0.04))
    cube_at(cell, -0.40, -0.12, size=(0.04, 0.04, 0.04))
    cube_at(cell, -0.62, -0.12, size=(0.04, 0.04, 0.04))   # the table is not cleared by two picks
    pixels = [base_to_pixel(x, y, cfg.workspace) for x, y in ((-0.50, 0.05), (-0.40, -0.12))]
    return cfg, cell, _Scripted([Action("grasp", int(r), int(c), 0, 16) for r, c in pixels])


def test_the_next_decision_is_made_while_the_arm_places_on_a_picture_taken_at_home(tmp_path):
    cfg, cell, agent = _cell_and_agent(tmp_path)
    store = Store(tmp_path)
    try:
        runner = CycleRunner(cfg, cell, agent, store=store)
        first = runner.run_once()
        assert first.success is True and agent.outcomes == [True]
        place = [plan for plan in cell.plans if plan[0] == "place"]
        assert len(place) == 1 and "home" not in place[0][1]   # the arm stays at the place
        decided_at, decided_on = agent.decisions[1]
        assert place[0][2] < decided_at < place[0][3]   # the second decision was made while the arm placed
        assert tool_in_view(runner.last_frame.tool_position, cfg) == ""
        assert np.allclose(runner.last_frame.tool_position, cfg.robot.home.position, atol=0.01)
        assert decided_on is runner.current   # ... on the picture the first pick's transition ends in

        second = runner.run_once()
        place = [plan for plan in cell.plans if plan[0] == "place"]
        # the decision made ahead was used; the only one made since is the third, again while the arm placed
        assert len(agent.decisions) == 3 and place[1][2] < agent.decisions[2][0] < place[1][3]
        grasp_plans = [plan for plan in cell.plans if plan[0] == "grasp"]
        assert np.allclose(grasp_plans[1][4], cfg.robot.place.position, atol=0.01)   # started from the place
        assert second.success is True and second.decide_hidden is not None and second.decide_hidden > 0.0
        logged = store.action_log()
        assert logged[-1]["decide_hidden"] == pytest.approx(second.decide_hidden)
        assert [row["success"] for row in logged] == [1, 1]
    finally:
        store.close()
        cell.close()


class _OnTheWay(_Watched):
    on_the_way = True


def test_the_next_decision_is_made_on_a_picture_taken_on_the_way_home_once_the_arm_is_out_of_view(tmp_path):
    cfg, cell, agent = _cell_and_agent(tmp_path, _OnTheWay)
    agent.thinking = 1.0   # longer than the rest of the carry home: the arm goes on to the place meanwhile
    store = Store(tmp_path)
    try:
        runner = CycleRunner(cfg, cell, agent, store=store)
        first = runner.run_once()
        assert first.success is True and agent.outcomes == [True]
        taken_at = runner.last_frame.tool_position
        assert tool_in_view(taken_at, cfg) == ""
        # taken on the way, short of home: the carry went on after it
        assert math.dist(taken_at, cfg.robot.home.position) > 0.02
        grasp, place = (plan for plan in cell.plans if plan[0] in ("grasp", "place"))
        assert place[0] == "place" and "home" not in place[1]   # the arm stays at the place
        assert agent.decisions[1][1] is runner.current   # decided on the picture taken on the way
        # ... and the place did not wait for the decision to be over
        assert place[2] < agent.decided[1]
        second = runner.run_once()
        assert len(agent.decisions) == 3 and second.success is True
        assert second.decide_hidden is not None and second.decide_hidden > 0.0
        assert store.action_log()[-1]["decide_hidden"] == pytest.approx(second.decide_hidden)
    finally:
        store.close()
        cell.close()


def test_the_simulator_takes_no_picture_on_the_way_while_a_long_held_object_still_shows_over_the_workspace(
        tmp_path, monkeypatch):
    """A 20 cm bar held across its middle overhangs the 7 cm tool model: where the model first calls the tool out
    of view, the bar's end is still over the workspace.  The simulator looks at its render and waits (tested with
    the 7 cm model as the trigger, so that the render's check is what keeps the bar out of the picture)."""
    monkeypatch.setattr(sim_cell.cell, "in_view_on_the_way", tool_in_view)
    cfg = dataclasses.replace(make_config(objects=0, depth_noise=False, domain_randomization=False),
                              state_dir=str(tmp_path))
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, capture_on_the_way=True))
    cell = _OnTheWay(cfg)
    cube_at(cell, -0.45, 0.0, size=(0.03, 0.20, 0.03))   # its long side along y, towards home
    cube_at(cell, -0.62, -0.12, size=(0.04, 0.04, 0.04))
    bar = base_to_pixel(-0.45, 0.0, cfg.workspace)
    agent = _Scripted([Action("grasp", int(bar[0]), int(bar[1]), 0, 16)])
    try:
        runner = CycleRunner(cfg, cell, agent)
        assert runner.run_once().success is True and len(agent.decisions) == 2
        taken_at = runner.last_frame.tool_position
        assert tool_in_view(taken_at, cfg) == "" and math.dist(taken_at, cfg.robot.home.position) > 0.02
        assert agent.decisions[1][1] is runner.current
        assert float(runner.current.height.max()) < 0.06   # the 4 cm cube, not the held bar at 0.3 m
    finally:
        cell.close()


def test_without_capture_on_the_way_the_picture_is_taken_at_home(tmp_path):
    cfg, cell, agent = _cell_and_agent(tmp_path, _OnTheWay)
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, capture_on_the_way=False))
    try:
        runner = CycleRunner(cfg, cell, agent)
        assert runner.run_once().success is True
        assert np.allclose(runner.last_frame.tool_position, cfg.robot.home.position, atol=0.01)
        place = [plan for plan in cell.plans if plan[0] == "place"]
        assert place[0][2] < agent.decisions[1][0] < place[0][3]   # decided while the arm placed
    finally:
        cell.close()


def test_the_last_pick_placed_from_the_carry_parks_the_arm_at_home(tmp_path):
    """The picture on the way shows nothing left: the place, run on from the carry, stays there, and the arm goes
    home after it."""
    cfg = dataclasses.replace(make_config(objects=0, depth_noise=False, domain_randomization=False),
                              state_dir=str(tmp_path))
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, capture_on_the_way=True))
    cell = _OnTheWay(cfg)
    cube_at(cell, -0.50, 0.05, size=(0.04, 0.04, 0.04))
    row, col = base_to_pixel(-0.50, 0.05, cfg.workspace)
    agent = _Scripted([Action("grasp", int(row), int(col), 0, 16)])
    try:
        runner = CycleRunner(cfg, cell, agent)
        assert runner.run_once().success is True and agent.outcomes == [True] and runner._ahead is None
        assert [plan[0] for plan in cell.plans][-2:] == ["place", "home"]
        assert np.allclose(cell._tcp()[:3, 3], cfg.robot.home.position, atol=0.01)
    finally:
        cell.close()


class _StopOnceThePickIsPlaced(_OnTheWay):
    """Asks the cycle to stop as soon as a place has ended (while the decision made on the way still runs)."""

    runner: CycleRunner | None = None

    def __init__(self, cfg):
        super().__init__(cfg)
        self.durations: dict[str, float] = {}

    def execute(self, plan):
        result = super().execute(plan)
        self.durations[plan.plan.primitive] = result.duration
        if plan.plan.primitive == "place" and self.runner is not None:
            self.runner.request_stop()
        return result

    def execute_and_capture(self, plan, on_frame):
        result = super().execute_and_capture(plan, on_frame)
        self.durations[plan.plan.primitive] = result.duration
        return result


def test_a_stop_while_the_decision_outlasts_the_place_counts_the_places_time(tmp_path):
    cfg, cell, agent = _cell_and_agent(tmp_path, _StopOnceThePickIsPlaced)
    agent.thinking = 1.0
    try:
        runner = cell.runner = CycleRunner(cfg, cell, agent)
        record = runner.run_once()
        assert record.outcome == "stopped" and agent.outcomes == [] and runner._ahead is None
        assert [plan[0] for plan in cell.plans] == ["home", "grasp", "place"]
        assert set(cell.durations) == {"home", "grasp", "place"}   # the arm sent home first, as a new state is
        assert record.cell_time == pytest.approx(sum(cell.durations.values()))
    finally:
        cell.close()


def test_a_grasp_that_lifted_nothing_takes_back_the_decision_made_on_the_way_home(tmp_path):
    cfg, cell, _ = _cell_and_agent(tmp_path, _OnTheWay)
    empty = base_to_pixel(-0.62, 0.12, cfg.workspace)
    agent = _Scripted([Action("grasp", int(empty[0]), int(empty[1]), 0, 16)])
    try:
        runner = CycleRunner(cfg, cell, agent)
        record = runner.run_once()
        assert record.success is False and agent.outcomes == [False]   # "held" was taken back
        assert len(agent.decisions) == 2 and agent.taken == 1   # the decision made on the way is discarded
        assert runner.current is not agent.decisions[1][1]
        assert np.allclose(runner.last_frame.tool_position, cfg.robot.home.position, atol=0.01)
    finally:
        cell.close()


class _ToolInViewOnTheWay(_OnTheWay):
    def execute_and_capture(self, plan, on_frame):
        def shows_the_tool(frame, at):
            on_frame(dataclasses.replace(frame, tool_position=(-0.50, 0.0, 0.30)), at)
        return super().execute_and_capture(plan, shows_the_tool)


def test_a_picture_on_the_way_that_shows_the_tool_is_refused_and_the_picture_is_taken_at_home(tmp_path):
    cfg, cell, agent = _cell_and_agent(tmp_path, _ToolInViewOnTheWay)
    try:
        runner = CycleRunner(cfg, cell, agent)
        record = runner.run_once()
        assert record.success is True and runner.frames_refused == 1
        assert np.allclose(runner.last_frame.tool_position, cfg.robot.home.position, atol=0.01)
        place = [plan for plan in cell.plans if plan[0] == "place"]
        assert place[0][2] < agent.decisions[1][0] < place[0][3]   # decided on the picture at home, while placing
    finally:
        cell.close()


class _Posed(_Watched):
    """Keeps each plan's moves too."""

    def __init__(self, cfg):
        super().__init__(cfg)
        self.moves: list[tuple[str, dict[str, MoveL]]] = []

    def execute(self, plan):
        self.moves.append((plan.plan.primitive, {s.label: s for s in plan.plan.steps if isinstance(s, MoveL)}))
        return super().execute(plan)


@pytest.mark.parametrize("overlap", [True, False])
def test_with_carry_at_grasp_yaw_the_pick_reaches_home_and_the_place_at_the_grasps_wrist_angle(tmp_path, overlap):
    cfg, cell, _ = _cell_and_agent(tmp_path, _Posed)
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, carry_at_grasp_yaw=True,
                                                             decide_while_placing=overlap))
    row, col = base_to_pixel(-0.50, 0.05, cfg.workspace)
    agent = _Scripted([Action("grasp", int(row), int(col), 3, 16)])   # 67.5 degrees
    try:
        assert CycleRunner(cfg, cell, agent).run_once().success is True
        moves = dict(cell.moves)

        def yaw(m: MoveL) -> float:
            r = np.asarray(m.pose.matrix)
            return float(np.degrees(np.arctan2(r[1, 0], r[0, 0])))

        assert yaw(moves["grasp"]["home"]) == pytest.approx(67.5)
        assert yaw(moves["place"]["place"]) == pytest.approx(67.5), "the place plan got the grasp's angle"
    finally:
        cell.close()


@pytest.mark.parametrize("overlap", [True, False])
def test_the_next_pick_turns_the_wrist_from_where_the_carried_pick_left_it(tmp_path, overlap):
    cfg, cell, _ = _cell_and_agent(tmp_path, _Posed)
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, carry_at_grasp_yaw=True,
                                                             decide_while_placing=overlap))
    pixels = [base_to_pixel(x, y, cfg.workspace) for x, y in ((-0.50, 0.05), (-0.40, -0.12), (-0.62, -0.12))]
    # 67.5 degrees, then -67.5 twice: its equivalent 112.5 is a 45-degree turn from the carried 67.5 (-67.5 one of
    # 135), and from home (after a fresh start) -67.5 is the nearer one
    agent = _Scripted([Action("grasp", int(r), int(c), k, 16) for (r, c), k in zip(pixels, (3, 13, 13))])
    try:
        runner = CycleRunner(cfg, cell, agent)
        assert runner.run_once().success is True and runner.run_once().success is True
        runner.forget_state()   # as after a reset: the arm is sent home before the next picture
        runner.run_once()
        grasps = [moves for primitive, moves in cell.moves if primitive == "grasp"]
        places = [moves for primitive, moves in cell.moves if primitive == "place"]

        def yaw(m: MoveL) -> float:
            r = np.asarray(m.pose.matrix)
            return float(np.degrees(np.arctan2(r[1, 0], r[0, 0])))

        assert [yaw(g["approach"]) for g in grasps] == pytest.approx([67.5, 112.5, -67.5])
        assert [yaw(p_["place"]) for p_ in places][:2] == pytest.approx([67.5, 112.5])
    finally:
        cell.close()


class _QuickPlace(_Watched):
    """A place that takes 0.1 s on the cell's clock, whatever the simulator took."""

    def execute(self, plan):
        result = super().execute(plan)
        return dataclasses.replace(result, duration=0.1) if plan.plan.primitive == "place" else result


class _SlowSecondThought(_Scripted):
    """Every decision after the first takes 0.6 s."""

    def decide(self, heightmaps, step):
        if self.decisions:
            time.sleep(0.6)
        return super().decide(heightmaps, step)


def test_a_decision_longer_than_the_place_counts_its_uncovered_part_as_the_controllers_time(tmp_path):
    cfg, cell, scripted = _cell_and_agent(tmp_path, cls=_QuickPlace)
    agent = _SlowSecondThought(scripted.actions)
    try:
        runner = CycleRunner(cfg, cell, agent)
        first = runner.run_once()
        # 0.5 s of the 0.6 s decision stood the arm still at the place: out of execute, into the controller's time
        unphased = first.duration - sum(first.timings.values())
        assert 0.45 < unphased < 0.7
        second = runner.run_once()
        assert second.timings["decide"] > 0.6 and 0.05 < second.decide_hidden <= 0.1
    finally:
        cell.close()


def test_without_decide_while_placing_the_arm_goes_home_and_the_picture_is_taken_after_the_place(tmp_path):
    cfg, cell, agent = _cell_and_agent(tmp_path)
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, decide_while_placing=False))
    try:
        runner = CycleRunner(cfg, cell, agent)
        assert runner.run_once().success is True
        place = [plan for plan in cell.plans if plan[0] == "place"]
        assert place[0][1][-1] == "home" and agent.decisions[1:] == []
    finally:
        cell.close()


def test_a_frame_taken_with_the_tool_over_the_workspace_is_refused(tmp_path):
    cfg, cell, agent = _cell_and_agent(tmp_path)
    try:
        over = MoveL(ToolPose.top_down(-0.50, 0.0, 0.30, 0.0), 0.25, 0.8, "over the table")
        assert cell.execute(check_plan(Plan("jog", (over,)), cfg)).completed
        store = Store(tmp_path)
        runner = CycleRunner(cfg, cell, agent, store=store)
        with pytest.raises(ToolInView, match="stands between the camera and the workspace") as raised:
            runner.perceive_now()
        assert isinstance(raised.value, CellFault) and runner.frames_refused == 1 and runner.last_frame is None
        assert compute_stats(store)["frames_refused"] == 1   # flgctl stats and the metrics page count it
        store.close()
    finally:
        cell.close()


def test_a_training_worker_s_refused_frame_goes_to_its_notes_for_the_learner_s_store(tmp_path):
    from flgd.training.collected import CollectingStore

    cfg, cell, agent = _cell_and_agent(tmp_path)
    notes = []
    try:
        over = MoveL(ToolPose.top_down(-0.50, 0.0, 0.30, 0.0), 0.25, 0.8, "over the table")
        assert cell.execute(check_plan(Plan("jog", (over,)), cfg)).completed
        runner = CycleRunner(cfg, cell, agent, store=CollectingStore(lambda *note: notes.append(note)))
        with pytest.raises(ToolInView):
            runner.perceive_now()
        assert [n[0] for n in notes] == ["frame_refused"] and "camera" in notes[0][2]
    finally:
        cell.close()


def test_a_picture_at_home_that_shows_the_tool_is_not_decided_on_the_arm_places_first(tmp_path):
    """A cell that reports its tool in view at the home capture: the cycle does not decide on that picture; it
    places, goes home and takes the picture after, as it does without the overlap."""
    cfg, cell, agent = _cell_and_agent(tmp_path)
    try:
        runner = CycleRunner(cfg, cell, agent)
        runner.current = runner.perceive_now()
        honest = cell.capture

        def capture_once_with_the_tool_in_view():
            cell.capture = honest   # only the capture at home with the object held shows the tool
            return dataclasses.replace(honest(), tool_position=(-0.50, 0.0, 0.30))

        cell.capture = capture_once_with_the_tool_in_view
        record = runner.run_once()
        assert record.success is True and runner.frames_refused == 1
        place = [plan for plan in cell.plans if plan[0] == "place"]
        assert place[-1][1][-1] == "home" and len(agent.decisions) == 1   # nothing decided ahead
        assert tool_in_view(runner.last_frame.tool_position, cfg) == ""   # the picture kept was taken after
    finally:
        cell.close()


@pytest.mark.parametrize("cls", [_Watched, _OnTheWay])
def test_a_pick_dropped_on_the_way_to_the_place_takes_back_the_decision_made_on_it(tmp_path, cls):
    cfg, cell, agent = _cell_and_agent(tmp_path, cls)
    cell.grip_gives_way = True
    try:
        runner = CycleRunner(cfg, cell, agent)
        record = runner.run_once()
        assert record.success is False and "dropped" in record.failure
        assert agent.outcomes == [False]   # the provisional "held" was taken back, the failure recorded
        assert agent.taken == 1 and len(agent.decisions) == 2   # the decision made on "held" is discarded ...
        # the picture taken at home before the drop is not the next state: one taken after the place is
        assert np.allclose(runner.last_frame.tool_position, cfg.robot.place.position, atol=0.01)
        assert runner.current is not agent.decisions[1][1]
        second = runner.run_once()
        grasp_plans = [plan for plan in cell.plans if plan[0] == "grasp"]
        # ... and the next cycle decides again, before its grasp, the action the agent would have chosen anyway
        assert agent.decisions[2][0] < grasp_plans[1][2] and second.action == agent.actions[1]
    finally:
        cell.close()


class _FaultAtPlace(_Watched):
    """The arm faults (a protective stop, say) on the way to the place."""

    def execute(self, plan):
        if plan.plan.primitive == "place":
            raise CellFault("protective stop during move 'place' (injected)")
        return super().execute(plan)


class _FaultAtPlaceOnTheWay(_FaultAtPlace):
    on_the_way = True


@pytest.mark.parametrize("cls", [_FaultAtPlace, _FaultAtPlaceOnTheWay])
def test_a_fault_on_the_way_to_the_place_takes_back_the_outcome_and_the_decision_and_is_raised(tmp_path, cls):
    cfg, cell, agent = _cell_and_agent(tmp_path, cls=cls)
    store = Store(tmp_path)
    try:
        runner = CycleRunner(cfg, cell, agent, store=store)
        with pytest.raises(CellFault, match="injected"):
            runner.run_once()
        assert len(agent.decisions) == 2   # the next decision was made while the arm was on its way ...
        assert agent.outcomes == [] and agent.taken == 1   # ... and taken back with the outcome it rested on
        assert runner.current is None and runner._ahead is None   # the next cycle starts from a fresh picture
        [row] = store.action_log()
        assert row["outcome"] == "fault" and "injected" in row["failure"]
    finally:
        store.close()
        cell.close()


class _CameraHiccup(_Watched):
    """The camera fails once: the picture at home after the first grasp."""

    captures = 0

    def capture(self):
        self.captures += 1
        if self.captures == 2:
            raise CellFault("camera: no frame within 5 s (injected)")
        return super().capture()


def test_a_camera_fault_at_home_places_the_pick_first_and_takes_the_picture_after(tmp_path):
    cfg, cell, agent = _cell_and_agent(tmp_path, cls=_CameraHiccup)
    try:
        runner = CycleRunner(cfg, cell, agent)
        record = runner.run_once()
        assert record.success is True and cell.stats["grasped_out"] == 1   # placed, not left in the gripper
        place = [plan for plan in cell.plans if plan[0] == "place"]
        assert "home" in place[0][1] and len(agent.decisions) == 1   # the serial cycle: no decision ahead
        assert cell.captures == 3 and agent.outcomes == [True]
    finally:
        cell.close()


class _FailsSecondTime(_Scripted):
    def decide(self, heightmaps, step):
        if self.decisions:
            raise RuntimeError("the network failed (injected)")
        return super().decide(heightmaps, step)


def test_a_decision_that_fails_while_the_arm_places_takes_the_provisional_outcome_back(tmp_path):
    cfg, cell, scripted = _cell_and_agent(tmp_path)
    agent = _FailsSecondTime(scripted.actions)
    try:
        runner = CycleRunner(cfg, cell, agent)
        with pytest.raises(RuntimeError, match="injected"):
            runner.run_once()
        assert [plan[0] for plan in cell.plans] == ["home", "grasp", "place"]   # the arm placed the pick
        assert agent.outcomes == [] and runner._ahead is None
    finally:
        cell.close()


def test_a_decision_that_fails_on_the_way_home_is_taken_back_and_made_again_at_the_place(tmp_path):
    """The failure is logged and the arm goes on to the place; the pick's outcome is recorded once, as without
    deciding ahead, the next picture is taken at the place, and the decision made on it fails again."""
    cfg, cell, scripted = _cell_and_agent(tmp_path, _OnTheWay)
    agent = _FailsSecondTime(scripted.actions)
    try:
        runner = CycleRunner(cfg, cell, agent)
        assert runner.run_once().success is True
        assert [plan[0] for plan in cell.plans] == ["home", "grasp", "place"]   # the arm placed the pick
        assert agent.outcomes == [True] and runner._ahead is None
        assert np.allclose(runner.last_frame.tool_position, cfg.robot.place.position, atol=0.01)
        with pytest.raises(RuntimeError, match="injected"):
            runner.run_once()
    finally:
        cell.close()


def test_the_agent_takes_back_a_provisional_outcome_and_the_draws_made_after_it():
    from flgd.learning.agent import Agent
    from flgd.learning.networks import FastQNet

    cfg = make_config(objects=0)
    height = np.zeros((224, 224), dtype=np.float32)
    height[100:120, 100:120] = 0.04
    failed, grasp = Action("grasp", 110, 110, 0, 16), Action("grasp", 105, 112, 3, 16)
    agents = [Agent(cfg, FastQNet(), seed=3) for _ in range(2)]
    for agent in agents:
        agent.record_outcome(failed, False, height_after=height)
    agent, twin = agents
    saved = agent.outcome_state()
    agent.record_outcome(grasp, True, height_after=height)
    agent.rng.random(), agent._assign_rng.random()
    agent._exhausted = "nothing left to try"   # as a decision made on the provisional outcome may leave it
    assert agent.failed_grasps == 0
    agent.restore_outcome_state(saved)
    agent.record_outcome(grasp, False, height_after=height)
    twin.record_outcome(grasp, False, height_after=height)
    assert (agent.failed_grasps, agent.forced_moves, agent.previous) == (2, 0, grasp) == \
        (twin.failed_grasps, twin.forced_moves, twin.previous)
    assert agent.rng.random() == twin.rng.random() and agent._assign_rng.random() == twin._assign_rng.random()
    assert np.array_equal(agent.memory.suppressed(), twin.memory.suppressed())
    assert agent.stuck_reason() == twin.stuck_reason()


def test_a_snapshot_asked_for_with_the_arm_in_view_is_refused_without_faulting_the_daemon():
    from flgd.daemon.commands import fresh_snapshot
    from flgd.daemon.protocol import ProtocolError

    faults: list[str] = []

    def in_view():
        raise ToolInView("frame refused: the tool stands between the camera and the workspace")

    ctl = SimpleNamespace(runner=SimpleNamespace(perceive_now=in_view), fault=faults.append)
    with pytest.raises(ProtocolError, match="stands between the camera"):
        fresh_snapshot(ctl)
    assert faults == []   # the arm standing in view is no cell fault


def test_the_simulator_finds_the_arm_in_a_render_over_the_workspace_and_not_at_home(tmp_path):
    cfg = dataclasses.replace(make_config(objects=0, depth_noise=False, domain_randomization=False),
                              state_dir=str(tmp_path))
    cell = SimCell(cfg)
    try:
        _, depth, seg = cell._render(segmented=True)
        assert not cell._arm_over_workspace(depth, seg)
        over = MoveL(ToolPose.top_down(-0.50, 0.0, 0.25, 0.0), 0.25, 0.8, "over the table")
        assert cell.execute(check_plan(Plan("probe", (over,)), cfg)).completed
        _, depth, seg = cell._render(segmented=True)
        assert cell._arm_over_workspace(depth, seg)
    finally:
        cell.close()


class _Gripping(_Watched):
    """Keeps each plan's gripper commands and the widths it measured."""

    def __init__(self, cfg):
        super().__init__(cfg)
        self.gripper: list[tuple[str, list[GripperCommand], list[float]]] = []

    def execute(self, plan):
        result = super().execute(plan)
        self.gripper.append((plan.plan.primitive, [s for s in plan.plan.steps if isinstance(s, GripperCommand)],
                             list(result.widths)))
        return result


class _GrippingOnTheWay(_Gripping):
    on_the_way = True


@pytest.mark.parametrize("cls,overlap", [(_Gripping, False), (_Gripping, True), (_GrippingOnTheWay, True)])
def test_with_a_preshape_every_release_path_opens_only_its_gap_beyond_the_width_the_grasp_held(tmp_path, cls,
                                                                                               overlap):
    cfg = dataclasses.replace(make_config(objects=0, depth_noise=False, domain_randomization=False),
                              state_dir=str(tmp_path))
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, capture_on_the_way=cls.on_the_way,
                                                             decide_while_placing=overlap),
                              gripper=dataclasses.replace(cfg.gripper, preshape_margin=0.01))
    cell = cls(cfg)
    try:
        for x, y in ((-0.50, 0.05), (-0.40, -0.12), (-0.62, -0.12)):
            cube_at(cell, x, y, size=(0.04, 0.04, 0.04))
        row, col = base_to_pixel(-0.50, 0.05, cfg.workspace)
        agent = _Scripted([Action("grasp", int(row), int(col), 0, 16)])
        assert CycleRunner(cfg, cell, agent).run_once().success is True
        (grasp,) = [g for g in cell.gripper if g[0] == "grasp"]
        (place,) = [g for g in cell.gripper if g[0] == "place"]
        assert grasp[1][0].label == PRESHAPE_LABEL and grasp[1][0].width < cfg.gripper.open_width
        held = grasp[2][-1]
        assert held == pytest.approx(0.04, abs=0.004)
        assert [(s.width, s.proceed_after) for s in place[1]] == [(pytest.approx(held + 0.01), 0.0)]
    finally:
        cell.close()
