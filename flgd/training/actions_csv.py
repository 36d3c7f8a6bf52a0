"""The training action log: ``actions.csv`` in the run directory, one row per step.

The store's ``actions`` table is the authority (it is written in the same
transaction as the transition); the CSV adds what only the trainer knows
(objects left, scene, learner updates and loss, update time) and is easy to
read with any tool.  On resume the CSV is made to agree with the store: rows
beyond the store's last step (the step in flight when the process was killed)
are dropped, and a step the store has but the CSV lost is filled in from the
store with the trainer-only columns left empty.

``objects_left`` counts the objects after the action in the scene it acted on
(also when that ended the scene with objects nothing could grasp; empty for a
discarded action, whose scene blew up); ``scene`` numbers that scene, uniquely
across the segments of a run.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any, Mapping

__all__ = ["COLUMNS", "ActionsCsv", "read_rows"]

COLUMNS = ("step", "time", "outcome", "primitive", "kind", "row", "col", "rotation", "reward", "success", "rule",
           "epsilon", "q_value",
           "mu", "eta", "refused", "failure", "contact_stop_mm", "objects_left", "scene", "scene_kind", "updates", "loss",
           "t_capture", "t_perceive", "t_decide", "t_plan", "t_execute", "t_judge", "t_store", "t_update",
           "duration")


def read_rows(path: str | os.PathLike) -> list[dict[str, str]]:
    """All rows of an action log (empty if the file does not exist)."""
    p = Path(path)
    if not p.exists():
        return []
    with p.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) >= 1e5 else f"{v:.6g}"  # wall-clock times keep their milliseconds
    return v


class ActionsCsv:
    """Appends rows and keeps them in memory for the learning curve."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.rows: list[dict[str, str]] = []

    def reconcile(self, store_rows: list[Mapping[str, Any]]) -> None:
        """Make the CSV agree with the store's action log (see module doc) and load it."""
        by_step = {int(r["step"]): r for r in read_rows(self.path) if r.get("step") not in (None, "")}
        rows = []
        for sr in store_rows:
            step = int(sr["step"])
            if step in by_step:
                rows.append(by_step[step])
            else:
                rows.append({k: str(_cell(sr.get(k))) for k in COLUMNS if k in sr})
        self.rows = [{k: r.get(k, "") for k in COLUMNS} for r in rows]
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        with tmp.open("w", newline="", encoding="utf-8") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(self.rows)
            f.flush()
            os.fsync(f.fileno())
        tmp.replace(self.path)

    def append(self, row: Mapping[str, Any]) -> None:
        unknown = set(row) - set(COLUMNS)
        if unknown:
            raise ValueError(f"action log: unknown columns {sorted(unknown)}")
        out = {k: str(_cell(row.get(k))) for k in COLUMNS}
        new = not self.path.exists()
        with self.path.open("a", newline="", encoding="utf-8") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            if new:
                w.writeheader()
            w.writerow(out)
        self.rows.append(out)
