"""The numbers of ``flgctl stats``, computed from the action log so they always agree with it.

Definitions (VPG's where they exist):
  * cycles: rows of the action log (one per decided action, whatever its outcome).
  * grasp attempts / successes: executed grasps / those that held an object.
  * rolling grasp success: successes over the last 50 and last 200 grasp attempts.
  * picks per hour: grasp successes per hour of cycle time: the summed cycles, each
    the controller's own work (wall clock) plus its plans on the cell's clock (the
    controller's, or simulated time), so pauses and idle time do not count and an
    emulated or simulated arm is counted at its own speed, not the PC's.
  * action efficiency: grasp successes / executed actions (objects per action).
  * moves by kind: executed pushes and shifts.
  * contact stops: executed grasps whose guarded descent stopped at a contact,
    and the median of how far short of the planned depth (mm) -- what
    ``robot.descent_contact_force`` tunes.
  * plans refused: decisions the safety envelope refused (never sent to the cell).
  * faults: fault events recorded by the daemon.
  * frames refused: pictures taken with the tool in the camera's view of the workspace (never decided on).
  * timing: medians over the last ``TIMING_WINDOW`` cycles of each phase, the
    whole cycle, and the controller's own time (cycle minus execution); on the
    cell's clock, the cycle and its motion, gripper and waiting parts (the arm
    standing still for the controller).
  * decide hidden share: of the decision time in the same window, the part
    made while the arm placed the previous pick (``robot.decide_while_placing``).
"""

from __future__ import annotations

import statistics
import threading
from typing import Any

from flgd.store import DELETED_TOTALS, TIMING_PHASES, Store
from flgd.store.schema import CYCLE_ON_CELL_CLOCK_SQL

__all__ = ["compute_stats", "status_summary", "TIMING_WINDOW", "format_stats", "FAULT_KINDS", "fault_counts",
           "PHASE_BUCKETS", "PhaseHistograms"]

TIMING_WINDOW = 200


def _rate(rows: list[tuple[Any, ...]]) -> float | None:
    return (sum(1 for (s,) in rows if s) / len(rows)) if rows else None


def _deleted(store: Store) -> dict[str, int]:
    """What the action-log retention deleted (flgd/store/retention.py), so that totals never go down."""
    names = ("actions_deleted", *DELETED_TOTALS)
    marks = ", ".join("?" * len(names))
    found = dict(store.query(f"SELECT name, value FROM counters WHERE name IN ({marks})", names))
    return {name: int(found.get(name, 0)) for name in names}


