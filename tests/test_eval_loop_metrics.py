"""The evaluation's loop metrics (flgd/evaluation/metrics.py) on runs built by hand: the longest failure streak,
the failed actions in streaks of at least five, the runs that ended stuck, and picks per action."""

from __future__ import annotations

from flgd.evaluation.metrics import (LONG_STREAK, ActionEntry, RunLog, actions_in_long_streaks,
                                     longest_failure_streak, run_result, summarize)

HIT = ActionEntry("grasp", True)
MISS = ActionEntry("grasp", False)
PUSH = ActionEntry("push", True)
NO_CHANGE = ActionEntry("push", False)
REFUSED = ActionEntry("grasp", False, refused=True)


def _run(pattern: str, end: str = "cleared", objects: int = 3, grasped: int | None = None, run: int = 0) -> RunLog:
    """A run from a pattern: H hit, M miss, P successful push, N push that changed nothing, R refused grasp."""
    table = {"H": HIT, "M": MISS, "P": PUSH, "N": NO_CHANGE, "R": REFUSED}
    actions = tuple(table[c] for c in pattern)
    grasped = pattern.count("H") if grasped is None else grasped
    return RunLog("s", run, objects, actions, objects - grasped, grasped, end)


def test_the_longest_failure_streak_counts_refused_and_unchanged_moves_and_ends_at_any_success():
    assert longest_failure_streak(_run("MMHMNRMPMM").actions) == 4  # M N R M, then a successful push
    assert longest_failure_streak(_run("HHH").actions) == 0
    assert longest_failure_streak(_run("HMMMMMMM").actions) == 7  # a streak running to the end counts


def test_actions_in_long_streaks_count_only_streaks_of_five_or_more_the_last_one_included():
    assert LONG_STREAK == 5
    assert actions_in_long_streaks(_run("MMMMH").actions) == 0            # four: not a loop
    assert actions_in_long_streaks(_run("MMMMMH").actions) == 5           # exactly five
    assert actions_in_long_streaks(_run("MMMMMMHMMMHMMMMM").actions) == 6 + 5  # 6, 3 (not), 5 at the end
    assert actions_in_long_streaks(_run("MMMH").actions, at_least=3) == 3


def test_a_run_result_carries_its_streaks_and_whether_it_ended_stuck():
    res = run_result(_run("MMMMMMHHH", end="stuck", objects=5))
    assert res.failure_streak == 6 and res.streak_actions == 6 and res.stuck
    assert not res.completed  # objects were left
    calm = run_result(_run("HMHMHH", objects=4))
    assert calm.failure_streak == 1 and calm.streak_actions == 0 and not calm.stuck


def test_the_summary_pools_picks_per_action_streaks_and_stuck_runs_over_counted_runs_only():
    runs = [
        _run("HMHH", objects=3, run=0),                                 # 3 picks, 4 actions
        _run("MMMMMMMHH", end="stuck", objects=4, run=1),               # 2 picks, 9 actions, streak 7
        _run("PMMMMMH", objects=2, grasped=1, run=2),                   # 1 pick, 7 actions, streak 5
        _run("MMMMMMMMMMMM", end="unstable", objects=3, grasped=0, run=3),  # aborted: not counted at all
    ]
    s = summarize(runs)
    assert s.counted_runs == 3 and s.aborted == 1
    assert s.picks_per_action == (3 + 2 + 1) / (4 + 9 + 7)
    assert s.longest_failure_streak == 7  # the aborted run's 12 is not the policy's
    assert s.streak_actions == 7 + 5
    assert s.stuck_runs == 1
    assert s.ends == {"cleared": 2, "stuck": 1, "unstable": 1}


def test_a_summary_without_actions_has_no_picks_per_action_and_no_streaks():
    s = summarize([_run("", objects=0)])
    assert s.picks_per_action is None and s.longest_failure_streak == 0 and s.streak_actions == 0
    assert s.stuck_runs == 0
