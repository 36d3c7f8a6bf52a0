"""The simulated cell's speed shortcuts keep what matters: shifts drag blocks, weak grips still slip,
and a carried block leaves with the gripper."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flgd.clutter import grasp_reward
from flgd.geometry import ToolPose
from flgd.plans import MoveL, Plan, plan_grasp, plan_home, plan_shift
from flgd.safety import check_plan
from sim_cell.cell import SimCell
from sim_cell.objects import ObjectSpec
from tests.test_sim_cell import cube_at, make_config, state


@pytest.fixture
def empty_cell():
    cell = SimCell(make_config(objects=0, depth_noise=False, domain_randomization=False))
    yield cell
    cell.close()


@pytest.mark.parametrize("size,theta", [((0.04, 0.04, 0.04), 0.0), ((0.06, 0.03, 0.03), math.pi / 3),
                                        ((0.05, 0.05, 0.025), 5 * math.pi / 4)])
def test_shift_on_a_free_block_drags_it_along_theta(empty_cell, size, theta):
    """The paper's shift: the closed fingers press shift_press into the top and drag the block.
    The intended press must not be taken for a collision."""
    cfg = empty_cell.config
    body = cube_at(empty_cell, -0.50, 0.0, size=size)
    before = state(empty_cell, body)
    plan = plan_shift(before.position[0], before.position[1], before.top - cfg.workspace.table_z, theta, cfg)
    result = empty_cell.execute(check_plan(plan, cfg))
    assert result.completed, result.failure
    after = state(empty_cell, body)
    assert after is not None and empty_cell.stats["left_workspace"] == 0
    u = np.array([math.cos(theta), math.sin(theta)])
    moved = np.array(after.position[:2]) - np.array(before.position[:2])
    assert 0.03 <= float(moved @ u) <= cfg.robot.shift_distance + 0.01
    assert abs(float(moved @ np.array([-u[1], u[0]]))) < 0.02
    # the block was dragged, not pressed into the table or tipped over
    assert abs(after.top - before.top) < 0.003


def test_shift_pressing_far_deeper_than_planned_is_a_collision_stop(empty_cell):
    """The compliant give covers the planned press only: a shift planned on a surface read 2 cm too
    low (the fingers would go 25 mm into the block) still stops the arm."""
    cfg = empty_cell.config
    body = cube_at(empty_cell, -0.50, 0.0, size=(0.04, 0.04, 0.04))
    before = state(empty_cell, body)
    plan = plan_shift(before.position[0], before.position[1], before.top - cfg.workspace.table_z - 0.02, 0.0, cfg)
    result = empty_cell.execute(check_plan(plan, cfg))
    assert not result.completed
    assert result.failure.startswith("collision stop")
    assert "mm into what it rests on" in result.failure


def test_a_block_too_heavy_for_the_grip_slips_out_during_the_lift(empty_cell):
    """Lifts after the grip are simulated before the carry becomes a jump, so a grip that cannot
    hold the block still fails by width and leaves the block on the table."""
    cfg = empty_cell.config
    spec = ObjectSpec(shape="cube", size=(0.04,), color=(0.2, 0.5, 0.9), position=(-0.5, 0.0, 0.021),
                      mass=8.0, friction=0.2)
    body = empty_cell.add_object(spec)
    s = state(empty_cell, body)
    result = empty_cell.execute(check_plan(plan_grasp(s.position[0], s.position[1], s.top - cfg.workspace.table_z,
                                                      0.0, cfg), cfg))
    assert result.completed, result.failure
    assert grasp_reward(result.widths[0], cfg.gripper) == 0.0
    left = state(empty_cell, body)
    assert left is not None and left.top < 0.05


def test_a_gripped_block_moves_with_the_gripper_and_is_carried_out(empty_cell):
    """After the trial lift the carry is a jump: the block must arrive between the fingers."""
    cfg = empty_cell.config
    body = cube_at(empty_cell, -0.55, 0.05, size=(0.05, 0.03, 0.03), yaw=-0.4)
    s = state(empty_cell, body)
    grasp = plan_grasp(s.position[0], s.position[1], s.top - cfg.workspace.table_z, -0.4 + math.pi / 2, cfg)
    # instead of going home (outside the workspace), end above another part of the workspace
    over = MoveL(ToolPose.top_down(-0.40, -0.12, 0.25, 0.3), cfg.robot.speed, cfg.robot.acceleration, "over")
    steps = tuple(over if getattr(st, "label", "") == "home" else st for st in grasp.steps)
    result = empty_cell.execute(check_plan(Plan("grasp", steps), cfg))
    assert result.completed, result.failure
    assert grasp_reward(result.widths[0], cfg.gripper) == 1.0
    held = state(empty_cell, body)
    tcp = empty_cell._tcp()[:3, 3]
    assert np.linalg.norm(tcp - np.array([-0.40, -0.12, 0.25])) < 0.002
    assert np.linalg.norm(np.array(held.position[:2]) - tcp[:2]) < 0.01
    assert abs(tcp[2] - held.position[2]) < 0.03
    # opening the gripper hands the measured block out of the cell
    empty_cell.execute(check_plan(plan_home(cfg), cfg))
    assert empty_cell.object_count == 0 and empty_cell.stats["grasped_out"] == 1
