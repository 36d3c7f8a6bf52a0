"""The UR5e cell against a fake at the ur_rtde class boundary.

``FakeURController`` models one UR controller in simulated time: linear
motion at the commanded speed, protective and emergency stops, lost
connections, a control script that dies, and False returns.  The four fake
interfaces (``FakeRTDEControl``, ``FakeRTDEReceive``, ``FakeRTDEIO``,
``FakeDashboard``) have the method names, arguments and failure behaviour of
ur_rtde 1.6's classes, and record every call, so the tests can check what
reached the "robot" and in which order.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from pathlib import Path

import numpy as np
import pytest

from flgd.camera_view import in_view_on_the_way, tool_in_view
from flgd.cell import CellFault, Frame, make_cell
from flgd.config import load_config
from flgd.geometry import ToolPose
from flgd.clutter import grasp_reward
from flgd.plans import GripperCommand, MeasureWidth, MoveL, Plan, plan_home
from flgd.safety import CheckedPlan, PlanRefused, check_plan
from flgd.hardware.rg2 import RG2XmlRpcDriver
from flgd.hardware.ur5e_cell import CLEAR_BEFORE_CAPTURE, UR5eCell
from flgd.hardware.ur_arm import PROTECTIVE_STOP_UNLOCK_DELAY
from tests.fakes.ur5e import MOTION, FakeRTDEFactory, NoCamera, grasp, make_ur5e, push, real_config

ROOT = Path(__file__).resolve().parents[1]



# --------------------------------------------------------------------------- tests

def test_grasp_plan_runs_as_checked_async_moves_and_measures_the_width(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    rg2.object_width_mm = 31.0
    checked = grasp(cfg)
    result = cell.execute(checked)
    assert result.completed, result.failure
    assert result.widths == [pytest.approx(0.031)]
    assert ctl.tcp_offset == [0.0, 0.0, 0.225, 0.0, 0.0, 0.0], "the TCP is the fingertip centre"
    moves = [s for s in checked.plan.steps if isinstance(s, MoveL)]
    sent = ctl.calls("moveL")
    assert len(sent) == len(moves)
    names = ctl.names()
    for step, (pose, speed, acc, asynchronous) in zip(moves, sent):
        np.testing.assert_allclose(pose, step.pose.as_ur_pose(), atol=1e-12)
        assert (speed, acc, asynchronous) == (step.speed, step.acceleration, True)
    # The controller's own limits are consulted before every single move, for that very pose.
    i_moves = [i for i, n in enumerate(names) if n == "moveL"]
    for i in i_moves:
        j = max(k for k in range(i) if names[k] == "isPoseWithinSafetyLimits")
        assert "moveL" not in names[j + 1:i]
        np.testing.assert_allclose(ctl.log[j][3][0], ctl.log[i][3][0])
    grips = [c for c in rg2.calls if c[0] == "rg_grip"]
    assert [g[2] for g in grips] == [pytest.approx(85.0), pytest.approx(0.0)]
    np.testing.assert_allclose(ctl.tcp[:3], cfg.robot.home.position, atol=1e-9)


def test_the_width_is_read_once_the_fingers_stop_so_a_block_slipping_out_at_home_is_a_failure(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    rg2.object_width_mm = 31.0
    rg2.slip_mm = [31.0, 22.0, 9.0, 0.0]  # the block slides out as the arm arrives home
    t0 = ctl.clock()
    result = cell.execute(grasp(cell.config))
    assert result.completed, result.failure
    assert result.widths == [0.0]
    assert grasp_reward(result.widths[0], cell.config.gripper) == 0.0
    # a steady width is read twice and that is all: one settle interval
    rg2.slip_mm = []
    rg2.object_width_mm = 31.0
    reads = rg2.names().count("rg_get_width")
    result = cell.execute(grasp(cell.config))
    assert result.widths == [pytest.approx(0.031)]
    assert rg2.names().count("rg_get_width") - reads == 2
    assert ctl.clock() > t0


def test_a_release_lets_the_arm_leave_while_the_fingers_open_and_the_next_grasp_descends_only_once_open(ctl, rg2):
    """gripper.release_gap on the real cell: the place plan ends while the RG2 still opens, the next grasp's
    approach runs meanwhile, and its descent starts only after the fingers have stopped."""
    import time

    from flgd.plans import plan_release

    rg2.move_time = 0.4
    cell = make_ur5e(ctl, rg2, real_config(xmlrpc_port=rg2.port, release_gap=0.01))
    busy_at: list[tuple[int, bool]] = []   # (move index, RG2 busy when the move was sent)
    record = ctl.record

    def watching(iface, method, *args):
        if method == "moveL":
            busy_at.append((ctl.moves, time.monotonic() < rg2._busy_until))
        record(iface, method, *args)

    ctl.record = watching
    rg2.object_width_mm = 31.0
    assert cell.execute(grasp(cell.config)).completed
    released = cell.execute(check_plan(plan_release(True, cell.config, home=False), cell.config))
    assert released.completed and released.widths == [pytest.approx(0.031)]
    assert time.monotonic() < rg2._busy_until, "the place plan ended before the fingers were open"
    rg2.object_width_mm = None
    busy_at.clear()
    plan = grasp(cell.config)
    moves = [s.label for s in plan.plan.steps if isinstance(s, MoveL)]
    assert cell.execute(plan).completed
    sent = dict(zip(moves, (busy for _, busy in busy_at)))
    assert sent["approach"], "the approach ran while the release's opening went on"
    assert not sent["descend"], "the descent started with the fingers still opening"


def test_a_preshape_sets_the_opening_while_the_arm_travels_and_the_descent_waits_until_it_stands(ctl, rg2):
    """gripper.preshape_margin on the real cell: after a release that opened only its gap, the grasp's first
    step narrows nothing held while the approach runs, and its descent starts with the fingers stopped there."""
    import time

    from flgd.plans import plan_grasp, plan_release

    rg2.move_time = 0.4
    cell = make_ur5e(ctl, rg2, real_config(xmlrpc_port=rg2.port, release_gap=0.01, preshape_margin=0.01))
    cfg = cell.config
    busy_at: list[bool] = []   # RG2 busy when each move was sent
    record = ctl.record

    def watching(iface, method, *args):
        if method == "moveL":
            busy_at.append(time.monotonic() < rg2._busy_until)
        record(iface, method, *args)

    ctl.record = watching
    rg2.object_width_mm = 31.0
    held = cell.execute(grasp(cfg))
    assert held.completed
    released = cell.execute(check_plan(plan_release(True, cfg, home=False, width=held.widths[-1]), cfg))
    assert released.completed and time.monotonic() >= rg2._busy_until, "the release waits for its gap"
    rg2.object_width_mm = None
    busy_at.clear()
    plan = check_plan(plan_grasp(0.50, 0.05, 0.04, 0.3, cfg, opening=0.06), cfg)
    moves = [s.label for s in plan.plan.steps if isinstance(s, MoveL)]
    grips = len([c for c in rg2.calls if c[0] == "rg_grip"])
    assert cell.execute(plan).completed
    sent = dict(zip(moves, busy_at))
    assert sent["approach"], "the approach ran while the fingers moved to the opening"
    assert not sent["descend"], "the descent started with the fingers still moving"
    widths = [c[2] for c in rg2.calls if c[0] == "rg_grip"]
    assert widths[grips - 1] == pytest.approx(41.0)   # the release: 31 mm held, its 10 mm gap
    # the pre-shape, then the close: the wait at the approach pose sends nothing (the fingers stand at 60 mm)
    assert widths[grips:] == [pytest.approx(60.0), pytest.approx(0.0)]


def test_a_plan_outside_the_envelope_never_reaches_the_robot(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    n = len(ctl.log)
    outside = ToolPose.top_down(0.50, 0.0, cfg.workspace.table_z - 0.05, 0.0)   # below the table
    too_fast = ToolPose.top_down(0.50, 0.0, 0.20, 0.0)
    for plan in (Plan("push", (MoveL(outside, 0.1, 0.5),)),
                 Plan("push", (MoveL(too_fast, cfg.safety.max_speed * 3, 0.5),)),
                 Plan("grasp", (GripperCommand(0.085, 400.0), MeasureWidth()))):
        with pytest.raises(PlanRefused):
            check_plan(plan, cfg)
        with pytest.raises(PlanRefused):   # a hand-made "checked" plan is re-verified by the cell
            cell.execute(CheckedPlan(plan, id(cfg)))
    assert ctl.log[n:] == [], "nothing at all was sent for a refused plan"
    assert not any(c[0] == "rg_grip" for c in rg2.calls)


def test_a_pose_the_controller_refuses_is_not_sent_and_is_not_a_fault(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    checked = push(cell.config)
    bad = checked.plan.poses[1].as_ur_pose()  # the descent
    ctl.unreachable = lambda pose: np.allclose(pose, bad)
    result = cell.execute(checked)
    assert not result.completed and "step 2 (descend)" in result.failure and "safety limits" in result.failure
    assert len(ctl.calls("moveL")) == 1, "only the approach went out; nothing after the refused pose"
    assert not any(np.allclose(p[0], bad) for p in ctl.calls("moveL"))
    ctl.unreachable = lambda pose: False
    assert cell.execute(push(cell.config)).completed


def test_a_false_return_latches_a_fault_that_stops_all_motion(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.fail_next["moveL"] = 1
    with pytest.raises(CellFault, match=r"moveL .* returned False"):
        cell.execute(grasp(cell.config))
    n = len(ctl.log)
    grips = len(rg2.calls)
    for plan in (grasp(cell.config), push(cell.config), check_plan(plan_home(cell.config), cell.config)):
        with pytest.raises(CellFault, match="in FAULT .*recovery"):
            cell.execute(plan)
    assert not MOTION & set(ctl.names(n)), "no motion command after a fault"
    assert len(rg2.calls) == grips, "nor a gripper command"


def test_protective_stop_mid_move_then_recovery_in_documented_order(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.at(2, 0.5, ctl.protective_stop)         # halfway through the descent
    with pytest.raises(CellFault, match="protective stop during move 'descend'"):
        cell.execute(grasp(cell.config))
    stopped_at = ctl.protective_at
    n = len(ctl.log)
    with pytest.raises(CellFault):
        cell.execute(push(cell.config))
    assert not MOTION & set(ctl.names(n))

    n = len(ctl.log)
    cell.recover()
    seq = [m for m in ctl.names(n) if m in {"isEmergencyStopped", "unlockProtectiveStop", "closeSafetyPopup",
                                             "getSafetyMode", "reuploadScript", "setTcp", "moveL", "rg_grip"}]
    first = {m: seq.index(m) for m in ("isEmergencyStopped", "unlockProtectiveStop", "closeSafetyPopup",
                                       "reuploadScript", "setTcp", "moveL")}
    assert first["isEmergencyStopped"] < first["unlockProtectiveStop"] < first["closeSafetyPopup"] \
        < first["reuploadScript"] < first["setTcp"] < first["moveL"]
    # NORMAL safety mode is confirmed after closing the popup and before the script comes back.
    assert "getSafetyMode" in seq[first["closeSafetyPopup"]:first["reuploadScript"]]
    unlock_time = next(t for t, _, m, _ in ctl.log[n:] if m == "unlockProtectiveStop")
    assert unlock_time - stopped_at >= PROTECTIVE_STOP_UNLOCK_DELAY
    assert len(ctl.calls("unlockProtectiveStop")) == 1, "unlocked once, after waiting, not retried early"
    assert not ctl.popup and ctl.program_running
    home = ctl.calls("moveL", n)
    assert len(home) == 1
    np.testing.assert_allclose(home[0][0][:3], cell.config.robot.home.position)
    assert cell.execute(grasp(cell.config)).completed


def test_emergency_stop_refuses_recovery_until_released_and_powered(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.at(1, 0.3, ctl.emergency_stop)
    with pytest.raises(CellFault, match="emergency stop engaged during move 'approach'"):
        cell.execute(push(cell.config))
    n = len(ctl.log)
    with pytest.raises(CellFault, match="emergency stop engaged.*recovery refused"):
        cell.recover()
    assert not MOTION & set(ctl.names(n)) and "closeSafetyPopup" not in ctl.names(n)
    ctl.release_emergency_stop()
    with pytest.raises(CellFault, match="robot mode POWER_OFF"):
        cell.recover()
    assert "moveL" not in ctl.names(n)
    ctl.power_on()
    cell.recover()
    assert cell.execute(push(cell.config)).completed


def test_lost_connection_is_a_fault_and_recovery_reconnects(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.at(3, 0.4, ctl.lose_network)
    with pytest.raises(CellFault, match="lost the RTDE receive connection during move 'push'"):
        cell.execute(push(cell.config))
    n = len(ctl.log)
    with pytest.raises(CellFault, match="cannot open the RTDE receive interface"):
        cell.recover()
    assert not MOTION & set(ctl.names(n))
    ctl.network_up = True
    n = len(ctl.log)
    cell.recover()
    names = ctl.names(n)
    assert "reconnect" not in names  # fresh interfaces, not ur_rtde's reconnect (module docstring of ur_arm)
    assert names.index("RTDEReceiveInterface") < names.index("RTDEControlInterface") < names.index("moveL")
    assert cell.execute(push(cell.config)).completed


def test_a_dead_control_script_is_a_fault_and_is_reuploaded(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.at(1, 1.0, ctl.kill_script)  # the script dies right as the first move ends
    with pytest.raises(CellFault, match="control script is not running"):
        cell.execute(grasp(cell.config))
    n = len(ctl.log)
    ctl.fail_next["reuploadScript"] = 1
    with pytest.raises(CellFault, match="reuploadScript returned False"):
        cell.recover()
    assert "moveL" not in ctl.names(n)
    cell.recover()
    assert ctl.program_running and cell.execute(grasp(cell.config)).completed


def test_stop_motion_from_another_thread_halts_the_move_promptly(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.real_sleep = 0.0005                      # let the other thread run while the fake arm moves
    ctl.tcp[:3] = (0.40, 0.30, 0.30)             # far from the grasp so the first move takes a while
    result = {}
    worker = threading.Thread(target=lambda: result.setdefault("r", cell.execute(grasp(cell.config))))
    worker.start()
    assert ctl.moving.wait(10), "the arm started moving"
    cell.stop_motion()                           # what the daemon's SIGTERM handler calls
    worker.join(10)
    assert not worker.is_alive()
    r = result["r"]
    assert not r.completed and "stopped on request" in r.failure
    names = ctl.names()
    assert "stopL" in names and names.count("moveL") == 1, "stopL sent; no move after it"
    assert names.index("stopL") > names.index("moveL")
    # The stop is latched: the next plan sends nothing until the owner clears it on purpose.
    n = len(ctl.log)
    again = cell.execute(push(cell.config))
    assert not again.completed and "stopped on request" in again.failure
    assert "moveL" not in ctl.names(n) and cell.fault is None, "a stop is not a fault, and nothing moved"
    cell.clear_stop()
    assert cell.execute(push(cell.config)).completed, "after a deliberate clear the next plan runs"


def test_a_stop_request_that_lands_between_two_looks_at_the_arm_is_a_stop_not_a_fault(ctl, rg2):
    """The daemon's stop (SIGTERM, the end of a bench) may come after the move's poll looked for a stop request and
    before it asks whether the arm still moves: the arm then stands short of its target because it was stopped."""
    cell = make_ur5e(ctl, rg2)
    ctl.tcp[:3] = (0.40, 0.30, 0.30)
    control = cell.arm.control
    progress = control.getAsyncOperationProgressEx
    polls = {"n": 0}

    def stopped_in_between():
        polls["n"] += 1
        if polls["n"] == 5:
            cell.stop_motion()
        return progress()

    control.getAsyncOperationProgressEx = stopped_in_between
    result = cell.execute(grasp(cell.config))
    assert polls["n"] >= 5
    assert not result.completed and "stopped on request" in result.failure
    assert cell.fault is None, "a stop is not a fault"


def test_a_controller_slower_than_the_wall_clock_is_judged_by_its_own_clock(ctl, rg2):
    """An emulator on a busy PC runs at a fifth of real time: a 0.6 m move that takes it 3 s of its own time takes
    15 s of the wall clock, beyond the 11.3 s the move is allowed; it is timed on the controller's clock and
    completes."""
    cell = make_ur5e(ctl, rg2)
    arm = cell.arm
    ctl.tcp[:3] = (0.40, 0.30, 0.30)
    ctl.rate = 0.2
    start_wall = ctl.now
    arm.move_linear([0.40, -0.30, 0.30, np.pi, 0.0, 0.0], 0.2, 1.2, "long")
    assert ctl.now - start_wall > 14.0, "the move outlasted its limit on the wall clock"
    assert cell.fault is None


def test_a_controller_clock_that_cannot_be_read_mid_move_halts_the_arm_and_latches(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    ctl.tcp[:3] = (0.40, 0.30, 0.30)
    ctl.at(1, 0.3, lambda: ctl.fail_next.update(getTimestamp=1))
    with pytest.raises(CellFault, match="cannot read the controller's clock"):
        cell.arm.move_linear([0.40, -0.30, 0.30, np.pi, 0.0, 0.0], 0.2, 1.2, "blind")
    assert "stopL" in ctl.names() and cell.fault is not None and ctl.moving.is_set() is False


def test_a_plans_duration_is_its_time_on_the_controllers_clock(ctl, rg2):
    """A cycle time a user plans with is the arm's, not that of a PC which emulates the arm more slowly."""
    cell = make_ur5e(ctl, rg2)
    ctl.rate = 0.5
    wall, controller = ctl.now, ctl.controller_now
    result = cell.execute(grasp(cell.config))
    assert result.completed
    assert result.duration == pytest.approx(ctl.controller_now - controller)
    assert result.duration == pytest.approx(0.5 * (ctl.now - wall), rel=0.05)
    assert 0.0 < result.gripper_time < 0.5 * result.duration, "the width readings' settling, on the same clock"


