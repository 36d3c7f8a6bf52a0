"""Primitive plans and the safety envelope."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flgd.actions import Action
from flgd.cell import ExecutionResult
from flgd.config import load_config
from flgd.config.loader import config_from_dict, config_to_dict
from flgd.config.messages import ConfigError
from flgd.cycle_record import held_at_place
from flgd.geometry import ToolPose, top_down_yaw
from flgd.perception import base_to_pixel, pixel_to_base
from flgd.plans import PLACE_CHECK_LABEL, PRESHAPE_LABEL, GripperCommand, MeasureWidth, MoveL, Plan, blended_runs, end_yaw, \
    move_kind, plan_action, plan_grasp, plan_push, plan_release, plan_shift
from flgd.safety import CheckedPlan, PlanRefused, check_plan

ROOT = Path(__file__).resolve().parents[1]
CFG = load_config(ROOT / "cell_config" / "sim.yaml")
REAL = load_config(ROOT / "cell_config" / "ur5e-d415.yaml")


def assert_inside_envelope(plan: Plan, cfg) -> None:
    """An independent restatement of the envelope, to check what check_plan let through."""
    sf = cfg.safety
    for step in plan.steps:
        if isinstance(step, MoveL):
            p = np.asarray(step.pose.position)
            r = np.asarray(step.pose.rotation)
            assert np.isfinite(p).all() and np.isfinite(r).all()
            assert sf.envelope_x[0] <= p[0] <= sf.envelope_x[1]
            assert sf.envelope_y[0] <= p[1] <= sf.envelope_y[1]
            assert sf.envelope_z[0] <= p[2] <= sf.envelope_z[1]
            assert p[2] >= cfg.workspace.table_z + sf.min_table_clearance - 1e-12
            assert np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0
            assert math.degrees(math.acos(min(1.0, -r[2, 2]))) <= math.degrees(sf.max_tilt) + 1e-9
            assert 0 < step.speed <= sf.max_speed and 0 < step.acceleration <= sf.max_acceleration
        elif isinstance(step, GripperCommand):
            assert 0 <= step.width <= 0.110 and 0 < step.force <= cfg.gripper.force
        else:
            assert isinstance(step, MeasureWidth)


def test_with_a_raise_speed_a_grasp_lifts_slowly_only_up_to_the_approach_height() -> None:
    cfg = dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, raise_speed=0.4))
    plan = plan_grasp(-0.5, 0.05, 0.05, 0.0, cfg)
    assert [s.label for s in plan.steps] == ["approach", "open", "descend", "close", "lift", "raise", "home", "held"]
    lift, raise_ = plan.steps[4], plan.steps[5]
    assert lift.pose.position == pytest.approx(plan.steps[0].pose.position) and lift.speed == cfg.robot.approach_speed
    assert raise_.pose.position[2] == pytest.approx(cfg.workspace.table_z + cfg.robot.lift_height)
    assert raise_.speed == 0.4
    check_plan(plan, cfg)


def test_a_grasp_whose_approach_height_reaches_the_lift_height_lifts_slowly_all_the_way() -> None:
    cfg = dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, approach_height=0.24, raise_speed=0.4))
    plan = plan_grasp(-0.5, 0.05, 0.05, 0.0, cfg)
    assert [s.label for s in plan.steps] == ["approach", "open", "descend", "close", "lift", "home", "held"]
    assert plan.steps[4].pose.position[2] == pytest.approx(cfg.workspace.table_z + cfg.robot.lift_height)
    assert plan.steps[4].speed == cfg.robot.approach_speed


def test_with_a_contact_clearance_a_grasps_slow_lift_ends_once_the_object_clears_its_surroundings() -> None:
    """The slow lift ends, and the slow guarded descent begins, 2 cm above the highest point within the contact
    radius; above it the gripper comes straight down at raise_speed from the unchanged approach height."""
    cfg = dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, raise_speed=0.4, contact_clearance=0.02,
                                                             contact_radius=0.05))
    h = np.zeros((224, 224), np.float32)
    h[110:116, 110:116] = 0.03              # the grasped block: fingertips go to 0 + clearance floor
    h[110:116, 122:128] = 0.04              # a taller neighbour 2.4 cm away: inside the 5 cm radius
    h[160:170, 160:170] = 0.20              # far away: not among the surroundings
    table = cfg.workspace.table_z
    plan = plan_action(Action("grasp", 113, 113, 0), h, cfg)
    steps = {s.label: s for s in plan.steps if isinstance(s, MoveL)}
    z = steps["descend"].pose.position[2]
    assert z == pytest.approx(table + cfg.safety.min_table_clearance)
    assert steps["approach"].pose.position[2] == pytest.approx(z + cfg.robot.approach_height)   # unchanged
    assert [s.label for s in plan.steps][:4] == ["approach", "open", "lower", "descend"]
    assert steps["lower"].pose.position[2] == pytest.approx(table + 0.04 + 0.02)   # fingertips clear the neighbour
    assert steps["lower"].pose.position[:2] == pytest.approx(steps["approach"].pose.position[:2])   # straight down
    assert steps["lower"].speed == 0.4 and steps["lower"].stop_on_contact > 0.0   # guarded: a part not seen
    assert steps["descend"].speed == cfg.robot.approach_speed and steps["descend"].stop_on_contact > 0.0
    assert steps["lift"].pose.position[2] == pytest.approx(z + 0.04 + 0.02)   # the block's bottom clears its top
    assert steps["lift"].speed == cfg.robot.approach_speed and steps["raise"].speed == 0.4
    # never higher than the approach height over the grasp point: a tall neighbour inside the radius
    h[110:116, 122:128] = 0.20
    tall = {s.label: s for s in plan_action(Action("grasp", 113, 113, 0), h, cfg).steps if isinstance(s, MoveL)}
    assert tall["lift"].pose.position[2] == pytest.approx(z + cfg.robot.approach_height)
    assert "lower" not in tall   # the whole descent slow
    # off (the default): slow up to the approach height, whatever surrounds the grasp
    h[110:116, 122:128] = 0.04
    off_cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, contact_clearance=0.0))
    off = {s.label: s for s in plan_action(Action("grasp", 113, 113, 0), h, off_cfg).steps if isinstance(s, MoveL)}
    assert off["lift"].pose.position[2] == pytest.approx(z + CFG.robot.approach_height)
    assert "lower" not in off
    check_plan(plan, cfg)


def _blending(radius: float, cfg=None):
    cfg = cfg or CFG
    return dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, raise_speed=0.4, blend_radius=radius))


def test_with_a_blend_radius_a_grasp_runs_its_raise_and_home_as_one_checked_path() -> None:
    """The raise blends into home; the lift never blends (it starts where a guarded descent stopped)."""
    cfg = _blending(0.03)
    plan = plan_grasp(-0.5, 0.05, 0.05, 0.3, cfg)
    moves = {s.label: s for s in plan.steps if isinstance(s, MoveL)}
    assert (moves["lift"].blend, moves["raise"].blend, moves["home"].blend) == (0.0, 0.03, 0.0)
    assert moves["approach"].blend == 0.0 and moves["descend"].blend == 0.0
    labels = [s.label for s in plan.steps]
    assert blended_runs(plan.steps) == [(0, 0), (2, 2), (4, 4), (labels.index("raise"), labels.index("home"))]
    check_plan(plan, cfg)
    # a radius larger than half the raise is cut to fit its corner
    near = plan_grasp(-0.5, 0.05, 0.05, 0.3, dataclasses.replace(
        _blending(0.05), robot=dataclasses.replace(_blending(0.05).robot, lift_height=0.25)))
    raise_ = {s.label: s for s in near.steps if isinstance(s, MoveL)}["raise"]
    assert raise_.blend == pytest.approx(min(0.05, 0.5 * (0.25 - 0.12)))
    # a push's retreat blends into home
    push = {s.label: s for s in plan_push(-0.5, 0.05, 0.3, cfg).steps if isinstance(s, MoveL)}
    assert push["retreat"].blend == 0.03 and push["push"].blend == 0.0
    check_plan(plan_push(-0.5, 0.05, 0.3, cfg), cfg)


def test_one_bad_corner_refuses_the_whole_blended_plan() -> None:
    """A corner is checked with its three poses: a radius past the middle of a line, a blend into or out of a
    guarded move, or into a gripper step, or on the plan's first move refuse the plan before anything moves."""
    cfg = _blending(0.03)
    plan = plan_grasp(-0.5, 0.05, 0.05, 0.3, cfg)
    i = [s.label for s in plan.steps].index("raise")
    lift = plan.steps[i]   # the raise: its incoming line is the lift

    def with_step(index: int, step) -> Plan:
        steps = list(plan.steps)
        steps[index] = step
        return dataclasses.replace(plan, steps=tuple(steps))

    too_wide = with_step(i, dataclasses.replace(lift, blend=0.09))   # the raise is 13 cm: more than half of it
    wide_cap = dataclasses.replace(cfg, safety=dataclasses.replace(cfg.safety, max_blend_radius=0.2))
    with pytest.raises(PlanRefused, match="more than half the incoming line") as refused:
        check_plan(too_wide, wide_cap)
    assert refused.value.step == i
    above_cap = with_step(i, dataclasses.replace(lift, blend=0.06))
    with pytest.raises(PlanRefused, match="safety.max_blend_radius"):
        check_plan(above_cap, cfg)
    d = [s.label for s in plan.steps].index("descend")
    with pytest.raises(PlanRefused, match="step that is not a move"):   # the descent is followed by the close
        check_plan(with_step(d, dataclasses.replace(plan.steps[d], blend=0.01)), cfg)
    a = [s.label for s in plan.steps].index("approach")
    with pytest.raises(PlanRefused, match="step that is not a move"):   # the approach is followed by the open
        check_plan(with_step(a, dataclasses.replace(plan.steps[a], blend=0.01)), cfg)
    push = plan_push(-0.5, 0.05, 0.3, cfg)   # its approach runs into the guarded descent
    pa = [s.label for s in push.steps].index("approach")
    steps = list(push.steps)
    steps[pa] = dataclasses.replace(steps[pa], blend=0.01)
    with pytest.raises(PlanRefused, match="guarded move"):
        check_plan(dataclasses.replace(push, steps=tuple(steps)), cfg)
    first = Plan("home", (MoveL(plan.steps[a].pose, 0.2, 1.0, "a", blend=0.01), MoveL(lift.pose, 0.2, 1.0, "b")))
    with pytest.raises(PlanRefused, match="first move cannot blend"):
        check_plan(first, cfg)
    # every point of the corner lies in the triangle of its three poses, so in a box envelope that holds them;
    # the envelope checks the points anyway (flgd.blending.corner_curve), and a pose outside refuses the plan
    outside = with_step(i + 1, dataclasses.replace(plan.steps[i + 1], pose=ToolPose.top_down(-0.5, 0.05, 0.5, 0.3)))
    with pytest.raises(PlanRefused, match="outside the envelope"):
        check_plan(outside, cfg)


