"""The evaluation report: a dict (the JSON), a text table for the terminal and a PNG of bars per scene.

JSON (``format: flgd-eval``, ``version: 1``):

* ``policy`` (path, variant, training_steps, weights_sha256), ``config``,
  ``options`` (runs, seed, learn, grasp_only, max_actions, failure_limit);
* ``scenes``: one entry per scene -- ``scene``, ``set``, ``source``, the
  ``flgd.evaluation.metrics.Summary`` fields, and ``run_logs`` (per run:
  objects, actions, grasp attempts/successes, pushes, shifts, refused,
  objects grasped/left/lost/dropped, end, completed, seconds);
* ``sets``: a Summary per named set; ``overall``: a Summary of every run;
* ``seconds``: wall time of the evaluation;
* ``status``: ``complete`` (every planned run finished), ``in-progress``
  (written after each finished run while the evaluation goes on: a file still
  saying so was left by a process killed without warning), ``interrupted``
  (Ctrl-C or SIGTERM) or ``failed`` (an error stopped it); ``complete`` (bool),
  ``runs_finished`` and ``runs_planned`` (scenes x runs), and ``stopped``: why it
  stopped early ("" otherwise).  A partial report holds the finished runs only;
  scenes without a finished run are left out.

Runs are numbered from 1 within each scene (``run_logs[].run``).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from flgd.evaluation.metrics import FAILURE_LIMIT, RunLog, run_result, summarize
from flgd.evaluation.scene_sets import SceneSpec

__all__ = ["FORMAT", "VERSION", "STATUSES", "build_report", "format_table", "summary_picture", "partial_note",
           "run_line"]

FORMAT = "flgd-eval"
VERSION = 1
STATUSES = ("complete", "in-progress", "interrupted", "failed")


def _run_row(log: RunLog, failure_limit: int) -> dict[str, Any]:
    res = run_result(log, failure_limit)
    return {"run": log.run, "objects": log.objects, "actions": res.actions, "grasp_attempts": res.grasp_attempts,
            "grasp_successes": res.grasp_successes, "push": res.moves["push"], "shift": res.moves["shift"],
            "refused": res.refused, "objects_grasped": log.objects_grasped, "objects_left": log.objects_left,
            "objects_lost": log.objects_lost, "objects_dropped": log.dropped_lost,
            "longest_failure_streak": res.failure_streak,
            "streak_actions": res.streak_actions, "end": log.end,
            "completed": res.completed, "seconds": round(log.seconds, 3), "note": log.note}


def build_report(results: list[tuple[SceneSpec, list[RunLog]]], *, policy: dict[str, Any], config: str,
                 options: dict[str, Any], seconds: float, status: str = "complete",
                 runs_planned: int | None = None, stopped: str = "") -> dict[str, Any]:
    """The JSON-ready report of the module doc; ``runs_planned`` defaults to the runs in ``results``.

    ``status`` says whether the runs are all there, so that a partial report is never read as a
    finished evaluation.
    """
    if status not in STATUSES:
        raise ValueError(f"status: got {status!r}, expected one of {', '.join(STATUSES)}")
    limit = int(options.get("failure_limit", FAILURE_LIMIT))
    finished = sum(len(logs) for _, logs in results)
    planned = finished if runs_planned is None else int(runs_planned)
    if status == "complete" and finished != planned:
        raise ValueError(f"status complete: {finished} runs finished, expected runs_planned ({planned})")
    scenes = []
    groups: dict[str, list[RunLog]] = {}
    everything: list[RunLog] = []
    for spec, logs in results:
        if not logs:
            continue
        scenes.append({"scene": spec.name, "set": spec.group, "source": spec.describe(),
                       **summarize(logs, limit).as_dict(),
                       "run_logs": [_run_row(log, limit) for log in logs]})
        if spec.group:
            groups.setdefault(spec.group, []).extend(logs)
        everything.extend(logs)
    return {"format": FORMAT, "version": VERSION, "policy": policy, "config": config, "options": options,
            "scenes": scenes, "sets": {g: summarize(logs, limit).as_dict() for g, logs in groups.items()},
            "overall": summarize(everything, limit).as_dict(), "seconds": round(seconds, 1),
            "status": status, "complete": status == "complete", "runs_finished": finished, "runs_planned": planned,
            "stopped": stopped}


def run_line(scene: str, log: RunLog, runs: int | None = None) -> str:
    """One finished run for the terminal.  A cleared table with an object pushed off or dropped is not a
    completed run, so the line says which it was and how many were lost."""
    res = run_result(log)
    lost = log.objects_lost
    of = f" of {runs}" if runs is not None else ""
    left = f", {log.objects_left}/{log.objects} objects left"
    if log.aborted:  # the simulator gave up: the scene was reset, its objects were not counted
        verdict, left = "not counted in the rates", ""
    else:
        dropped = log.dropped_lost
        how = f" ({dropped} dropped from the gripper)" if dropped else ""
        verdict = "completed" if res.completed else ("not completed" + (f", {lost} lost{how}" if lost else ""))
    return (f"{scene} run {log.run}{of}: {log.end} ({verdict}), {res.actions} actions, "
            f"{res.grasp_successes}/{res.grasp_attempts} grasps, {res.moves['push']} push, "
            f"{res.moves['shift']} shift{left} ({log.seconds:.1f} s)")


def partial_note(report: dict[str, Any]) -> str:
    """"" for a complete report, else one line saying it is partial, how far it got and why it stopped."""
    status = report.get("status", "complete")
    if status == "complete":
        return ""
    why = f": {report['stopped']}" if report.get("stopped") else ""
    return (f"PARTIAL REPORT ({status}): {report.get('runs_finished', '?')} of {report.get('runs_planned', '?')} "
            f"runs finished{why}")


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100.0 * v:.1f}%"


def _ratio(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


_COLUMNS = (("scene", "<"), ("runs", ">"), ("aborted", ">"), ("complete", ">"), ("grasp ok", ">"), ("grasps", ">"),
            ("picks/act", ">"), ("act.eff", ">"), ("actions/run", ">"), ("streak", ">"), ("in>=5", ">"),
            ("stuck", ">"), ("push", ">"), ("shift", ">"), ("lost", ">"), ("dropped", ">"),
            ("ends", "<"))


def _row(name: str, s: dict[str, Any]) -> list[str]:
    ends = ", ".join(f"{k} {v}" for k, v in sorted(s["ends"].items()))
    return [name, str(s["runs"]), str(s.get("aborted", 0)), _pct(s["completion"]), _pct(s["grasp_success"]),
            f"{s['grasp_successes']}/{s['grasp_attempts']}", _ratio(s.get("picks_per_action")),
            _pct(s["action_efficiency"]), _num(s["mean_actions"]), str(s.get("longest_failure_streak", "-")),
            str(s.get("streak_actions", "-")), str(s.get("stuck_runs", "-")),
            str(s["moves"]["push"]), str(s["moves"]["shift"]), str(s["objects_lost"]), str(s.get("objects_dropped", 0)),
            ends]


def format_table(report: dict[str, Any]) -> str:
    """Fixed-width table: one row per scene, then per set and overall."""
    rows = [_row(sc["scene"], sc) for sc in report["scenes"]]
    tail = [_row(f"[{name}]", s) for name, s in report["sets"].items()]
    tail.append(_row("OVERALL", report["overall"]))
    header = [c for c, _ in _COLUMNS]
    widths = [max(len(r[i]) for r in [header, *rows, *tail]) for i in range(len(header))]

    def line(cells: list[str]) -> str:
        return "  ".join(c.ljust(w) if a == "<" else c.rjust(w)
                         for c, w, (_, a) in zip(cells, widths, _COLUMNS)).rstrip()

    rule = "-" * len(line(header))
    opts = report["options"]
    mode = ("learning online" if opts.get("learn") else "frozen, greedy") + \
           (", grasp-only" if opts.get("grasp_only") else ", grasp-and-move")
    note = partial_note(report)
    out = [*([note] if note else []),
           f"policy {report['policy'].get('path', '?')} ({mode}; {opts.get('runs')} run(s) per scene, "
           f"seed {opts.get('seed')})", line(header), rule, *map(line, rows), rule, *map(line, tail),
           "complete: cleared without more than "
           f"{opts.get('failure_limit', FAILURE_LIMIT)} consecutive failed actions, over the runs not aborted "
           "(aborted: the simulator gave up, the run is in no rate); grasp ok: successful/attempted "
           "grasps; picks/act: successful grasps/actions; act.eff: objects/actions over completed runs; streak: longest "
           "run of consecutive failed actions; in>=5: failed actions in streaks of 5 or more; stuck: runs the cell "
           "gave up (exploration.stuck_after); lost: objects that left the workspace other than in the gripper (pushed off, or dropped on the way out); dropped: of those, lifted by the gripper first",
           *([note] if note else [])]
    return "\n".join(out)


_BAR_COLORS = ((80, 175, 76), (243, 150, 33), (0, 152, 255))  # BGR: completion, grasp success, efficiency
_BAR_NAMES = ("completion", "grasp success", "action efficiency")


def summary_picture(report: dict[str, Any], title: str = "") -> np.ndarray:
    """Grouped bars per scene (and OVERALL): completion, grasp success and action efficiency in %."""
    entries = [(sc["scene"], sc) for sc in report["scenes"]] + [("OVERALL", report["overall"])]
    group_w, bar_w = 96, 24
    left, right, top, bottom = 60, 20, 70, 120
    plot_h = 300
    width = max(640, left + right + group_w * len(entries))
    img = np.full((top + plot_h + bottom, width, 3), 255, dtype=np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    heading = title or f"flgd eval: {report['policy'].get('path', '')}"
    note = partial_note(report)
    if note:   # a partial evaluation must not pass for a finished one, even as a picture
        heading = f"{note.split(':')[0]}, {report.get('runs_finished')} of {report.get('runs_planned')} runs -- {heading}"
    cv2.putText(img, heading[:110], (10, 24), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    x = left
    for name, colour in zip(_BAR_NAMES, _BAR_COLORS):   # legend
        cv2.rectangle(img, (x, 38), (x + 14, 52), colour, -1)
        cv2.putText(img, name, (x + 20, 50), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        x += 30 + cv2.getTextSize(name, font, 0.45, 1)[0][0]
    y0 = top + plot_h
    for pct in range(0, 101, 20):                        # axis and grid
        y = y0 - int(plot_h * pct / 100)
        cv2.line(img, (left - 4, y), (width - right, y), (215, 215, 215) if pct else (0, 0, 0), 1)
        cv2.putText(img, f"{pct}%", (8, y + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for i, (name, s) in enumerate(entries):
        gx = left + i * group_w + (group_w - 3 * bar_w) // 2
        if name == "OVERALL":
            cv2.rectangle(img, (left + i * group_w + 2, top - 8), (left + (i + 1) * group_w - 2, y0), (235, 235, 235), -1)
        for j, value in enumerate((s["completion"], s["grasp_success"], s["action_efficiency"])):
            bx = gx + j * bar_w
            if value is None:
                cv2.putText(img, "-", (bx + 8, y0 - 6), font, 0.5, (90, 90, 90), 1, cv2.LINE_AA)
                continue
            h = int(round(plot_h * max(0.0, min(1.0, float(value)))))
            cv2.rectangle(img, (bx + 2, y0 - h), (bx + bar_w - 3, y0), _BAR_COLORS[j], -1)
            cv2.putText(img, f"{100 * value:.0f}", (bx + 1, y0 - h - 4), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
        label = name if len(name) <= 22 else name[:20] + ".."
        # scene names written downwards under the group
        (tw, th), _ = cv2.getTextSize(label, font, 0.42, 1)
        text = np.full((th + 8, tw + 4, 3), 255, dtype=np.uint8)
        cv2.putText(text, label, (2, th + 2), font, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        text = cv2.rotate(text, cv2.ROTATE_90_CLOCKWISE)
        th2, tw2 = text.shape[:2]
        tx = left + i * group_w + group_w // 2 - tw2 // 2
        th2 = min(th2, bottom - 8)
        img[y0 + 6:y0 + 6 + th2, tx:tx + tw2] = text[:th2]
    return img

