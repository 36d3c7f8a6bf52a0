"""Apply rule.md's choice to the evaluation JSONs in evals/: ``python benchmarks/results/steep-sides-confirm/decide.py [OUT]``."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from benchmarks.rule_checks import decide, rule_script  # noqa: E402

EVALS = Path(__file__).resolve().parent / "evals"
VARIANTS = ("base", "t2")
PARTS = {"validation": ("valpacked", "validation"), "packed": ("valpacked", "packed"),
         "presets_grasp_only": ("presets15", "presets, grasp-only"),
         "presets_grasp_and_move": ("presets15", "presets, grasp-and-move")}
POOLED = ("validation", "packed", "presets_grasp_and_move")   # rule (d)


# the first trial's checks (a)-(d), unchanged (rule.md)
qualifies = rule_script("steep-sides").qualifies


if __name__ == "__main__":
    decide(EVALS, VARIANTS, PARTS, POOLED, qualifies, "benchmarks/results/steep-sides-confirm/rule.md",
           sys.argv[1] if len(sys.argv) > 1 else None)
