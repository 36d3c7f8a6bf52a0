"""``flgd bench grasp_objects``: a policy's grasp success per object kind, from the simulator's ground truth.

Why: an evaluation's grasp success says how often grasps fail, not on what.
This runs ``flgd eval``'s evaluator (frozen, greedy) on random clutter and, for
every grasp, asks the simulator which object it aimed at: the object whose
footprint holds the grasp point, else the nearest one.  A kind that fails far
more often than the rest points at a simulator or scene-generator problem (an
object too wide for the gripper, say) or at a gap in training; the numbers are
a diagnosis, never something to train or tune on when the objects are held out.

The simulator is observed, not changed: ``SimCell.execute`` is wrapped to look
at the object poses just before the grasp plan runs.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "cell_config" / "sim.yaml"


def aimed_object(states: list[Any], x: float, y: float) -> tuple[str, bool] | None:
    """(label, whether the point lies inside its footprint's bounding box) of the object a grasp at (x, y) aims at."""
    best = None
    for s in states:
        pts = np.asarray(s.points)
        inside = bool(pts[:, 0].min() <= x <= pts[:, 0].max() and pts[:, 1].min() <= y <= pts[:, 1].max())
        dist = float(np.min(np.hypot(pts[:, 0] - x, pts[:, 1] - y)))
        key = (0 if inside else 1, dist)
        if best is None or key < best[0]:
            best = (key, s.label, inside)
    return None if best is None else (best[1], best[2])


class GraspTally:
    """Grasps per object kind, filled by a wrapper around ``SimCell.execute``."""

    def __init__(self) -> None:
        self.attempts: dict[str, int] = defaultdict(int)
        self.successes: dict[str, int] = defaultdict(int)
        self.off_object = 0

    def wrap(self, cell_class: type) -> Any:
        """Install the observer on ``cell_class``; returns the original method (to restore)."""
        original = cell_class.execute
        tally = self

        def execute(cell: Any, checked: Any) -> Any:
            plan = checked.plan
            aim = aimed_object(cell.object_states(), plan.target[0], plan.target[1]) \
                if plan.primitive == "grasp" else None
            result = original(cell, checked)
            if aim is not None:
                label, inside = aim
                width = result.widths[-1] if result.widths else None
                held = width is not None and width > cell.config.gripper.success_threshold
                tally.attempts[label] += 1
                tally.successes[label] += int(held)
                tally.off_object += int(not inside)
            return result

        cell_class.execute = execute
        return original

    def rows(self) -> list[tuple[str, int, int]]:
        return sorted(((k, self.successes[k], n) for k, n in self.attempts.items()), key=lambda r: (-r[2], r[0]))


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="flgd bench grasp_objects", description=__doc__.splitlines()[0])
    ap.add_argument("--policy", required=True, help="policy file")
    ap.add_argument("--config", default=str(DEFAULT_CONFIG))
    ap.add_argument("--objects", default="", help="object set (sim.object_set syntax); default: the held-out "
                    "novel objects, as in flgd eval --set novel-clutter")
    ap.add_argument("--count", type=int, default=10, help="objects per scene")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-actions", type=int, help="cap per run (default: flgd eval's)")
    args = ap.parse_args(argv)
    if args.runs < 1 or args.count < 1:
        print("flgd bench grasp_objects: --runs and --count must be >= 1", file=sys.stderr)
        return 1

    from flgd.config import ConfigError, load_config
    from flgd.evaluation.evaluator import EvalOptions, EvaluationError, Evaluator
    from flgd.evaluation.scene_sets import HELD_OUT_OBJECTS, clutter_scene
    from flgd.learning.policy_file import PolicyFileError, load_policy
    from sim_cell.cell import SimCell

    objects = args.objects or ",".join(HELD_OUT_OBJECTS)
    try:
        config = load_config(args.config)
        network = load_policy(args.policy).network
        scene = clutter_scene(objects, args.count)
    except (ConfigError, PolicyFileError, ValueError) as exc:
        print(f"flgd bench grasp_objects: {exc}", file=sys.stderr)
        return 1
    tally = GraspTally()
    original = tally.wrap(SimCell)
    try:
        with Evaluator(config, network, EvalOptions(runs=args.runs, seed=args.seed, max_actions=args.max_actions)) as ev:
            ev.evaluate([scene])
    except EvaluationError as exc:
        print(f"flgd bench grasp_objects: {exc}", file=sys.stderr)
        return 1
    finally:
        SimCell.execute = original
    print(f"# flgd bench grasp_objects {' '.join(argv)}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cpus; {args.runs} runs of {args.count} objects "
          f"from {objects!r}, seed {args.seed}")
    print("\n| object | grasp success | grasps |\n|---|---|---|")
    total_ok = total = 0
    for label, ok, n in tally.rows():
        print(f"| {label} | {100 * ok / n:.0f} % | {ok}/{n} |")
        total_ok, total = total_ok + ok, total + n
    if total:
        print(f"| all | {100 * total_ok / total:.1f} % | {total_ok}/{total} |")
    print(f"\n{tally.off_object} grasp(s) aimed outside every object's footprint box (counted at the nearest).")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