def test_a_controller_whose_clock_stops_is_a_fault_within_a_bounded_wall_time(ctl, rg2):
    """A state stream that keeps answering but no longer advances (a frozen controller link) cannot hold a move
    for ever: after five times the move's limit on the wall clock the arm is halted and the fault latched."""
    cell = make_ur5e(ctl, rg2)
    arm = cell.arm
    ctl.tcp[:3] = (0.40, 0.30, 0.30)
    ctl.rate = 0.0
    start_wall = ctl.now
    with pytest.raises(CellFault, match="clock advanced 0.0 s in 56.[67] s; its state stream has stalled"):
        arm.move_linear([0.40, -0.30, 0.30, np.pi, 0.0, 0.0], 0.2, 1.2, "frozen")
    assert 5 * 11.3 < ctl.now - start_wall < 5 * 11.4, "five times the 11.3 s limit"
    assert "stopL" in ctl.names() and cell.fault is not None


def test_starting_while_protective_stopped_reports_and_recovers(ctl, rg2):
    ctl.protective_stop()
    cell = make_ur5e(ctl, rg2)
    assert "protective stop" in cell.fault
    assert "RTDEControlInterface" not in ctl.names(), "the control script is not uploaded into a stopped arm"
    with pytest.raises(CellFault, match="protective stop"):
        cell.execute(push(cell.config))
    cell.recover()
    names = ctl.names()
    assert names.index("unlockProtectiveStop") < names.index("RTDEControlInterface") < names.index("moveL")
    assert cell.fault is None


