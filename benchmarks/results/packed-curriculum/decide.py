"""Apply rule.md to the evaluation JSONs in evals/: ``python benchmarks/results/packed-curriculum/decide.py [OUT]``."""

import json
import sys
from pathlib import Path

EVALS = Path(__file__).resolve().parent / "evals"
SEEDS = (30, 31)
NAMES = {"baseline": "s{}-3000", "candidate": "packed-s{}-3000"}
PARTS = {"valpacked": ("valpacked", None), "validation": ("valpacked", "validation"),
         "packed": ("valpacked", "packed"), "presets_grasp_only": ("presets7", "presets, grasp-only"),
         "presets_grasp_and_move": ("presets7", "presets, grasp-and-move")}


def pool(path: Path, prefix: str | None) -> dict:
    """Grasps, actions, completions and drops summed over the reports of one ``flgd bench eval --json`` file."""
    total = {"successes": 0, "attempts": 0, "actions": 0, "dropped": 0, "completed": 0, "runs": 0}
    for name, report in json.loads(path.read_text()).items():
        if prefix and not name.startswith(prefix):
            continue
        o = report["overall"]
        total["successes"] += o["grasp_successes"]
        total["attempts"] += o["grasp_attempts"]
        total["actions"] += o["actions"]
        total["dropped"] += o.get("objects_dropped", 0)
        total["completed"] += o["completed_runs"]
        total["runs"] += o["counted_runs"]
    return total


def rates(total: dict) -> dict:
    return dict(total, grasp_success=total["successes"] / total["attempts"],
                picks_per_action=total["successes"] / total["actions"])


def policy(kind: str) -> tuple[dict, dict]:
    per_seed = {seed: {part: rates(pool(EVALS / f"{NAMES[kind].format(seed)}-{file}.json", prefix))
                       for part, (file, prefix) in PARTS.items()} for seed in SEEDS}
    pooled = {part: rates({k: sum(per_seed[s][part][k] for s in SEEDS)
                           for k in ("successes", "attempts", "actions", "dropped", "completed", "runs")})
              for part in PARTS}
    return per_seed, pooled


def main() -> None:
    base, bp = policy("baseline")
    cand, cp = policy("candidate")
    gm, go = cp["presets_grasp_and_move"]["grasp_success"], cp["presets_grasp_only"]["grasp_success"]
    a = gm > go and gm > bp["presets_grasp_and_move"]["grasp_success"]
    b = cp["valpacked"]["grasp_success"] >= bp["valpacked"]["grasp_success"] - 0.015
    c = cp["valpacked"]["picks_per_action"] >= bp["valpacked"]["picks_per_action"] - 0.03
    result = {"rule": "benchmarks/results/packed-curriculum/rule.md", "baseline": {"per_seed": base, "pooled": bp},
              "candidate": {"per_seed": cand, "pooled": cp}, "a": a, "b": b, "c": c, "adopt": a and b and c}
    for name, pooled in (("baseline", bp), ("candidate", cp)):
        for part, v in pooled.items():
            print(f"{name:9s} {part:24s} {100 * v['grasp_success']:.1f} % ({v['successes']}/{v['attempts']}) "
                  f"picks/action {v['picks_per_action']:.3f} completed {v['completed']}/{v['runs']} "
                  f"dropped {v['dropped']}")
    print(f"(a) {a} (b) {b} (c) {c}: {'adopt' if result['adopt'] else 'not adopted'}")
    if len(sys.argv) > 1:
        Path(sys.argv[1]).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