def compute_stats(store: Store) -> dict[str, Any]:
    q = store.query
    gone = _deleted(store)
    cycles = q("SELECT COUNT(*) FROM actions")[0][0] + gone["actions_deleted"]
    by_outcome = dict(q("SELECT outcome, COUNT(*) FROM actions GROUP BY outcome"))
    for outcome in ("executed", "refused"):
        if gone[f"deleted_{outcome}"]:
            by_outcome[outcome] = by_outcome.get(outcome, 0) + gone[f"deleted_{outcome}"]
    executed = by_outcome.get("executed", 0)
    kept_attempts, successes = q("SELECT COUNT(*), COALESCE(SUM(success), 0) FROM actions "
                                 "WHERE outcome='executed' AND primitive='grasp'")[0]
    attempts = kept_attempts + gone["deleted_grasp_attempts"]
    successes += gone["deleted_grasp_successes"]
    window = {}
    for n in (50, 200):
        rows = q("SELECT success FROM actions WHERE outcome='executed' AND primitive='grasp' "
                 "ORDER BY step DESC LIMIT ?", (n,))
        window[f"grasp_success_last_{n}"] = _rate(rows)
    moves = dict(q("SELECT kind, COUNT(*) FROM actions WHERE outcome='executed' AND primitive!='grasp' "
                   "GROUP BY kind"))
    for kind in ("push", "shift"):
        moves[kind] = moves.get(kind, 0) + gone[f"deleted_{kind}"]
    stopped_short = [r[0] for r in q("SELECT contact_stop_mm FROM actions WHERE outcome='executed' "
                                     "AND primitive='grasp' AND contact_stop_mm IS NOT NULL")]
    cycle_time = _cycle_time(store)
    faults = q("SELECT COUNT(*) FROM events WHERE kind='fault'")[0][0]
    stuck = q("SELECT COUNT(*) FROM events WHERE kind='stuck'")[0][0]
    frames_refused = q("SELECT COUNT(*) FROM events WHERE kind='frame_refused'")[0][0]
    since_pick = _actions_since_pick(store)
    cols = ", ".join(f"t_{p}" for p in TIMING_PHASES)
    recent = q(f"SELECT {cols}, duration FROM actions ORDER BY step DESC LIMIT ?", (TIMING_WINDOW,))
    timing: dict[str, float | None] = {}
    for i, phase in enumerate((*TIMING_PHASES, "cycle")):
        vals = [r[i] for r in recent if r[i] is not None]
        timing[phase] = statistics.median(vals) if vals else None
    i_exec, i_store = TIMING_PHASES.index("execute"), TIMING_PHASES.index("store")
    # A stored row's duration ends before its own commit (t_store is filled in by the next one), so the
    # store time is added here; a live CycleRecord's duration already includes it (benchmarks/overhead.py).
    overhead = [r[-1] + (r[i_store] or 0.0) - (r[i_exec] or 0.0) for r in recent if r[-1] is not None]
    timing["controller"] = statistics.median(overhead) if overhead else None
    # the cell's side of the same window, on the cell's clock: the arm's motion and the gripper's steps
    split = q(f"SELECT cell_time, gripper_time, {CYCLE_ON_CELL_CLOCK_SQL} FROM actions "
              "WHERE cell_time IS NOT NULL AND duration > 0 ORDER BY step DESC LIMIT ?", (TIMING_WINDOW,))
    timing["motion"] = statistics.median(c - (g or 0.0) for c, g, _ in split) if split else None
    timing["gripper"] = statistics.median(g or 0.0 for _, g, _ in split) if split else None
    timing["cycle_on_cell_clock"] = statistics.median(c for _, _, c in split) if split else None
    # the arm standing still while the controller captured, perceived, decided, planned and stored
    timing["waiting"] = statistics.median(cycle - c for c, _, cycle in split) if split else None
    decided = q("SELECT t_decide, decide_hidden FROM actions WHERE t_decide IS NOT NULL ORDER BY step DESC LIMIT ?",
                (TIMING_WINDOW,))
    deciding = sum(d for d, _ in decided)
    hidden_share = sum(h or 0.0 for _, h in decided) / deciding if deciding > 0 else None
    return {
        "cycles": cycles,
        "outcomes": by_outcome,
        "actions_executed": executed,
        "grasp_attempts": attempts,
        "grasp_successes": successes,
        "grasp_success": (successes / attempts) if attempts else None,
        **window,
        "picks_per_hour": _picks_per_hour(successes, cycle_time),
        "action_efficiency": (successes / executed) if executed else None,
        "moves": {"push": moves.get("push", 0), "shift": moves.get("shift", 0)},
        "plans_refused": by_outcome.get("refused", 0),
        "contact_stops": len(stopped_short),
        "contact_stop_share": (len(stopped_short) / kept_attempts) if kept_attempts else None,  # the kept log
        "contact_stop_mm_median": statistics.median(stopped_short) if stopped_short else None,
        "faults": faults,
        "stuck_events": stuck,
        "frames_refused": frames_refused,
        "actions_since_pick": since_pick,
        "cycle_time_total": cycle_time,
        "timing_median": timing,
        "decide_hidden_share": hidden_share,
        "timing_window": min(len(recent), TIMING_WINDOW),
    }


