"""The simulated cell's speed shortcuts keep what matters: shifts drag blocks, weak grips still slip,
a carried block leaves with the gripper, and sleeping blocks wake when touched or left unsupported."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest

from flgd.clutter import grasp_reward
from flgd.geometry import ToolPose
from flgd.plans import MoveL, Plan, plan_grasp, plan_home, plan_push, plan_shift
from flgd.safety import check_plan
from sim_cell.cell import SimCell
from sim_cell.objects import ObjectSpec
from tests.fakes.sim import cube_at, make_config, state


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
    """The carry is simulated: the block must arrive centred between the fingers (coupled like the RG2's, not
    two independent fingers that drift to one side together with the block)."""
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


def _asleep(cell: SimCell, body: int) -> bool:
    """A sleeping body reports exactly zero velocity (an awake resting one jitters by micrometres per second)."""
    return p.getBaseVelocity(body, physicsClientId=cell._client) == ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


def test_a_block_whose_support_is_removed_wakes_and_falls(empty_cell):
    """Still blocks sleep (the solver skips them); a sleeping block that lost what it rested on must not hang
    in the air: pybullet does not wake it, the cell does."""
    bottom = cube_at(empty_cell, -0.5, 0.0, size=(0.08, 0.03, 0.03))
    top = empty_cell.add_object(ObjectSpec(shape="cube", size=(0.03,), position=(-0.5, 0.0, 0.046)), settle=0.5)
    assert _asleep(empty_cell, bottom) and _asleep(empty_cell, top)
    assert state(empty_cell, top).top > 0.055
    assert empty_cell.remove_object(bottom, settle=0.3)
    assert state(empty_cell, top).top < 0.032, "the cube fell onto the table"


def test_a_sleeping_block_is_pushed_like_an_awake_one(empty_cell):
    cfg = empty_cell.config
    body = cube_at(empty_cell, -0.50, 0.0, size=(0.04, 0.04, 0.04))
    empty_cell.simulate(0.5)
    assert _asleep(empty_cell, body)
    before = np.array(state(empty_cell, body).position)
    result = empty_cell.execute(check_plan(plan_push(-0.56, 0.0, 0.0, cfg), cfg))
    assert result.completed, result.failure
    moved = np.array(state(empty_cell, body).position) - before
    assert moved[0] > 0.03 and abs(moved[1]) < 0.02, moved
    # and after the push it is still again: every body below the stillness threshold, asleep or not
    lin, ang = p.getBaseVelocity(body, physicsClientId=empty_cell._client)
    assert np.linalg.norm(lin) < 0.01 and np.linalg.norm(ang) < 0.2
