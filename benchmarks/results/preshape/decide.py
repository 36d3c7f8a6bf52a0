"""Apply part 1 of rule.md to the evaluation JSONs in evals/: ``python benchmarks/results/preshape/decide.py [OUT
[BASE PRE]]`` (the second addendum's run: base31 pre31)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from benchmarks.rule_checks import decide  # noqa: E402

EVALS = Path(__file__).resolve().parent / "evals"
VARIANTS = tuple(sys.argv[2:4]) if len(sys.argv) > 3 else ("base", "pre")   # second addendum: base31 pre31
PARTS = {"validation": ("valpacked", "validation"), "packed": ("valpacked", "packed")}


def qualifies(c: dict, b: dict) -> dict:
    both = ("validation", "packed")
    return {
        "a": c["pooled"]["grasp_success"] >= b["pooled"]["grasp_success"] - 0.01
        and c["pooled"]["picks_per_action"] >= b["pooled"]["picks_per_action"] - 0.02,
        "b": all(c[p]["grasp_success"] >= b[p]["grasp_success"] - 0.02 for p in both),
        "c": sum(c[p]["completed"] for p in both) >= sum(b[p]["completed"] for p in both) - 1
        and sum(c[p]["dropped"] for p in both) <= sum(b[p]["dropped"] for p in both) + 2,
    }


if __name__ == "__main__":
    decide(EVALS, VARIANTS, PARTS, ("validation", "packed"), qualifies, "benchmarks/results/preshape/rule.md",
           sys.argv[1] if len(sys.argv) > 1 else None)