def status_summary(store: Store) -> dict[str, Any]:
    """The cheap subset for the live status line and STATUS= notifications."""
    q = store.query
    gone = _deleted(store)
    cycles = q("SELECT COUNT(*) FROM actions")[0][0] + gone["actions_deleted"]
    rows = q("SELECT success FROM actions WHERE outcome='executed' AND primitive='grasp' "
             "ORDER BY step DESC LIMIT 50")
    successes = q("SELECT COALESCE(SUM(success), 0) FROM actions WHERE outcome='executed' AND primitive='grasp'")[0][0]
    successes += gone["deleted_grasp_successes"]
    return {"cycles": cycles, "grasp_success_last_50": _rate(rows),
            "picks_per_hour": _picks_per_hour(successes, _cycle_time(store))}


def _actions_since_pick(store: Store) -> int:
    """Decided actions (executed or refused) logged after the newest successful grasp: the loop a person
    should hear about when it grows (docs/metrics.md's alert)."""
    return int(store.query("SELECT COUNT(*) FROM actions WHERE outcome IN ('executed', 'refused') AND step > "
                           "(SELECT COALESCE(MAX(step), -1) FROM actions WHERE success=1)")[0][0])


def _cycle_time(store: Store) -> float:
    kept = store.query(f"SELECT COALESCE(SUM({CYCLE_ON_CELL_CLOCK_SQL}), 0) FROM actions")[0][0]
    return float(kept + _deleted(store)["deleted_cycle_ms"] / 1000.0)


def _picks_per_hour(grasp_successes: int, cycle_time: float) -> float | None:
    """Successful grasps (never successful moves) per hour of cycling; one definition for status and stats."""
    return (grasp_successes * 3600.0 / cycle_time) if cycle_time > 0 else None


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100.0 * v:.1f}%"


def _num(v: float | None, fmt: str = "{:.1f}") -> str:
    return "-" if v is None else fmt.format(v)


def format_stats(s: dict[str, Any]) -> str:
    """Human-readable ``flgctl stats``."""
    t = s["timing_median"]
    lines = [
        f"cycles               {s['cycles']}  (executed {s['actions_executed']}, refused {s['plans_refused']}, "
        f"other {s['cycles'] - s['actions_executed'] - s['plans_refused']})",
        f"grasps               {s['grasp_successes']} / {s['grasp_attempts']} succeeded ({_pct(s['grasp_success'])})",
        f"rolling success      last 50: {_pct(s['grasp_success_last_50'])}   last 200: "
        f"{_pct(s['grasp_success_last_200'])}",
        f"picks per hour       {_num(s['picks_per_hour'])}",
        f"action efficiency    {_pct(s['action_efficiency'])}",
        f"moves                push {s['moves']['push']}, shift {s['moves']['shift']}",
        f"contact stops        {s['contact_stops']} of the grasps ({_pct(s['contact_stop_share'])}), median "
        f"{_num(s['contact_stop_mm_median'], '{:.1f}')} mm short of the planned depth",
        f"plans refused        {s['plans_refused']}",
        f"faults               {s['faults']}",
        f"frames refused       {s['frames_refused']} (taken with the tool between the camera and the workspace: "
        f"never decided on)",
        f"stuck                {s['stuck_events']} times declared; {s['actions_since_pick']} actions since the "
        f"last successful grasp",
        f"cycle time (median of last {s['timing_window']}):",
    ]
    for phase in (*TIMING_PHASES, "cycle", "controller"):
        lines.append(f"  {phase:<10} {_num(t.get(phase), '{:.3f}')} s")
    lines.append(f"  on the cell's clock: cycle {_num(t.get('cycle_on_cell_clock'), '{:.3f}')} s, motion "
                 f"{_num(t.get('motion'), '{:.3f}')} s, gripper {_num(t.get('gripper'), '{:.3f}')} s, waiting "
                 f"for the controller {_num(t.get('waiting'), '{:.3f}')} s")
    lines.append(f"  decide time hidden behind the arm's motion: {_pct(s.get('decide_hidden_share'))}")
    return "\n".join(lines)