def test_gripper_failure_latches_the_fault_too(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    rg2.fault = "tool not connected"
    with pytest.raises(CellFault, match="step 1 \\(open\\).*tool not connected"):
        cell.execute(grasp(cell.config))
    rg2.fault = None
    n = len(ctl.log)
    with pytest.raises(CellFault, match="in FAULT"):
        cell.execute(push(cell.config))
    assert "moveL" not in ctl.names(n)


def test_tool_digital_output_gripper(ctl, rg2):
    cfg = real_config(driver="tool_digital_output", digital_output=1)
    with pytest.raises(CellFault, match="cannot measure the finger width"):
        UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), camera_factory=lambda c: NoCamera(),
                 clock=ctl.clock, sleep=ctl.sleep)
    cell = UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), camera_factory=lambda c: NoCamera(),
                    clock=ctl.clock, sleep=ctl.sleep, require_width=False)
    assert cell.execute(push(cfg)).completed
    assert ctl.calls("setToolDigitalOut") == [(1, True)]
    ctl.fail_next["setToolDigitalOut"] = 1
    with pytest.raises(CellFault, match=r"setToolDigitalOut\(1, True\) returned False"):
        cell.execute(push(cfg))
    with pytest.raises(CellFault):
        cell.gripper_width()


def test_registered_as_the_ur5e_backend_and_refuses_an_empty_host():
    cfg = load_config(ROOT / "cell_config" / "ur5e-d415.yaml")
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, host=""))
    with pytest.raises(CellFault, match="robot.host is empty"):
        make_cell(cfg)


