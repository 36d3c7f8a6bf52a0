"""Apply rule.md to the evaluation JSONs in evals/: ``python benchmarks/results/finger-clearance/decide.py [OUT]``."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from benchmarks.rule_checks import decide  # noqa: E402

EVALS = Path(__file__).resolve().parent / "evals"
VARIANTS = ("base", "fc01", "fc02")
PARTS = {"validation": ("valpacked", "validation"), "packed": ("valpacked", "packed"),
         "valpacked": ("valpacked", None), "presets_grasp_only": ("presets7", "presets, grasp-only"),
         "presets_grasp_and_move": ("presets7", "presets, grasp-and-move")}


def qualifies(c: dict, b: dict) -> dict:
    pk, va, gm = "packed", "validation", "presets_grasp_and_move"
    return {
        "a": c[pk]["grasp_success"] > b[pk]["grasp_success"]
        and c[pk]["picks_per_action"] >= b[pk]["picks_per_action"] - 0.02,
        "b": c[va]["grasp_success"] >= b[va]["grasp_success"] - 0.01
        and c[va]["picks_per_action"] >= b[va]["picks_per_action"] - 0.02 and c[va]["dropped"] <= b[va]["dropped"] + 1,
        "c": c[gm]["grasp_success"] >= b[gm]["grasp_success"] - 0.01 and c[gm]["completed"] >= b[gm]["completed"],
    }


if __name__ == "__main__":
    decide(EVALS, VARIANTS, PARTS, None, qualifies, "benchmarks/results/finger-clearance/rule.md",
           sys.argv[1] if len(sys.argv) > 1 else None, choose_by="valpacked")