def _centring(metres: float):
    return dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, grasp_centring=metres))


def test_a_grasp_near_the_end_of_a_bar_moves_along_the_pads_to_its_middle_by_at_most_the_limit() -> None:
    h = np.zeros((224, 224), np.float32)
    h[100:140, 110:125] = 0.03    # an 8 cm bar along the rows: the pads' axis of a grasp closing along x (angle 0)
    h[140:160, 110:125] = 0.012   # a lower neighbour touching its end: not the surface the fingers grip
    near_end = Action("grasp", 105, 117, 0)
    res = CFG.workspace.resolution

    def target(cfg, action=near_end):
        return plan_action(action, h, cfg).target

    chosen = pixel_to_base(105, 117, 0.03, CFG.workspace)
    assert target(CFG)[:2] == pytest.approx(chosen[:2])                           # off by default
    assert target(_centring(0.05))[:2] == pytest.approx((chosen[0], pixel_to_base(119.5, 117, 0, CFG.workspace)[1]))
    assert target(_centring(0.02))[:2] == pytest.approx((chosen[0], chosen[1] + 0.02))   # at most the limit
    assert target(_centring(0.02))[2] == pytest.approx(plan_action(near_end, h, CFG).target[2])
    # closing along y (angle pi/2): the pads lie along x, across the bar's 3 cm: centred on its width
    across = Action("grasp", 120, 112, 4)
    assert target(_centring(0.05), across)[:2] == pytest.approx(
        (pixel_to_base(120, 117, 0, CFG.workspace)[0], pixel_to_base(120, 112, 0, CFG.workspace)[1]), abs=res / 2)
    # a grasp on the table has no surface to centre on
    assert target(_centring(0.05), Action("grasp", 20, 20, 0))[:2] == pytest.approx(
        pixel_to_base(20, 20, 0, CFG.workspace)[:2])
    check_plan(plan_action(near_end, h, _centring(0.05)), CFG)


