"""Learning curves from an action log: rolling grasp success, steps to a threshold, the PNG.

Rolling grasp success at a grasp attempt = successes among the last ``window``
grasp attempts (the paper's figure: "the average success rate of the [last]
200 steps").  A window counts only once it is full: early on, 3 successes out
of 3 attempts would otherwise "reach 90 %" at step 5.  Refused grasps (the
safety envelope said no) count as failed attempts, as in the cycle's log.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

__all__ = ["GraspSeries", "grasp_series", "rolling_success", "steps_to_threshold", "move_fraction",
           "success_by_rule", "Spread", "spread", "plot_curves"]


@dataclass(frozen=True)
class GraspSeries:
    steps: np.ndarray      # step of each grasp attempt, increasing
    success: np.ndarray    # 1.0 / 0.0 per attempt
    last_step: int         # last step in the log (-1 if empty)


def _as_int(v) -> int | None:
    if v is None or v == "":
        return None
    return int(float(v))


def grasp_series(rows: Iterable[Mapping]) -> GraspSeries:
    """Grasp attempts of action-log rows (dicts with ``step``, ``primitive`` and ``success``)."""
    steps, success, last = [], [], -1
    for r in rows:
        step = _as_int(r.get("step"))
        if step is None:
            continue
        last = max(last, step)
        ok = _as_int(r.get("success"))
        if r.get("primitive") == "grasp" and ok is not None and r.get("outcome", "executed") == "executed":
            steps.append(step)
            success.append(float(ok))
    order = np.argsort(np.asarray(steps, dtype=np.int64), kind="stable")
    return GraspSeries(np.asarray(steps, dtype=np.int64)[order], np.asarray(success, dtype=np.float64)[order], last)


def success_by_rule(rows: Iterable[Mapping], last_steps: int | None = None) -> dict[str, tuple[int, int]]:
    """{decision rule: (successful, attempted)} of executed grasps, over the last ``last_steps`` steps.

    Why: the rolling success mixes greedy grasps with ε-random ones; split by
    the action log's ``rule`` it says whether a plateau is the policy's or the
    exploration's.
    """
    rows = list(rows)
    steps = [s for s in (_as_int(r.get("step")) for r in rows) if s is not None]
    first = (max(steps) + 1 - last_steps) if (steps and last_steps is not None) else None
    out: dict[str, tuple[int, int]] = {}
    for r in rows:
        step, ok = _as_int(r.get("step")), _as_int(r.get("success"))
        if step is None or ok is None or r.get("primitive") != "grasp" or r.get("outcome", "executed") != "executed":
            continue
        if first is not None and step < first:
            continue
        rule = str(r.get("rule") or "unknown")
        done, tried = out.get(rule, (0, 0))
        out[rule] = (done + int(ok > 0), tried + 1)
    return out


def rolling_success(series: GraspSeries, window: int, full_only: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(step, success rate over the last ``window`` attempts) at every attempt; full windows only by default."""
    if window < 1:
        raise ValueError(f"window: got {window!r}, expected >= 1")
    n = len(series.success)
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    csum = np.concatenate([[0.0], np.cumsum(series.success)])
    idx = np.arange(1, n + 1)
    lo = np.maximum(0, idx - window)
    rate = (csum[idx] - csum[lo]) / (idx - lo)
    if full_only:
        keep = idx >= window
        return series.steps[keep], rate[keep]
    return series.steps, rate


def steps_to_threshold(series: GraspSeries, threshold: float, window: int) -> int | None:
    """The first step whose full trailing window of grasp attempts succeeds >= ``threshold``; None if never.

    The returned value counts actions (steps are 0-based, so step s means s + 1 actions taken).
    """
    steps, rate = rolling_success(series, window)
    hit = np.nonzero(rate >= threshold - 1e-12)[0]
    return None if len(hit) == 0 else int(steps[hit[0]]) + 1


def move_fraction(rows: Sequence[Mapping], window: int) -> tuple[np.ndarray, np.ndarray]:
    """(step, share of moves among the last ``window`` actions), from the first full window on."""
    steps, moves = [], []
    for r in rows:
        step = _as_int(r.get("step"))
        if step is None or r.get("primitive") in (None, ""):
            continue
        steps.append(step)
        moves.append(0.0 if r.get("primitive") == "grasp" else 1.0)
    if len(steps) < window:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    order = np.argsort(steps, kind="stable")
    s, m = np.asarray(steps)[order], np.asarray(moves)[order]
    csum = np.concatenate([[0.0], np.cumsum(m)])
    idx = np.arange(window, len(m) + 1)
    return s[idx - 1], (csum[idx] - csum[idx - window]) / window


@dataclass(frozen=True)
class Spread:
    """Median and range over seeds; runs that never reached the value are counted separately."""

    median: float | None
    low: float | None
    high: float | None
    reached: int
    total: int

    def text(self) -> str:
        if self.reached == 0:
            return f"not reached (0/{self.total})"
        med = "not reached" if self.median is None or math.isinf(self.median) else f"{self.median:.0f}"
        hi = "not reached" if self.high is None or math.isinf(self.high) else f"{self.high:.0f}"
        return f"{med} [{self.low:.0f}..{hi}] ({self.reached}/{self.total} runs reached)"


def spread(values: Sequence[int | None]) -> Spread:
    """Median and min..max of ``values``; a None (never reached) ranks above every number."""
    total = len(values)
    reached = [float(v) for v in values if v is not None]
    if not reached:
        return Spread(None, None, None, 0, total)
    ranked = sorted(reached) + [math.inf] * (total - len(reached))
    return Spread(float(statistics.median(ranked)), ranked[0], ranked[-1], len(reached), total)


def plot_curves(path: str | Path, curves: Mapping[str, Sequence[Mapping]], windows: Sequence[int] = (50, 200),
                title: str = "", thresholds: Sequence[float] = (0.8, 0.9),
                groups: Mapping[str, str] | None = None) -> None:
    """One PNG: rolling grasp success (one line per run and window) above the share of moves per window.

    ``groups`` maps a curve label to a group (e.g. the variant); curves of one
    group share a colour.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax_moves) = plt.subplots(2, 1, figsize=(9, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ["-", "--", ":", "-."]
    group_index: dict[str, int] = {}
    for k, (label, rows) in enumerate(curves.items()):
        group = (groups or {}).get(label, label)
        colour = colours[group_index.setdefault(group, len(group_index)) % len(colours)]
        series = grasp_series(rows)
        for j, w in enumerate(windows):
            steps, rate = rolling_success(series, w)
            if len(steps):
                ax.plot(steps + 1, 100 * rate, styles[j % len(styles)], color=colour, lw=1.2,
                        label=f"{label} (last {w} grasps)")
        steps, frac = move_fraction(rows, max(windows))
        if len(steps):
            ax_moves.plot(steps + 1, 100 * frac, color=colour, lw=1.0, label=label)
    for t in thresholds:
        ax.axhline(100 * t, color="grey", lw=0.6, ls=":")
    ax.set_ylabel("rolling grasp success (%)")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="lower right")
    ax.set_title(title or "grasp success vs actions")
    ax_moves.set_ylabel(f"moves per\n{max(windows)} actions (%)")
    ax_moves.set_xlabel("actions (training steps)")
    ax_moves.set_ylim(0, 100)
    ax_moves.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(path)
