"""Apply rule.md to the ``flgd eval --json`` files in evals/: ``python benchmarks/results/border-grasps/decide.py [OUT]``."""

import json
import sys
from pathlib import Path

EVALS = Path(__file__).resolve().parent / "evals"
VARIANTS = ("today", "fallback", "off")
SEEDS = (11, 12, 13, 14)
SUMMED = ("runs", "completed_runs", "grasp_attempts", "grasp_successes", "actions", "objects_lost",
          "objects_dropped", "stuck_runs", "streak_actions")


def pooled(variant: str) -> dict:
    total = dict.fromkeys(SUMMED, 0)
    streak = 0
    for seed in SEEDS:
        o = json.loads((EVALS / f"{variant}-s{seed}.json").read_text())["overall"]
        for k in SUMMED:
            total[k] += o[k]
        streak = max(streak, o["longest_failure_streak"])
    return dict(total, longest_failure_streak=streak,
                grasp_success=total["grasp_successes"] / total["grasp_attempts"],
                picks_per_action=total["grasp_successes"] / total["actions"],
                completion=total["completed_runs"] / total["runs"])


def main() -> None:
    r = {v: pooled(v) for v in VARIANTS}
    for v, t in r.items():
        print(f"{v:9s} {100 * t['grasp_success']:5.1f} % ({t['grasp_successes']}/{t['grasp_attempts']}) picks/action "
              f"{t['picks_per_action']:.3f} completion {100 * t['completion']:.0f} % stuck {t['stuck_runs']} lost "
              f"{t['objects_lost']} dropped {t['objects_dropped']} streak {t['longest_failure_streak']}")
    today, fb, off = r["today"], r["fallback"], r["off"]
    keep_fallback = (fb["completion"] >= today["completion"] + 0.10 and fb["grasp_success"] >= today["grasp_success"] - 0.01
                     and fb["picks_per_action"] >= today["picks_per_action"] - 0.02)
    ref = max((today, fb), key=lambda t: t["grasp_success"])
    set_off = off["grasp_success"] >= ref["grasp_success"] + 0.01 and off["completion"] >= ref["completion"]
    print("fallback kept:", keep_fallback, "| off set in sim.yaml:", set_off)
    if len(sys.argv) > 1:
        Path(sys.argv[1]).write_text(json.dumps({"rule": "benchmarks/results/border-grasps/rule.md", "pooled": r,
                                                 "fallback_kept": keep_fallback, "off_set": set_off}, indent=1))


if __name__ == "__main__":
    main()
