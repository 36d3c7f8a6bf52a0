"""VPG's evaluation metrics on hand-made action logs (flgd.evaluation.metrics)."""

from __future__ import annotations

import dataclasses
import re

import pytest

from flgd.evaluation.metrics import (FAILURE_LIMIT, ActionEntry, RunLog, longest_failure_streak, run_result,
                                     summarize)

G_OK, G_MISS = ActionEntry("grasp", True), ActionEntry("grasp", False)
PUSH_OK, PUSH_NOP = ActionEntry("push", True), ActionEntry("push", False)
SHIFT_OK = ActionEntry("shift", True)
REFUSED = ActionEntry("grasp", False, refused=True)


def run(actions, objects=3, left=0, grasped=None, end="cleared", scene="s", index=0) -> RunLog:
    grasped = sum(1 for a in actions if a.kind == "grasp" and a.success) if grasped is None else grasped
    return RunLog(scene=scene, run=index, objects=objects, actions=tuple(actions), objects_left=left,
                  objects_grasped=grasped, end=end)


def test_failure_limit_is_vpgs_ten():
    assert FAILURE_LIMIT == 10


def test_exactly_ten_consecutive_failures_still_completes():
    acts = [G_OK] + [G_MISS] * 10 + [G_OK, G_OK]
    res = run_result(run(acts))
    assert res.failure_streak == 10
    assert res.completed


def test_eleven_consecutive_failures_do_not_complete_even_if_cleared_later():
    acts = [G_OK] + [G_MISS] * 7 + [PUSH_NOP, REFUSED] + [G_MISS] * 2 + [G_OK, G_OK]  # 11 failures in a row
    res = run_result(run(acts))
    assert res.failure_streak == 11
    assert not res.completed


def test_streak_is_reset_by_any_success_move_or_grasp():
    acts = [G_MISS] * 9 + [PUSH_OK] + [G_MISS] * 9 + [SHIFT_OK] + [G_MISS] * 10 + [G_OK] * 3
    assert longest_failure_streak(acts) == 10
    assert run_result(run(acts)).completed


def test_objects_left_or_pushed_out_mean_not_completed():
    assert not run_result(run([G_OK, G_OK], objects=3, left=1)).completed
    lost = run([G_OK, G_OK, PUSH_OK], objects=3, left=0)   # third object pushed out of the workspace
    assert lost.objects_lost == 1
    assert not run_result(lost).completed


def test_grasp_success_is_successes_over_attempts_refused_grasps_are_not_attempts():
    acts = [G_OK, G_MISS, G_MISS, REFUSED, G_OK, PUSH_OK, G_OK]
    res = run_result(run(acts))
    assert (res.grasp_successes, res.grasp_attempts) == (3, 5)
    assert res.grasp_success == pytest.approx(3 / 5)
    assert res.refused == 1 and res.actions == 7


def test_action_efficiency_is_objects_over_all_actions_of_a_completed_run():
    acts = [G_OK, PUSH_OK, G_MISS, G_OK, G_OK, REFUSED]
    res = run_result(run(acts, objects=3))
    assert res.completed
    assert res.action_efficiency == pytest.approx(3 / 6)
    assert run_result(run([G_OK], objects=3, left=2)).action_efficiency is None  # not completed: none


def test_moves_are_counted_by_kind_executed_only():
    acts = [PUSH_OK, PUSH_NOP, SHIFT_OK, ActionEntry("shift", False, refused=True), G_OK]
    res = run_result(run(acts, objects=1))
    assert res.moves == {"push": 2, "shift": 1}


def test_summary_pools_grasps_and_averages_vpg_numbers_over_completed_runs():
    a = run([G_OK, G_MISS, G_OK, G_OK], objects=3, index=0)                   # completed, 3/4, eff 3/4
    b = run([G_OK, G_OK], objects=2, index=1)                                # completed, 2/2, eff 2/2
    c = run([G_MISS] * 11, objects=2, left=2, end="failures", index=2)       # failed, 0/11
    s = summarize([a, b, c])
    assert (s.runs, s.counted_runs, s.completed_runs) == (3, 3, 2)
    assert s.completion == pytest.approx(2 / 3)
    assert (s.grasp_successes, s.grasp_attempts) == (5, 17)
    assert s.grasp_success == pytest.approx(5 / 17)
    assert s.grasp_success_completed == pytest.approx((3 / 4 + 1.0) / 2)
    assert s.action_efficiency == pytest.approx((3 / 4 + 1.0) / 2)
    assert s.mean_actions == pytest.approx((4 + 2 + 11) / 3)
    assert s.ends == {"cleared": 2, "failures": 1}


