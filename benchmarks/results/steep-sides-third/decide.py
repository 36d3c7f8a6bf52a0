"""Apply rule.md's choice to the evaluation JSONs in evals/: ``python benchmarks/results/steep-sides-third/decide.py [OUT]``."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from benchmarks.rule_checks import decide, rule_script  # noqa: E402

EVALS = Path(__file__).resolve().parent / "evals"
VARIANTS = ("base", "t2")
PARTS = {"validation": ("valpacked", "validation"), "packed": ("valpacked", "packed"),
         "presets_grasp_only": ("presets23", "presets, grasp-only"),
         "presets_grasp_and_move": ("presets23", "presets, grasp-and-move")}
POOLED = ("validation", "packed", "presets_grasp_and_move")   # rule (d)


def qualifies(c: dict, b: dict) -> dict:
    """The first trial's checks (a), (b) and (d), and (c) as this rule changes it: completed runs at most 4 fewer."""
    checks = rule_script("steep-sides").qualifies(c, b)
    gm = "presets_grasp_and_move"
    checks["c"] = c[gm]["grasp_success"] >= b[gm]["grasp_success"] - 0.01 and c[gm]["completed"] >= b[gm]["completed"] - 4
    return checks


if __name__ == "__main__":
    decide(EVALS, VARIANTS, PARTS, POOLED, qualifies, "benchmarks/results/steep-sides-third/rule.md",
           sys.argv[1] if len(sys.argv) > 1 else None)