# What a fault was about, from how the daemon words its cause (flgd/daemon/controller.py): a small fixed set,
# so that a dashboard can count faults by kind without one series per message.
FAULT_KINDS: tuple[tuple[str, str], ...] = (
    ("cell fault", "cell"),            # the cell reported a fault (arm, gripper, camera), also during a snapshot
    ("store ", "storage"),             # the store could not be written or read (disk full, read-only, damaged)
    ("checkpoint failed", "learning"),  # a checkpoint of the learner could not be written
    ("reset failed", "reset"),         # the recovery of a reset failed
    ("internal error", "internal"),    # a bug caught in the cycle
)
OTHER_FAULT = "other"


def fault_counts(store: Store) -> dict[str, int]:
    """Recorded faults by kind (every kind of FAULT_KINDS and "other", zeros included)."""
    cases = " ".join(f"WHEN message LIKE '{prefix}%' THEN '{kind}'" for prefix, kind in FAULT_KINDS)
    rows = store.query(f"SELECT CASE {cases} ELSE '{OTHER_FAULT}' END AS k, COUNT(*) FROM events "
                       "WHERE kind='fault' GROUP BY k")
    counts = {kind: 0 for _, kind in FAULT_KINDS}
    counts[OTHER_FAULT] = 0
    counts.update({k: int(n) for k, n in rows})
    return counts


# Upper bounds (s) of the cycle-phase histograms: a decision takes ~0.1 s, a real cell's move several seconds.
PHASE_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 20.0, 40.0, 80.0)


class PhaseHistograms:
    """Cumulative histograms of every phase's duration (and the whole cycle's) over the whole action log.

    Read incrementally: each call adds only the rows logged since the last one, so a scrape costs the
    same after a year of cycles as after an hour.  The newest row is left for the next call, because its
    store time is filled in by the commit after it.
    """

    PHASES = (*TIMING_PHASES, "cycle")

    def __init__(self, buckets: tuple[float, ...] = PHASE_BUCKETS):
        self.buckets = tuple(buckets)
        self._lock = threading.Lock()
        self._upto = -1  # highest step already counted (steps start at 0)
        self._counts = {p: [0] * len(self.buckets) for p in self.PHASES}  # cumulative: <= bound
        self._sums = {p: 0.0 for p in self.PHASES}
        self._totals = {p: 0 for p in self.PHASES}

    def read(self, store: Store) -> dict[str, tuple[list[int], float, int]]:
        """phase -> (cumulative counts per bucket bound, sum of seconds, count of cycles with the phase)."""
        columns = [f"t_{p}" for p in TIMING_PHASES] + ["duration"]
        parts = []
        for c in columns:
            parts.append(f"COUNT({c})")
            parts.append(f"COALESCE(SUM({c}), 0)")
            parts.extend(f"COALESCE(SUM({c} <= {b!r}), 0)" for b in self.buckets)
        with self._lock:
            newest = store.query("SELECT COALESCE(MAX(step), -1) FROM actions")[0][0]
            if newest - 1 > self._upto:
                row = store.query(f"SELECT {', '.join(parts)} FROM actions WHERE step > ? AND step < ?",
                                  (self._upto, newest))[0]
                width = 2 + len(self.buckets)
                for i, phase in enumerate(self.PHASES):
                    chunk = row[i * width:(i + 1) * width]
                    self._totals[phase] += int(chunk[0])
                    self._sums[phase] += float(chunk[1])
                    self._counts[phase] = [a + int(b) for a, b in zip(self._counts[phase], chunk[2:])]
                self._upto = newest - 1
            return {p: (list(self._counts[p]), self._sums[p], self._totals[p]) for p in self.PHASES}