def _descend_step(checked: CheckedPlan) -> MoveL:
    return next(s for s in checked.plan.steps if isinstance(s, MoveL) and s.label == "descend")


def test_guarded_descent_stops_at_contact_and_the_grasp_goes_on_from_there(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    assert cfg.robot.descent_contact_force > 0, "the shipped real-cell config guards grasp descents"
    checked = grasp(cfg)
    descend = _descend_step(checked)
    assert descend.stop_on_contact == cfg.robot.descent_contact_force
    # a neighbour's top 2 cm above the planned fingertip height: the descent must stop on it
    surface = descend.pose.position[2] + 0.02
    ctl.surface_z = surface
    since = len(ctl.log)
    result = cell.execute(checked)
    assert result.completed, result.failure
    names = ctl.names(since)
    moves = [i for i, n in enumerate(names) if n == "moveL"]
    stops = [i for i, n in enumerate(names) if n == "stopL"]
    assert len(stops) == 1 and moves[1] < stops[0] < moves[2], "one stopL, during the descent"
    # stopped just past first contact (within the force threshold's squeeze + one poll of travel)
    (at_stop,) = ctl.stop_positions
    assert surface - 0.003 < at_stop[2] <= surface
    np.testing.assert_allclose(at_stop[:2], descend.pose.position[:2], atol=1e-9)
    # reported: which move stopped, and how far short of its pose (the arm's own TCP reading)
    (stop,) = result.contact_stops
    assert stop.label == "descend"
    assert stop.short_by == pytest.approx(at_stop[2] - descend.pose.position[2], abs=1e-6)
    # the fingers closed there and the plan went on: lift to its absolute pose, home
    grips = [c for c in rg2.calls if c[0] == "rg_grip"]
    assert [g[2] for g in grips] == [pytest.approx(85.0), pytest.approx(0.0)]
    lift = ctl.calls("moveL", since)[2][0]
    step_lift = next(s for s in checked.plan.steps if isinstance(s, MoveL) and s.label == "lift")
    np.testing.assert_allclose(lift, step_lift.pose.as_ur_pose())
    np.testing.assert_allclose(ctl.tcp[:3], cfg.robot.home.position, atol=1e-9)


def test_guard_measures_the_change_of_force_not_the_sensor_bias(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    ctl.force_offset = np.array([0.0, -5.0, 3.0 * cfg.robot.descent_contact_force])  # a big, constant bias
    checked = grasp(cfg)
    surface = _descend_step(checked).pose.position[2] + 0.01
    ctl.surface_z = surface
    result = cell.execute(checked)
    assert result.completed, result.failure
    (at_stop,) = ctl.stop_positions  # no stop from the bias alone, one at the contact
    assert surface - 0.003 < at_stop[2] <= surface


def test_free_descent_reaches_the_planned_depth(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    checked = grasp(cell.config)
    reached = []
    ctl.at(2, 1.0, lambda: reached.append(ctl.tcp[2]))
    result = cell.execute(checked)
    assert result.completed, result.failure
    assert ctl.calls("stopL") == [] and result.contact_stops == []
    assert reached == [pytest.approx(_descend_step(checked).pose.position[2])]


@pytest.mark.parametrize("reply", [None, [float("nan")] * 6, [1.0, 2.0], "garbage"])
def test_an_unusable_force_reading_stops_the_arm_and_latches(ctl, rg2, reply):
    cell = make_ur5e(ctl, rg2)
    checked = grasp(cell.config)
    ctl.at(2, 0.3, lambda: setattr(ctl, "force_reply", reply))  # mid-descent
    with pytest.raises(CellFault, match="TCP force"):
        cell.execute(checked)
    assert cell.fault is not None
    assert ctl.calls("stopL"), "the descent was halted before the fault was raised"
    assert ctl._target is None
    since = len(ctl.log)
    with pytest.raises(CellFault):
        cell.execute(checked)
    assert "moveL" not in ctl.names(since), "no motion until recovery"


def test_reset_reopens_a_camera_whose_stream_died(ctl, rg2):
    """flgctl reset clears a camera fault: the cell's recovery closes the camera and opens it anew.

    The camera is librealsense's own software_device (tests.fakes.realsense), driven through the real
    D415Camera; its depth sensor stopping is a stream that died under the camera.
    """
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 cannot load here (libusb-1.0 missing?)")
    from flgd.hardware.camera import CameraFault
    from flgd.hardware.d415 import D415Camera
    from tests.fakes.realsense import SERIAL, registered_camera, sim_config, synthetic_frame

    frame = synthetic_frame(sim_config(), width=64, height=48)
    dev = registered_camera(frame)
    cfg = real_config(xmlrpc_port=rg2.port)
    cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, serial=SERIAL, frame_timeout=1.0))
    opened = []

    def open_camera(c):
        opened.append(D415Camera.from_device(c, dev.device, warmup_frames=2))
        return opened[-1]

    gripper = RG2XmlRpcDriver("127.0.0.1", rg2.port, timeout=2.0, poll_interval=0.002)
    with dev.streaming(frame.depth, frame.color):
        cell = UR5eCell(cfg, rtde_factory=FakeRTDEFactory(ctl), gripper=gripper, camera_factory=open_camera,
                        clock=ctl.clock, sleep=ctl.sleep)
        assert cell.capture().depth.shape == (48, 64)
        dev.depth_sensor.stop()  # the stream dies; only a new start brings it back
        with pytest.raises(CameraFault, match=r"^RealSense .*: no depth\+colour frame within 1\.0 s"):
            cell.capture()
    # still gone when the operator resets: a clear error, and the arm is not touched
    n = len(ctl.log)
    with pytest.raises(CellFault, match=r"recovery: the camera did not come back: .*no depth\+colour frame.*"
                                        r"USB cable.*then flgctl reset again"):
        cell.recover()
    assert "moveL" not in ctl.names(n)
    with pytest.raises(CellFault, match="camera is not open"):
        cell.capture()
    # back: the next reset reopens it (the failed attempt left the device free) and homes the arm
    with dev.streaming(frame.depth, frame.color):
        cell.recover()
        assert cell.capture().depth.shape == (48, 64)
    assert len(opened) == 2, "the first camera, and the one reopened by the successful reset"
    assert len(ctl.calls("moveL", n)) == 1
    cell.close()


def test_the_unlock_is_sent_5_0_s_plus_the_margin_after_the_protective_stop_not_sooner_and_not_much_later(ctl, rg2):
    """The controller refuses an unlock sooner than 5.0 s after the stop; the arm waits exactly that plus a
    0.2 s margin for clock differences (simulated time: the fake controller's clock)."""
    from flgd.hardware.ur_recovery import _UNLOCK_MARGIN, UNLOCK_WAIT_STEP

    assert PROTECTIVE_STOP_UNLOCK_DELAY == 5.0 and _UNLOCK_MARGIN == 0.2
    cell = make_ur5e(ctl, rg2)
    ctl.at(2, 0.5, ctl.protective_stop)
    with pytest.raises(CellFault, match="protective stop"):
        cell.execute(grasp(cell.config))
    stopped_at = ctl.protective_at
    n = len(ctl.log)
    cell.recover()
    unlocks = [t for t, _, m, _ in ctl.log[n:] if m == "unlockProtectiveStop"]
    assert len(unlocks) == 1, "one unlock, not a retry after a refused early one"
    waited = unlocks[0] - stopped_at
    assert 5.0 + 0.2 <= waited <= 5.0 + 0.2 + 2 * UNLOCK_WAIT_STEP, waited


def test_a_blended_grasp_sends_its_raise_and_home_as_one_path_for_the_installation_tcp(ctl, rg2):
    """ur_rtde runs a path in a freshly uploaded script, which starts with the pendant's TCP: the path's poses
    are sent for that TCP, and the cell's own TCP is set again once the path has ended."""
    ctl.installation_tcp = [0.0, 0.0, 0.10, 0.0, 0.0, 0.0]
    ctl.tcp_offset = list(ctl.installation_tcp)
    base = real_config(xmlrpc_port=rg2.port)
    cfg = dataclasses.replace(base, robot=dataclasses.replace(base.robot, raise_speed=0.2, blend_radius=0.02))
    cell = make_ur5e(ctl, rg2, cfg)
    rg2.object_width_mm = 31.0
    checked = grasp(cfg)
    result = cell.execute(checked)
    assert result.completed, result.failure
    paths = [c for c in ctl.calls("moveL") if c[0] and isinstance(c[0][0], list)]
    assert len(paths) == 1
    rows, asynchronous = paths[0]
    moves = {s.label: s for s in checked.plan.steps if isinstance(s, MoveL)}
    assert asynchronous is True and len(rows) == 2
    for row, label in zip(rows, ("raise", "home")):
        ours = moves[label].pose.as_ur_pose()
        # the tool points down: the pendant's TCP, nearer the flange than ours, lies that much higher
        lift = cfg.robot.tcp_offset[2] - 0.10
        assert row[:6] == pytest.approx([ours[0], ours[1], ours[2] + lift, *ours[3:]], abs=1e-6)
        assert row[6:8] == [pytest.approx(moves[label].speed), pytest.approx(moves[label].acceleration)]
    assert [row[8] for row in rows] == [pytest.approx(0.02), 0.0]
    assert ctl.tcp_offset == [0.0, 0.0, 0.225, 0.0, 0.0, 0.0], "the cell's TCP is set again after the path"
    assert result.widths == [pytest.approx(0.031)]


def test_a_path_whose_script_runs_another_tcp_is_halted_and_latched(ctl, rg2):
    """The pendant's TCP changed since it was read: the path's poses would be off by the difference."""
    base = real_config(xmlrpc_port=rg2.port)
    cfg = dataclasses.replace(base, robot=dataclasses.replace(base.robot, raise_speed=0.2, blend_radius=0.02))
    cell = make_ur5e(ctl, rg2, cfg)
    cell.execute(check_plan(plan_home(cfg), cfg))
    ctl.installation_tcp = [0.0, 0.0, 0.15, 0.0, 0.0, 0.0]   # changed on the pendant after the arm connected
    with pytest.raises(CellFault, match="not the installation's"):
        cell.execute(grasp(cfg))
    assert cell.arm.fault and ctl.calls("stopL")


def test_with_the_installation_tcp_unknown_a_path_runs_as_single_moves(ctl, rg2):
    base = real_config(xmlrpc_port=rg2.port)
    cfg = dataclasses.replace(base, robot=dataclasses.replace(base.robot, raise_speed=0.2, blend_radius=0.02))
    cell = make_ur5e(ctl, rg2, cfg)
    rg2.object_width_mm = 31.0
    cell.arm.installation_tcp = None   # could not be read when the script started
    result = cell.execute(grasp(cfg))
    assert result.completed, result.failure
    assert not [c for c in ctl.calls("moveL") if c[0] and isinstance(c[0][0], list)]


def test_a_push_that_comes_down_on_something_backs_straight_up_and_goes_home_without_pushing(ctl, rg2):
    cell = make_ur5e(ctl, rg2)
    cfg = cell.config
    checked = push(cfg)
    steps = checked.plan.steps
    descend = next(s for s in steps if isinstance(s, MoveL) and s.label == "descend")
    approach = next(s for s in steps if isinstance(s, MoveL) and s.label == "approach")
    assert descend.stop_on_contact == cfg.robot.descent_contact_force and descend.abort_on_contact
    ctl.surface_z = descend.pose.position[2] + 0.03   # a part the heightmap did not show, 3 cm up
    since = len(ctl.log)
    result = cell.execute(checked)
    assert result.completed, result.failure
    assert [s.label for s in result.contact_stops] == ["descend"]
    moves = ctl.calls("moveL", since)
    # approach, the stopped descent, straight back up to the approach pose, home: no push, no retreat
    assert len(moves) == 4
    np.testing.assert_allclose(moves[2][0], approach.pose.as_ur_pose())
    np.testing.assert_allclose(ctl.tcp[:3], cfg.robot.home.position, atol=1e-9)
    assert not ctl.calls("triggerProtectiveStop", since)


class _CameraWatchingTheArm:
    """A camera that notes where the fake arm's TCP was at each capture and returns a blank frame."""

    def __init__(self, ctl, broken: bool = False):
        self.ctl, self.broken, self.tool_at = ctl, broken, []

    def capture(self) -> Frame:
        self.tool_at.append(tuple(float(v) for v in self.ctl.tcp[:3]))
        if self.broken:
            raise CellFault("the camera stopped delivering frames")
        return Frame(color=np.zeros((4, 4, 3), np.uint8), depth=np.zeros((4, 4), np.uint16), depth_scale=0.001,
                     intrinsics=np.eye(3), camera_pose=np.eye(4))

    def close(self) -> None:
        pass


def _watched_cell(ctl, rg2, camera, cfg=None, sleep=None) -> UR5eCell:
    return UR5eCell(cfg or real_config(xmlrpc_port=rg2.port), rtde_factory=FakeRTDEFactory(ctl),
                    gripper=RG2XmlRpcDriver("127.0.0.1", rg2.port, timeout=2.0, poll_interval=0.002),
                    camera_factory=lambda c: camera, clock=ctl.clock, sleep=sleep or ctl.sleep)


def test_a_grasp_takes_its_picture_on_the_way_home_once_the_tool_is_out_of_view(ctl, rg2):
    camera = _CameraWatchingTheArm(ctl)
    cell = _watched_cell(ctl, rg2, camera)
    cfg = cell.config
    rg2.object_width_mm = 31.0
    frames: list = []
    result = cell.execute_and_capture(grasp(cfg), lambda frame, at: frames.append((frame, at)))
    assert result.completed, result.failure
    assert len(frames) == 1 and len(camera.tool_at) == 1   # one picture, taken during the plan
    frame, at = frames[0]
    assert tool_in_view(frame.tool_position, cfg) == ""   # where the tool was as the capture began: out of view
    assert tool_in_view(camera.tool_at[0], cfg) == ""
    assert in_view_on_the_way(frame.tool_position, cfg) == ""   # clear of the wider model a held object needs
    assert math.dist(frame.tool_position, cfg.robot.home.position) > 0.005   # short of home: on the way
    assert 0.0 < at < result.duration
    assert cell.execute(grasp(cfg)).completed and len(camera.tool_at) == 1   # a plain execute takes none


def test_a_capture_on_the_way_that_fails_hands_nothing_over_and_the_plan_completes(ctl, rg2):
    camera = _CameraWatchingTheArm(ctl, broken=True)
    cell = _watched_cell(ctl, rg2, camera)
    rg2.object_width_mm = 31.0
    frames: list = []
    result = cell.execute_and_capture(grasp(cell.config), lambda frame, at: frames.append((frame, at)))
    assert result.completed, result.failure
    assert len(camera.tool_at) == 1 and frames == []


def test_the_capture_on_the_way_waits_until_a_held_object_has_been_out_of_view_for_a_streaming_camera_s_frame_age(
        ctl, rg2):
    """A D415 may deliver a frame exposed before the request: the capture starts only once the tool, with the reach
    of a long held object, has been out of view for ``CLEAR_BEFORE_CAPTURE`` on the controller's clock."""
    camera = _CameraWatchingTheArm(ctl)
    seen: list = []   # (controller time, TCP) after every tick of the fake controller

    def sleep(dt):
        ctl.sleep(dt)
        seen.append((ctl.controller_now, tuple(float(v) for v in ctl.tcp[:3])))

    cell = _watched_cell(ctl, rg2, camera, sleep=sleep)
    cfg = cell.config
    rg2.object_width_mm = 31.0
    captured_at: list = []
    honest = camera.capture
    camera.capture = lambda: (captured_at.append(ctl.controller_now), honest())[1]
    frames: list = []
    assert cell.execute_and_capture(grasp(cfg), lambda frame, at: frames.append(frame)).completed
    assert len(frames) == 1
    # in view as a held object up to 24 cm long would be (``in_view_on_the_way``), not just the 7 cm tool
    in_view = [t for t, tcp in seen if t <= captured_at[0] and in_view_on_the_way(tcp, cfg)]
    assert in_view and captured_at[0] - max(in_view) >= CLEAR_BEFORE_CAPTURE


def test_a_blended_path_home_takes_its_picture_on_the_way_with_the_fingertips_position(ctl, rg2):
    """The shipped real-cell config blends the raise into the move home (one path, whose script reports poses for the
    installation's TCP): the picture is taken on that path too, and its tool position is the arm's TCP."""
    camera = _CameraWatchingTheArm(ctl)
    base = real_config(xmlrpc_port=rg2.port)
    cfg = dataclasses.replace(base, robot=dataclasses.replace(base.robot, blend_radius=0.02, raise_speed=0.25))
    cell = _watched_cell(ctl, rg2, camera, cfg=cfg)
    rg2.object_width_mm = 31.0
    frames: list = []
    checked = grasp(cfg)
    assert cell.execute_and_capture(checked, lambda frame, at: frames.append(frame)).completed
    assert len(ctl.calls("moveL")) < len([s for s in checked.plan.steps if isinstance(s, MoveL)])   # a path ran
    assert len(frames) == 1
    lifted = cfg.workspace.table_z + cfg.robot.lift_height
    # the fingertips' height on the way from the lift to home (the flange is 0.225 m above them)
    assert lifted - 0.01 <= frames[0].tool_position[2] <= cfg.robot.home.position[2] + 0.01
    assert tool_in_view(frames[0].tool_position, cfg) == ""