def test_grasp_plan_shape() -> None:
    plan = plan_grasp(-0.5, 0.05, 0.05, math.radians(30), CFG)
    labels = [s.label for s in plan.steps]
    assert labels == ["approach", "open", "descend", "close", "lift", "home", "held"]
    descend = plan.steps[2].pose
    assert descend.position == pytest.approx((-0.5, 0.05, 0.05 - CFG.robot.grasp_depth))
    assert plan.steps[0].pose.position[2] == pytest.approx(descend.position[2] + CFG.robot.approach_height)
    assert plan.steps[4].speed == CFG.robot.approach_speed   # the whole lift slow: raise_speed is off by default
    # Fingers close along theta: tool x axis = (cos, sin, 0); tool z points down.
    r = descend.matrix
    assert r[:, 0] == pytest.approx([math.cos(math.radians(30)), math.sin(math.radians(30)), 0], abs=1e-12)
    assert r[:, 2] == pytest.approx([0, 0, -1])
    assert_inside_envelope(plan, CFG)
    check_plan(plan, CFG)


def test_grasp_yaw_is_wrapped_for_a_symmetric_gripper() -> None:
    a = plan_grasp(-0.5, 0.0, 0.03, math.radians(200), CFG).steps[2].pose.matrix
    b = plan_grasp(-0.5, 0.0, 0.03, math.radians(20), CFG).steps[2].pose.matrix
    assert a == pytest.approx(b)


