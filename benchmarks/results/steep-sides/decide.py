"""Apply rule.md step 2 to the evaluation JSONs in evals/: ``python benchmarks/results/steep-sides/decide.py [OUT]``."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from benchmarks.rule_checks import decide  # noqa: E402

EVALS = Path(__file__).resolve().parent / "evals"
VARIANTS = ("base", "t2", "t4")
PARTS = {"validation": ("valpacked", "validation"), "packed": ("valpacked", "packed"),
         "presets_grasp_only": ("presets7", "presets, grasp-only"),
         "presets_grasp_and_move": ("presets7", "presets, grasp-and-move")}
POOLED = ("validation", "packed", "presets_grasp_and_move")   # rule (d)


def qualifies(c: dict, b: dict) -> dict:
    """Rule step 2's checks (a)-(d) of candidate ``c`` against the baseline ``b``."""
    va, pk, gm = "validation", "packed", "presets_grasp_and_move"
    return {
        "a": c[va]["dropped"] <= b[va]["dropped"] and c[va]["grasp_success"] >= b[va]["grasp_success"] - 0.005
        and c[va]["picks_per_action"] >= b[va]["picks_per_action"] - 0.02 and c[va]["completed"] >= b[va]["completed"],
        "b": c[pk]["grasp_success"] >= b[pk]["grasp_success"] - 0.01
        and c[pk]["picks_per_action"] >= b[pk]["picks_per_action"] - 0.02,
        "c": c[gm]["grasp_success"] >= b[gm]["grasp_success"] - 0.01 and c[gm]["completed"] >= b[gm]["completed"],
        "d": c["pooled"]["grasp_success"] > b["pooled"]["grasp_success"],
    }


if __name__ == "__main__":
    decide(EVALS, VARIANTS, PARTS, POOLED, qualifies, "benchmarks/results/steep-sides/rule.md",
           sys.argv[1] if len(sys.argv) > 1 else None)