def test_runs_aborted_by_the_simulator_are_reported_not_counted():
    good = run([G_OK], objects=1)
    unstable = run([G_MISS, G_MISS], objects=4, left=4, end="unstable")
    s = summarize([good, unstable])
    assert (s.runs, s.counted_runs, s.aborted) == (2, 1, 1)
    assert s.completion == 1.0 and s.grasp_attempts == 1
    assert s.ends == {"cleared": 1, "unstable": 1}


def test_empty_summary_has_no_rates():
    s = summarize([])
    assert s.completion is None and s.grasp_success is None and s.action_efficiency is None


def test_malformed_entries_are_refused():
    with pytest.raises(ValueError, match="kind"):
        ActionEntry("poke", True)
    with pytest.raises(ValueError, match="refused"):
        ActionEntry("grasp", True, refused=True)
    with pytest.raises(ValueError, match="end"):
        run([G_OK], end="bored")


def test_the_run_line_says_whether_a_cleared_run_completed_and_what_was_lost():
    from flgd.evaluation.report import run_line

    grasps = (ActionEntry("grasp", True), ActionEntry("push", True), ActionEntry("grasp", True))
    clean = RunLog(scene="pile", run=2, objects=2, actions=grasps, objects_left=0, objects_grasped=2, end="cleared",
                   seconds=3.04)
    assert run_line("pile", clean, 3) == ("pile run 2 of 3: cleared (completed), 3 actions, 2/2 grasps, 1 push, "
                                          "0 shift, 0/2 objects left (3.0 s)")
    pushed_off = dataclasses.replace(clean, objects=3)  # the table is clear, but one object went over the edge
    line = run_line("pile", pushed_off)
    assert line.startswith("pile run 2: cleared (not completed, 1 lost), ") and "0/3 objects left" in line
    gave_up = dataclasses.replace(clean, end="unstable", objects_left=2, objects_grasped=1)
    line = run_line("pile", gave_up)
    assert "unstable (not counted in the rates)" in line and "objects left" not in line


def test_objects_dropped_from_the_gripper_are_told_apart_from_those_pushed_out():
    """Of the lost objects, the run line, the run's JSON row and the summary say how many the gripper had lifted."""
    from flgd.evaluation.metrics import summarize
    from flgd.evaluation.report import _run_row, format_table, run_line

    grasps = (ActionEntry("grasp", True), ActionEntry("grasp", False), ActionEntry("grasp", True))
    dropped = RunLog(scene="pile", run=1, objects=4, actions=grasps, objects_left=0, objects_grasped=2,
                     end="cleared", objects_dropped=1)   # one fell out of the fingers, one was knocked out
    line = run_line("pile", dropped)
    assert line.startswith("pile run 1: cleared (not completed, 2 lost (1 dropped from the gripper)), ")
    row = _run_row(dropped, FAILURE_LIMIT)
    assert row["objects_lost"] == 2 and row["objects_dropped"] == 1
    pushed = dataclasses.replace(dropped, run=2, objects=3, objects_dropped=0)
    s = summarize([dropped, pushed])
    assert s.objects_lost == 3 and s.objects_dropped == 1
    from flgd.evaluation.report import build_report
    from flgd.evaluation.scene_sets import SceneSpec

    report = build_report([(SceneSpec(name="pile"), [dropped, pushed])], policy={"path": "p"}, config="c",
                          options={"runs": 2, "seed": 0}, seconds=1.0)
    assert report["overall"]["objects_dropped"] == 1 and report["scenes"][0]["run_logs"][0]["objects_dropped"] == 1
    table = format_table(report).splitlines()
    header, overall = (re.split(r"\s{2,}", table[i].strip()) for i in (1, -2))
    assert header[-2:] == ["dropped", "ends"] and overall[0] == "OVERALL"
    assert overall[header.index("lost")] == "3" and overall[header.index("dropped")] == "1"
    # an aborted run's objects all count as left: a drop the simulator saw before it gave up is no lost object
    assert dataclasses.replace(dropped, end="unstable", objects_left=4, objects_grasped=0).dropped_lost == 0
    with pytest.raises(ValueError, match="counts"):
        dataclasses.replace(dropped, objects_dropped=-1)