def test_grasp_never_goes_below_the_clearance_floor() -> None:
    plan = plan_grasp(-0.5, 0.0, 0.005, 0.0, CFG)  # a flat object, 5 mm high
    assert plan.steps[2].pose.position[2] == pytest.approx(CFG.workspace.table_z + CFG.safety.min_table_clearance)


def test_push_travels_ten_cm_along_theta_near_the_table() -> None:
    theta = math.radians(45)
    plan = plan_push(-0.6, -0.1, theta, CFG)
    start, end = plan.steps[2].pose.position, plan.steps[3].pose.position
    assert start[2] == end[2] == pytest.approx(CFG.workspace.table_z + CFG.robot.push_height)
    travel = np.subtract(end, start)
    assert np.linalg.norm(travel) == pytest.approx(0.10)
    assert travel[:2] / 0.10 == pytest.approx([math.cos(theta), math.sin(theta)])
    assert plan.steps[0] == GripperCommand(CFG.gripper.closed_width, CFG.gripper.force, "close")
    check_plan(plan, CFG)


def test_push_end_is_clamped_to_the_workspace() -> None:
    plan = plan_push(-0.3, 0.0, 0.0, CFG)  # heading +x, 2.4 cm from the edge
    assert plan.steps[3].pose.position[0] == pytest.approx(CFG.workspace.x[1])


def test_shift_presses_on_the_object_and_drags() -> None:
    plan = plan_shift(-0.5, 0.0, 0.05, math.pi / 2, CFG)
    start, end = plan.steps[2].pose.position, plan.steps[3].pose.position
    assert start[2] == pytest.approx(0.05 - CFG.robot.shift_press)
    assert np.subtract(end, start) == pytest.approx([0, CFG.robot.shift_distance, 0], abs=1e-12)


def test_move_becomes_push_or_shift_by_height_at_its_point() -> None:
    hm = np.zeros((224, 224), np.float32)
    hm[100:120, 100:120] = 0.04
    on = plan_action(Action("push", 110, 110, 4), hm, CFG)
    off = plan_action(Action("shift", 10, 10, 4), hm, CFG)
    assert on.primitive == "shift" and off.primitive == "push"
    assert move_kind(0.0, CFG) == "push" and move_kind(0.04, CFG) == "shift"
    x, y, _ = pixel_to_base(110, 110, 0.0, CFG.workspace)
    assert on.target[:2] == pytest.approx((x, y))


def test_with_carry_at_grasp_yaw_the_wrist_keeps_the_grasps_angle_to_home_and_the_place() -> None:
    carry = dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, carry_at_grasp_yaw=True))
    angle = math.radians(120)   # the RG2 is symmetric: the wrist turns to -60 degrees
    for cfg, expected in ((carry, math.radians(-60)), (CFG, CFG.robot.home.yaw)):
        grasp = plan_grasp(-0.5, 0.05, 0.05, angle, cfg)
        moves = {s.label: s for s in grasp.steps if isinstance(s, MoveL)}
        place = {s.label: s for s in plan_release(True, cfg, carry_yaw=end_yaw(grasp, cfg)).steps
                 if isinstance(s, MoveL)}

        def yaw(m: MoveL) -> float:
            r = np.asarray(m.pose.matrix)
            return math.atan2(r[1, 0], r[0, 0])

        assert yaw(moves["descend"]) == pytest.approx(math.radians(-60))
        assert [yaw(moves["home"]), yaw(place["place"]), yaw(place["home"])] == pytest.approx([expected] * 3)
        check_plan(grasp, cfg)


