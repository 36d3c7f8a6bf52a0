"""VPG's evaluation metrics, computed from per-run action logs (Zeng et al. 2018, evaluate.py).

A *run* is one attempt to clear one scene.  Definitions:

* **failed action**: a grasp that held nothing, a move whose reward is 0 (it
  changed the scene less than the paper's mu/eta thresholds), or a plan the
  safety envelope refused (nothing happened).
* **completed run**: the workspace was cleared -- every object left it in the
  gripper (none is left, none was pushed off or dropped outside it) -- without
  more than ``FAILURE_LIMIT`` (10) consecutive failed actions.  The evaluator
  stops a run at the 11th consecutive failure.
* **completion rate**: completed runs / counted runs.  Runs aborted by the
  simulator (unstable physics, a cell fault) are not counted; they are
  reported separately.
* **grasp success rate**: successful grasps / grasp attempts, pooled over the
  counted runs.  ``grasp_success_completed`` is VPG's own printout: the mean
  of the per-run rates over completed runs.
* **action efficiency**: objects in the scene / actions, averaged over the
  completed runs (VPG: "objects / actions before completion"; a run that does
  not complete has no efficiency).
* **moves**: executed pushes and shifts, by kind; **actions** counts every
  decided action (executed or refused).
* **picks per action**: successful grasps / actions, pooled over the counted
  runs -- beside grasp success per grasp, since a run that spends 150 actions
  pushing can keep a good rate per grasp.
* **lost objects**: objects that left the workspace other than in the gripper;
  **dropped** counts those of them the gripper had lifted (a grip that gave way
  on the way out), the rest were pushed or knocked out.  Either makes a cleared
  table an incomplete run.
* **loops**: the longest failure streak (consecutive failed actions), the
  actions spent in streaks of at least ``LONG_STREAK`` (5), and the runs that
  ended because the cell declared itself **stuck** (``exploration.stuck_after``
  actions without a successful grasp, or nothing left to try): such a run is
  counted and not completed; in the daemon the simulated cell re-lays its scene.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

__all__ = ["FAILURE_LIMIT", "LONG_STREAK", "ABORTED_ENDS", "RUN_ENDS", "ActionEntry", "RunLog", "RunResult", "Summary",
           "longest_failure_streak", "actions_in_long_streaks", "run_result", "summarize"]

FAILURE_LIMIT = 10
LONG_STREAK = 5   # a failure streak this long is a loop worth counting
# why a run stopped
RUN_ENDS = ("cleared", "failures", "action-limit", "nothing-graspable", "stuck", "unstable", "fault")
ABORTED_ENDS = ("unstable", "fault")   # the simulator's fault, not the policy's: not counted
_KINDS = ("grasp", "push", "shift")


@dataclass(frozen=True)
class ActionEntry:
    """One decided action of a run."""

    kind: str                 # grasp, push or shift
    success: bool             # grasp: held an object; move: reward > 0; refused: False
    refused: bool = False     # the safety envelope refused the plan (counts as a failed action)

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ValueError(f"ActionEntry.kind: got {self.kind!r}, expected one of {_KINDS}")
        if self.refused and self.success:
            raise ValueError("ActionEntry: a refused action cannot be a success")


@dataclass(frozen=True)
class RunLog:
    """What happened in one run; the objects counts come from the simulator's ground truth."""

    scene: str
    run: int
    objects: int                          # objects in the workspace at the start
    actions: tuple[ActionEntry, ...]
    objects_left: int                     # still in the workspace at the end
    objects_grasped: int                  # carried out of the workspace by the gripper
    end: str                              # why the run stopped, one of RUN_ENDS
    seconds: float = 0.0
    note: str = ""
    objects_dropped: int = 0              # of the lost ones: lifted by the gripper, then dropped out

    def __post_init__(self) -> None:
        if self.end not in RUN_ENDS:
            raise ValueError(f"RunLog.end: got {self.end!r}, expected one of {RUN_ENDS}")
        if min(self.objects, self.objects_left, self.objects_grasped, self.objects_dropped) < 0:
            raise ValueError("RunLog: object counts must be >= 0")

    @property
    def objects_lost(self) -> int:
        """Objects that left the workspace without being grasped (pushed or dropped out)."""
        return max(0, self.objects - self.objects_grasped - self.objects_left)

    @property
    def dropped_lost(self) -> int:
        """Of ``objects_lost``, those dropped from the gripper (none in an aborted run, whose objects count as left)."""
        return min(self.objects_dropped, self.objects_lost)

    @property
    def aborted(self) -> bool:
        return self.end in ABORTED_ENDS


def longest_failure_streak(actions: Iterable[ActionEntry]) -> int:
    """The longest run of consecutive failed actions."""
    longest = streak = 0
    for a in actions:
        streak = 0 if a.success else streak + 1
        longest = max(longest, streak)
    return longest


