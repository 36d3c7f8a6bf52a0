"""Apply rule.md's choice to the evaluation JSONs in evals/: ``python benchmarks/results/steep-sides-third/decide.py [OUT]``."""

import json
import sys
from pathlib import Path

EVALS = Path(__file__).resolve().parent / "evals"
VARIANTS = ("base", "t2")
PARTS = {"validation": ("valpacked", "validation"), "packed": ("valpacked", "packed"),
         "presets_grasp_only": ("presets23", "presets, grasp-only"),
         "presets_grasp_and_move": ("presets23", "presets, grasp-and-move")}
POOLED = ("validation", "packed", "presets_grasp_and_move")   # rule (d)
KEYS = ("successes", "attempts", "actions", "dropped", "completed", "runs", "moves", "streak")


def pool(path: Path, prefix: str) -> dict:
    """Grasps, actions, moves, completions and drops summed over the reports of one ``flgd bench eval --json``."""
    total = dict.fromkeys(KEYS, 0)
    for name, report in json.loads(path.read_text()).items():
        if not name.startswith(prefix):
            continue
        o = report["overall"]
        total["successes"] += o["grasp_successes"]
        total["attempts"] += o["grasp_attempts"]
        total["actions"] += o["actions"]
        total["moves"] += sum(o["moves"].values())
        total["streak"] = max(total["streak"], o["longest_failure_streak"])
        total["dropped"] += o.get("objects_dropped", 0)
        total["completed"] += o["completed_runs"]
        total["runs"] += o["counted_runs"]
    return rates(total)


def rates(total: dict) -> dict:
    """The counts with grasp success per grasp and picks per action beside them."""
    return dict(total, grasp_success=total["successes"] / max(1, total["attempts"]),
                picks_per_action=total["successes"] / max(1, total["actions"]))


def variant(name: str) -> dict:
    """Every part of one variant's evaluations, and rule (d)'s pool."""
    out = {part: pool(EVALS / f"{name}-{file}.json", prefix) for part, (file, prefix) in PARTS.items()}
    out["pooled"] = rates({k: sum(out[p][k] for p in POOLED) for k in ("successes", "attempts", "actions")})
    return out


def qualifies(c: dict, b: dict) -> dict:
    """Rule step 2's checks (a)-(d) of candidate ``c`` against the baseline ``b``."""
    va, pk, gm = "validation", "packed", "presets_grasp_and_move"
    return {
        "a": c[va]["dropped"] <= b[va]["dropped"] and c[va]["grasp_success"] >= b[va]["grasp_success"] - 0.005
        and c[va]["picks_per_action"] >= b[va]["picks_per_action"] - 0.02 and c[va]["completed"] >= b[va]["completed"],
        "b": c[pk]["grasp_success"] >= b[pk]["grasp_success"] - 0.01
        and c[pk]["picks_per_action"] >= b[pk]["picks_per_action"] - 0.02,
        "c": c[gm]["grasp_success"] >= b[gm]["grasp_success"] - 0.01 and c[gm]["completed"] >= b[gm]["completed"] - 4,
        "d": c["pooled"]["grasp_success"] > b["pooled"]["grasp_success"],
    }


def main() -> None:
    results = {v: variant(v) for v in VARIANTS}
    for v, parts in results.items():
        for part, t in parts.items():
            print(f"{v:5s} {part:24s} {100 * t['grasp_success']:5.1f} % ({t['successes']}/{t['attempts']}) "
                  f"picks/action {t['picks_per_action']:.3f} moves {t.get('moves')} "
                  f"completed {t.get('completed')}/{t.get('runs')} dropped {t.get('dropped')} streak {t.get('streak')}")
    checks = {v: qualifies(results[v], results["base"]) for v in VARIANTS[1:]}
    ok = [v for v, c in checks.items() if all(c.values())]
    chosen = max(ok, key=lambda v: results[v]["pooled"]["grasp_success"]) if ok else None
    for v, c in checks.items():
        print(v, c)
    print("chosen:", chosen)
    if len(sys.argv) > 1:
        Path(sys.argv[1]).write_text(json.dumps({"rule": "benchmarks/results/steep-sides-third/rule.md",
                                                 "results": results, "checks": checks, "chosen": chosen}, indent=1))


if __name__ == "__main__":
    main()