def _yaw(m: MoveL) -> float:
    return top_down_yaw(m.pose.matrix)


@pytest.mark.parametrize("start, angle, turned_to", [
    (67.5, -67.5, 112.5),    # the equivalent a quarter turn away, not 135 degrees back
    (0.0, 90.0, 90.0),       # from the home angle: as wrap_symmetric_yaw (a tie goes to +90)
    (-22.5, 90.0, -90.0),
    (112.5, 157.5, 157.5 - 180.0),   # 157.5 is past WRIST_YAW_LIMIT (135) from home: the other equivalent
    (-135.0, 0.0, 0.0),
])
def test_a_plan_turns_the_wrist_to_the_grasps_equivalent_nearest_where_it_stands(start, angle, turned_to) -> None:
    hm = np.zeros(CFG.workspace.shape)
    row, col = base_to_pixel(-0.5, 0.05, CFG.workspace)
    rotation = round(math.radians(angle) / (2 * math.pi / 16)) % 16
    for primitive in ("grasp", "push"):
        plan = plan_action(Action(primitive, row, col, rotation), hm, CFG, wrist_yaw=math.radians(start))
        first = next(s for s in plan.steps if isinstance(s, MoveL))
        assert math.degrees(_yaw(first)) == pytest.approx(turned_to), primitive
        assert abs(math.degrees(math.remainder(math.radians(turned_to - angle), math.pi))) == pytest.approx(0.0,
                                                                                                        abs=1e-6)
        check_plan(plan, CFG)


def test_the_place_keeps_a_carried_yaw_beyond_a_quarter_turn() -> None:
    carry = dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, carry_at_grasp_yaw=True))
    grasp = plan_grasp(-0.5, 0.05, 0.05, math.radians(-67.5), carry, wrist_yaw=math.radians(90.0))
    assert math.degrees(end_yaw(grasp, carry)) == pytest.approx(112.5)   # carried home at the angle it grasped at
    place = [s for s in plan_release(True, carry, carry_yaw=end_yaw(grasp, carry)).steps if isinstance(s, MoveL)]
    assert [math.degrees(_yaw(m)) for m in place] == pytest.approx([112.5, 112.5])


def test_a_home_yaw_away_from_zero_keeps_every_turn_short_and_the_carried_yaw_unwrapped() -> None:
    home = dataclasses.replace(CFG.robot.home, yaw=math.radians(100.0))
    place = dataclasses.replace(CFG.robot.place, yaw=math.radians(100.0))
    cfg = dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, home=home, place=place,
                                                             carry_at_grasp_yaw=True))
    wrist = None
    for angle in (20.0, 200.0, -70.0, 157.5, 0.0, 45.0, -135.0, 110.0):
        grasp = plan_grasp(-0.5, 0.05, 0.05, math.radians(angle), cfg, wrist_yaw=wrist)
        start = cfg.robot.home.yaw if wrist is None else wrist
        yaws = [top_down_yaw(m.matrix, cfg.robot.home.yaw) for m in grasp.poses]
        assert abs(yaws[0] - start) <= math.pi - 0.1, (angle, math.degrees(start), math.degrees(yaws[0]))
        assert all(abs(y - cfg.robot.home.yaw) <= 0.75 * math.pi + 1e-9 for y in yaws)
        wrist = end_yaw(grasp, cfg)
        assert wrist == pytest.approx(yaws[0])   # the yaw the plan named, beyond 180 degrees too
        placed = plan_release(True, cfg, home=False, carry_yaw=wrist)
        assert top_down_yaw(placed.poses[-1].matrix, cfg.robot.home.yaw) == pytest.approx(wrist)


def test_a_place_yaw_beyond_the_wrists_range_from_home_is_refused() -> None:
    place = dataclasses.replace(CFG.robot.place, yaw=math.radians(150.0))
    with pytest.raises(ConfigError, match="robot.place.yaw"):
        config_from_dict({**config_to_dict(CFG), "robot": {**config_to_dict(CFG)["robot"],
                                                            "place": config_to_dict(place)}})