def actions_in_long_streaks(actions: Iterable[ActionEntry], at_least: int = LONG_STREAK) -> int:
    """The failed actions that belong to streaks of at least ``at_least`` consecutive failures."""
    total = streak = 0
    for a in actions:
        if a.success:
            total += streak if streak >= at_least else 0
            streak = 0
        else:
            streak += 1
    return total + (streak if streak >= at_least else 0)


@dataclass(frozen=True)
class RunResult:
    completed: bool
    actions: int
    grasp_attempts: int          # executed grasps (refused grasps never reached an object)
    grasp_successes: int
    moves: dict[str, int]        # executed push / shift
    refused: int
    failure_streak: int
    grasp_success: float | None  # per run
    action_efficiency: float | None  # objects / actions, completed runs only
    streak_actions: int = 0      # failed actions in streaks of >= LONG_STREAK
    stuck: bool = False          # the cell declared itself stuck in this run


def run_result(run: RunLog, failure_limit: int = FAILURE_LIMIT) -> RunResult:
    """The metrics of one run (see the module doc)."""
    acts = run.actions
    executed = [a for a in acts if not a.refused]
    grasps = [a for a in executed if a.kind == "grasp"]
    successes = sum(1 for a in grasps if a.success)
    streak = longest_failure_streak(acts)
    completed = (not run.aborted and run.objects > 0 and run.objects_left == 0 and run.objects_lost == 0
                 and streak <= failure_limit)
    return RunResult(
        completed=completed,
        actions=len(acts),
        grasp_attempts=len(grasps),
        grasp_successes=successes,
        moves={k: sum(1 for a in executed if a.kind == k) for k in ("push", "shift")},
        refused=sum(1 for a in acts if a.refused),
        failure_streak=streak,
        grasp_success=(successes / len(grasps)) if grasps else None,
        action_efficiency=(run.objects / len(acts)) if completed and acts else None,
        streak_actions=actions_in_long_streaks(acts),
        stuck=run.end == "stuck",
    )


@dataclass(frozen=True)
class Summary:
    """Metrics over a set of runs (one scene, a scene set, or everything)."""

    runs: int                       # all runs, aborted ones included
    counted_runs: int               # runs the rates are computed over
    completed_runs: int
    completion: float | None
    grasp_attempts: int
    grasp_successes: int
    grasp_success: float | None             # pooled over counted runs
    grasp_success_completed: float | None   # VPG's: mean per-run rate over completed runs
    action_efficiency: float | None         # VPG's: mean objects/actions over completed runs
    actions: int
    mean_actions: float | None              # per counted run
    moves: dict[str, int]
    refused: int
    objects: int
    objects_grasped: int
    objects_lost: int
    ends: dict[str, int] = field(default_factory=dict)
    objects_dropped: int = 0                # of objects_lost: lifted by the gripper, then dropped out
    aborted: int = 0
    picks_per_action: float | None = None   # successful grasps / actions, pooled over counted runs
    longest_failure_streak: int = 0         # over the counted runs
    streak_actions: int = 0                 # failed actions in streaks of >= LONG_STREAK, summed
    stuck_runs: int = 0                     # runs that ended with the cell declaring itself stuck

    def as_dict(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.__dict__.items()}


def _mean(values: Sequence[float]) -> float | None:
    return statistics.fmean(values) if values else None


def summarize(runs: Sequence[RunLog], failure_limit: int = FAILURE_LIMIT) -> Summary:
    """Pool ``runs`` into the metrics of the module doc."""
    counted = [r for r in runs if not r.aborted]
    results = [run_result(r, failure_limit) for r in counted]
    done = [res for res in results if res.completed]
    attempts = sum(res.grasp_attempts for res in results)
    successes = sum(res.grasp_successes for res in results)
    ends: dict[str, int] = {}
    for r in runs:
        ends[r.end] = ends.get(r.end, 0) + 1
    return Summary(
        runs=len(runs),
        counted_runs=len(counted),
        completed_runs=len(done),
        completion=(len(done) / len(counted)) if counted else None,
        grasp_attempts=attempts,
        grasp_successes=successes,
        grasp_success=(successes / attempts) if attempts else None,
        grasp_success_completed=_mean([res.grasp_success for res in done if res.grasp_success is not None]),
        action_efficiency=_mean([res.action_efficiency for res in done if res.action_efficiency is not None]),
        actions=sum(res.actions for res in results),
        mean_actions=_mean([float(res.actions) for res in results]),
        moves={k: sum(res.moves[k] for res in results) for k in ("push", "shift")},
        refused=sum(res.refused for res in results),
        objects=sum(r.objects for r in counted),
        objects_grasped=sum(r.objects_grasped for r in counted),
        objects_lost=sum(r.objects_lost for r in counted),
        objects_dropped=sum(r.dropped_lost for r in counted),
        ends=ends,
        aborted=len(runs) - len(counted),
        picks_per_action=(successes / sum(res.actions for res in results)) if any(r.actions for r in results)
        else None,
        longest_failure_streak=max((res.failure_streak for res in results), default=0),
        streak_actions=sum(res.streak_actions for res in results),
        stuck_runs=sum(1 for res in results if res.stuck),
    )
