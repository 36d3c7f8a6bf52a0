"""The cycle's grasp judgement on the simulated cell: picked means still held at the place pose."""

from __future__ import annotations

import dataclasses

import pybullet as p
import pytest

from flgd.actions import Action
from flgd.cycle import CycleRunner
from flgd.perception import base_to_pixel
from flgd.store import Store
from sim_cell.cell import SimCell
from tests.fakes.agents import ScriptedAgentBase, scripted_decision
from tests.fakes.sim import cube_at, make_config, state


class _GraspAt(ScriptedAgentBase):
    """An agent that grasps at one pixel, closing along base x, and keeps what it was told."""

    def __init__(self, action: Action):
        super().__init__()
        self.action = action

    def decide(self, heightmaps, step):
        return scripted_decision(self.action, heightmaps)


class _GripGivesWay(SimCell):
    """The simulated cell, except that a held object weighs 20 kg from the moment the arm leaves home for the
    place pose: five times what two 40 N pads hold by friction, so it slides out on the way."""

    def execute(self, plan):
        if plan.plan.primitive == "place":
            for body in self._world.held:
                p.changeDynamics(body, -1, mass=20.0, physicsClientId=self._client)
        return super().execute(plan)


@pytest.mark.parametrize("grip_gives_way", [False, True])
def test_a_block_dropped_on_the_way_to_the_place_is_a_failed_grasp_in_the_record_and_the_store(tmp_path,
                                                                                              grip_gives_way):
    cfg = dataclasses.replace(make_config(objects=0, depth_noise=False, domain_randomization=False),
                              state_dir=str(tmp_path))
    cell = (_GripGivesWay if grip_gives_way else SimCell)(cfg)
    store = Store(tmp_path)
    try:
        body = cube_at(cell, -0.50, 0.05, size=(0.04, 0.04, 0.04))
        row, col = base_to_pixel(-0.50, 0.05, cfg.workspace)
        agent = _GraspAt(Action("grasp", int(row), int(col), 0, 16))
        record = CycleRunner(cfg, cell, agent, store=store).run_once()
        assert record.outcome == "executed" and record.kind == "grasp"
        transition = list(store.iter_transitions())[-1]
        logged = store.action_log()[-1]
        if grip_gives_way:
            assert record.success is False and record.reward == 0.0 and agent.outcomes == [False]
            assert transition.reward == 0.0 and logged["success"] == 0
            assert "dropped" in record.failure and logged["failure"] == record.failure
            assert cell.stats["dropped"] == 1 and cell.stats["grasped_out"] == 0 and state(cell, body) is None
        else:
            assert record.success is True and record.reward == 1.0 and agent.outcomes == [True]
            assert transition.reward == 1.0 and logged["success"] == 1 and record.failure == ""
            assert cell.stats["grasped_out"] == 1 and cell.stats["dropped"] == 0
    finally:
        store.close()
        cell.close()


class _PlansSeen(SimCell):
    """The simulated cell, keeping every plan it ran."""

    def __init__(self, config):
        super().__init__(config)
        self.plans = []

    def execute(self, plan):
        self.plans.append(plan.plan)
        return super().execute(plan)


class _SlipsAfterTheReading(_PlansSeen):
    """A held object weighs 20 kg once the plan that read it held has ended: it slips out where the arm stands."""

    def _settle_until_still(self, limit):
        if self._world.held:
            for body in self._world.held:
                p.changeDynamics(body, -1, mass=20.0, physicsClientId=self._client)
            self._world.step(int(0.5 / self._world.dt))   # the grip gives way while the arm stands still
        return super()._settle_until_still(limit)


@pytest.mark.parametrize("slips", [False, True])
def test_with_home_at_the_place_a_pick_is_judged_by_its_width_at_home_and_the_place_only_opens(tmp_path, slips):
    """The reading at home is read over the bin: one that slips out after it falls where picks go, and is a pick
    in the record and in the cell's counts alike."""
    base = make_config(objects=0, depth_noise=False, domain_randomization=False)
    cfg = dataclasses.replace(base, state_dir=str(tmp_path),
                              robot=dataclasses.replace(base.robot, home=base.robot.place))
    cell = (_SlipsAfterTheReading if slips else _PlansSeen)(cfg)
    store = Store(tmp_path)
    try:
        body = cube_at(cell, -0.50, 0.05, size=(0.04, 0.04, 0.04))
        row, col = base_to_pixel(-0.50, 0.05, cfg.workspace)
        record = CycleRunner(cfg, cell, _GraspAt(Action("grasp", int(row), int(col), 0, 16)), store=store).run_once()
        assert record.outcome == "executed" and record.success is True and record.failure == ""
        assert cell.stats["grasped_out"] == 1 and cell.stats["dropped"] == 0 and state(cell, body) is None
        place = [plan for plan in cell.plans if plan.primitive == "place"]
        assert len(place) == 1 and [type(s).__name__ for s in place[0].steps] == ["GripperCommand"]
    finally:
        store.close()
        cell.close()


class _TimedSimCell(SimCell):
    """The simulated cell, remembering every plan's duration (simulated time) as it hands it back."""

    def __init__(self, cfg):
        super().__init__(cfg)
        self.durations: list[float] = []
        self.gripper_times: list[float] = []

    def execute(self, plan):
        result = super().execute(plan)
        self.durations.append(result.duration)
        self.gripper_times.append(result.gripper_time)
        return result


def test_a_cycle_records_the_time_its_plans_took_on_the_cells_own_clock(tmp_path):
    """Home before the capture, the grasp and the place: the record and the action log hold their summed
    simulated time, not the few wall-clock seconds the simulator needed for them."""
    cfg = dataclasses.replace(make_config(objects=0, depth_noise=False, domain_randomization=False),
                              state_dir=str(tmp_path))
    cell = _TimedSimCell(cfg)
    store = Store(tmp_path)
    try:
        cube_at(cell, -0.50, 0.05, size=(0.04, 0.04, 0.04))
        cube_at(cell, -0.35, -0.15, size=(0.04, 0.04, 0.04))   # the table is not cleared: no scene reset follows
        row, col = base_to_pixel(-0.50, 0.05, cfg.workspace)
        record = CycleRunner(cfg, cell, _GraspAt(Action("grasp", int(row), int(col), 0, 16)), store=store).run_once()
        assert record.success is True and len(cell.durations) == 3   # home, grasp, place
        assert record.cell_time == pytest.approx(sum(cell.durations)) and record.cell_time > 5.0
        assert store.action_log()[-1]["cell_time"] == pytest.approx(record.cell_time)
        # open, close, the width read at home, the width at the place and the open there: the gripper's part
        assert record.gripper_time == pytest.approx(sum(cell.gripper_times)) and 0.2 < record.gripper_time < 4.0
        assert store.action_log()[-1]["gripper_time"] == pytest.approx(record.gripper_time)
    finally:
        store.close()
        cell.close()