def test_release_places_a_held_object_and_only_opens_otherwise() -> None:
    held = plan_release(True, CFG)
    assert [s.label for s in held.steps] == ["place", PLACE_CHECK_LABEL, "open", "home"]
    assert isinstance(held.steps[1], MeasureWidth)  # still held at the place pose, read before the fingers open
    assert plan_release(False, CFG).steps == (GripperCommand(CFG.gripper.open_width, CFG.gripper.force, "open"),)
    check_plan(held, CFG)
    # gripper.release_gap: both releases go on once the fingers opened that far; nothing else does
    gap = dataclasses.replace(CFG, gripper=dataclasses.replace(CFG.gripper, release_gap=0.01))
    opens = [s for p in (plan_release(True, gap), plan_release(False, gap)) for s in p.steps
             if isinstance(s, GripperCommand)]
    assert [s.proceed_after for s in opens] == [0.01, 0.01]
    grasp = plan_grasp(-0.5, 0.05, 0.05, 0.0, gap)
    assert all(s.proceed_after == 0.0 for s in grasp.steps if isinstance(s, GripperCommand))


def test_with_home_at_the_place_a_pick_is_judged_by_its_width_at_home_and_the_place_only_opens() -> None:
    at_place = dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, home=CFG.robot.place))
    release = GripperCommand(CFG.gripper.open_width, CFG.gripper.force, "open")
    assert plan_release(True, at_place).steps == (release,)            # no move there, no second reading
    assert plan_release(True, at_place, home=False).steps == (release,)
    check_plan(plan_release(True, at_place), at_place)
    opened = ExecutionResult(True, [])
    assert held_at_place(opened, ExecutionResult(True, [0.03]), at_place) == (True, "")
    held, why = held_at_place(opened, ExecutionResult(True, [0.0]), at_place)
    assert not held and "dropped" in why
    # another yaw at the place is a move there (unless the wrist carries the grasp's yaw to both)
    turned = dataclasses.replace(at_place.robot.place, yaw=0.3)
    other = dataclasses.replace(at_place, robot=dataclasses.replace(at_place.robot, place=turned))
    assert [s.label for s in plan_release(True, other).steps] == ["place", PLACE_CHECK_LABEL, "open", "home"]
    assert held_at_place(opened, ExecutionResult(True, [0.03]), other)[0] is False   # read at the place or nothing
    carried = dataclasses.replace(other, robot=dataclasses.replace(other.robot, carry_at_grasp_yaw=True))
    assert plan_release(True, carried, carry_yaw=0.5).steps == (release,)


@pytest.mark.parametrize("mutate,needle", [
    (lambda p: dataclasses.replace(p, steps=()), "no steps"),
    (lambda p: _replace_move(p, position=(-0.5, 0.0, 0.002)), "below the table"),
    (lambda p: _replace_move(p, position=(-0.5, 0.0, 1.0)), "outside the envelope"),
    (lambda p: _replace_move(p, position=(5.0, 0.0, 0.1)), "outside the envelope"),
    (lambda p: _replace_move(p, position=(float("nan"), 0.0, 0.1)), "finite"),
    (lambda p: _replace_move(p, speed=10.0), "speed"),
    (lambda p: _replace_move(p, speed=-0.1), "speed"),
    (lambda p: _replace_move(p, acceleration=float("inf")), "acceleration"),
    (lambda p: _replace_move(p, rotation=((1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0))), "tilted"),
    (lambda p: _replace_move(p, rotation=((2.0, 0, 0), (0, -1.0, 0), (0, 0, -1.0))), "rotation"),
    (lambda p: dataclasses.replace(p, steps=p.steps + (GripperCommand(0.5, 10.0),)), "gripper width"),
    (lambda p: dataclasses.replace(p, steps=p.steps + (GripperCommand(0.05, 400.0),)), "gripper force"),
    (lambda p: dataclasses.replace(p, steps=p.steps + (GripperCommand(0.085, 10.0, proceed_after=-0.01),)),
     "proceed_after"),
    (lambda p: dataclasses.replace(p, steps=p.steps + (GripperCommand(0.0, 10.0, proceed_after=0.01),)),
     "only an opening"),
    (lambda p: dataclasses.replace(p, steps=p.steps + ("moveJ",)), "unknown step"),
])
def test_bad_plans_are_refused_with_a_reason(mutate, needle) -> None:
    good = plan_grasp(-0.5, 0.0, 0.03, 0.3, CFG)
    with pytest.raises(PlanRefused) as info:
        check_plan(mutate(good), CFG)
    assert needle in str(info.value)


def _replace_move(plan: Plan, **changes) -> Plan:
    i = 2  # the descend step
    old = plan.steps[i]
    pose = old.pose
    if "position" in changes:
        pose = ToolPose(changes.pop("position"), pose.rotation)
    if "rotation" in changes:
        pose = ToolPose(pose.position, changes.pop("rotation"))
    new = dataclasses.replace(old, pose=pose, **changes)
    return dataclasses.replace(plan, steps=plan.steps[:i] + (new,) + plan.steps[i + 1:])


def test_a_checked_plan_is_reverified_by_the_cell_config() -> None:
    checked = check_plan(plan_grasp(-0.5, 0.0, 0.03, 0.3, CFG), CFG)
    assert isinstance(checked, CheckedPlan)
    assert checked.verify(CFG) is checked.plan
    tight = dataclasses.replace(CFG, safety=dataclasses.replace(CFG.safety, max_speed=0.05))
    with pytest.raises(PlanRefused):
        checked.verify(tight)


adversarial_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-2.0, 2.0),
    st.sampled_from([0.0, -0.0, 1e308, -1e308, 5e-324, float("nan"), float("inf"), -float("inf")]),
)


@settings(max_examples=6000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(x=adversarial_floats, y=adversarial_floats, h=adversarial_floats, angle=adversarial_floats,
       kind=st.sampled_from(["grasp", "push", "shift"]), real=st.booleans())
def test_no_plan_that_passes_holds_a_pose_outside_the_envelope(x, y, h, angle, kind, real) -> None:
    cfg = REAL if real else CFG
    plan = {"grasp": lambda: plan_grasp(x, y, h, angle, cfg), "push": lambda: plan_push(x, y, angle, cfg),
            "shift": lambda: plan_shift(x, y, h, angle, cfg)}[kind]()
    try:
        check_plan(plan, cfg)
    except PlanRefused as exc:
        assert exc.reason.strip(), "a refusal must say why"
        return
    assert_inside_envelope(plan, cfg)


@settings(max_examples=4500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(row=st.integers(-10**6, 10**6) | st.integers(-5, 230), col=st.integers(-10**6, 10**6) | st.integers(-5, 230),
       rotation=st.integers(0, 15), prim=st.sampled_from(["grasp", "push", "shift"]),
       height=adversarial_floats, real=st.booleans())
def test_actions_on_adversarial_heightmaps(row, col, rotation, prim, height, real) -> None:
    cfg = REAL if real else CFG
    hm = np.full(cfg.workspace.shape, np.float32(0.02), np.float32)
    if 0 <= row < hm.shape[0] and 0 <= col < hm.shape[1]:
        with np.errstate(over="ignore"):
            hm[row, col] = np.float32(height)
    plan = plan_action(Action(prim, row, col, rotation), hm, cfg)
    try:
        check_plan(plan, cfg)
    except PlanRefused as exc:
        assert exc.reason.strip()
        return
    assert_inside_envelope(plan, cfg)
    assert 0 <= row < hm.shape[0] and 0 <= col < hm.shape[1], "a pixel off the heightmap must be refused"


def test_a_push_descends_guarded_and_its_abort_path_is_straight_up_then_home_checked_with_it() -> None:
    from flgd.plans import ABORT_LABEL, abort_steps

    plan = plan_push(-0.5, 0.05, 0.3, CFG)
    labels = [s.label for s in plan.steps]
    i = labels.index("descend")
    descend, approach = plan.steps[i], plan.steps[labels.index("approach")]
    assert descend.stop_on_contact == CFG.robot.descent_contact_force > 0 and descend.abort_on_contact
    back = abort_steps(plan.steps, i)
    assert [m.label for m in back] == [ABORT_LABEL, "home"]
    assert back[0].pose == approach.pose and back[1].pose == plan.steps[-1].pose
    # a shift presses on the object's top on purpose: its descent is not guarded
    shift = plan_shift(-0.5, 0.05, 0.04, 0.3, CFG)
    assert not any(s.abort_on_contact or s.stop_on_contact for s in shift.steps if isinstance(s, MoveL))
    check_plan(plan, CFG)
    # abort_on_contact on a move that cannot stop is refused
    unguarded = dataclasses.replace(plan, steps=tuple(dataclasses.replace(s, stop_on_contact=0.0) if k == i else s
                                                      for k, s in enumerate(plan.steps)))
    with pytest.raises(PlanRefused, match="not guarded"):
        check_plan(unguarded, CFG)


PRESHAPE = dataclasses.replace(CFG, gripper=dataclasses.replace(CFG.gripper, preshape_margin=0.01))


def test_a_preshaped_grasp_sets_its_opening_on_the_way_and_has_the_fingers_stopped_there_before_the_descent():
    h = np.zeros((224, 224), dtype=np.float32)
    h[100:120, 100:116] = 0.03   # 32 mm across the closing line (along the columns)
    plan = plan_action(Action("grasp", 110, 108, 0), h, PRESHAPE)
    gripper = [s for s in plan.steps if isinstance(s, GripperCommand)]
    first = plan.steps[0]
    assert isinstance(first, GripperCommand) and first.label == PRESHAPE_LABEL and first.proceed_after > 0.0
    assert 0.052 <= first.width <= 0.056   # the block's 32 mm and 10 mm either side, to a pixel
    assert isinstance(plan.steps[1], MoveL) and plan.steps[1].label == "approach"
    assert isinstance(plan.steps[2], GripperCommand) and plan.steps[2].width == first.width
    assert plan.steps[2].proceed_after == 0.0
    assert [s.label for s in gripper] == [PRESHAPE_LABEL, "open", "close"]
    check_plan(plan, PRESHAPE)
    # without the margin: fully open at the approach pose, as before
    assert [s.width for s in plan_action(Action("grasp", 110, 108, 0), h, CFG).steps
            if isinstance(s, GripperCommand)] == [CFG.gripper.open_width, CFG.gripper.closed_width]


def test_only_a_grasps_first_step_repeated_before_its_descent_may_narrow_the_fingers_without_waiting():
    h = np.zeros((224, 224), dtype=np.float32)
    h[100:120, 100:116] = 0.03
    plan = plan_action(Action("grasp", 110, 108, 0), h, PRESHAPE)
    preshape, approach, stop, *rest = plan.steps
    assert isinstance(stop, GripperCommand)
    narrowing = (r"proceed_after .* only an opening to gripper.open_width .* or a grasp's pre-shape")
    descend = next(s for s in rest if isinstance(s, MoveL))
    unguarded = dataclasses.replace(descend, stop_on_contact=0.0)
    for steps in ((approach, preshape, stop, *rest),                                      # not the first step
                  (preshape, approach, *rest),                                            # never stopped
                  (preshape, approach, dataclasses.replace(stop, width=stop.width + 0.01), *rest),   # elsewhere
                  (preshape, approach, unguarded, stop, *rest[1:])):      # stopped only after coming down
        with pytest.raises(PlanRefused, match=narrowing):
            check_plan(dataclasses.replace(plan, steps=steps), PRESHAPE)
    push = plan_push(-0.5, 0.0, 0.0, PRESHAPE)
    with pytest.raises(PlanRefused, match=narrowing):
        check_plan(dataclasses.replace(push, steps=(preshape, stop, *push.steps)), PRESHAPE)


def test_with_a_preshape_a_release_opens_a_gap_beyond_the_width_held_and_waits_for_it():
    gap = dataclasses.replace(PRESHAPE, gripper=dataclasses.replace(PRESHAPE.gripper, release_gap=0.015))
    for cfg, opened in ((PRESHAPE, 0.01), (gap, 0.015)):
        for held in (True, False):
            release = [s for s in plan_release(held, cfg, width=0.03).steps if isinstance(s, GripperCommand)]
            assert release == [GripperCommand(0.03 + opened, cfg.gripper.force, "open")]
            check_plan(plan_release(held, cfg, width=0.03), cfg)
    # an unknown width, or no pre-shape: fully open, going on after the release gap
    assert plan_release(False, gap).steps == (GripperCommand(gap.gripper.open_width, gap.gripper.force, "open",
                                                             proceed_after=0.015),)
    assert plan_release(False, CFG, width=0.03).steps == (GripperCommand(CFG.gripper.open_width,
                                                                         CFG.gripper.force, "open"),)
