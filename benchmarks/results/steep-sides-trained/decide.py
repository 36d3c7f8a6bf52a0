"""Apply rule.md's choice to the evaluation JSONs in evals/: ``python benchmarks/results/steep-sides-trained/decide.py
[OUT]``.  The best of seeds 40-42 (pooled grasp success over validation, packed and the presets' grasp-and-move;
ties to picks per action, then the lower seed) is judged against the shipped policy by checks (a)-(d)."""

import importlib.util
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
EVALS = HERE / "evals"
SEEDS = ("s40", "s41", "s42")

# the same pooling and checks as steep-sides/ (its rule's (a)-(d) are this rule's (a)-(d))
_spec = importlib.util.spec_from_file_location("steep_sides_decide", HERE.parent / "steep-sides" / "decide.py")
assert _spec is not None and _spec.loader is not None
steep = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(steep)
steep.EVALS = EVALS


def best(results: dict) -> str:
    """The seed with the highest pooled grasp success; ties to picks per action, then the lower seed."""
    return max(SEEDS, key=lambda s: (results[s]["pooled"]["grasp_success"],
                                     results[s]["pooled"]["picks_per_action"],
                                     -int(s[1:])))


def main() -> None:
    results = {v: steep.variant(v) for v in ("base", *SEEDS)}
    for v, parts in results.items():
        for part, t in parts.items():
            print(f"{v:5s} {part:24s} {100 * t['grasp_success']:5.1f} % ({t['successes']}/{t['attempts']}) "
                  f"picks/action {t['picks_per_action']:.3f} moves {t.get('moves')} "
                  f"completed {t.get('completed')}/{t.get('runs')} dropped {t.get('dropped')} streak {t.get('streak')}")
    seed = best(results)
    checks = steep.qualifies(results[seed], results["base"])
    chosen = seed if all(checks.values()) else None
    print("best seed:", seed, checks)
    print("chosen:", chosen)
    if len(sys.argv) > 1:
        Path(sys.argv[1]).write_text(json.dumps({"rule": "benchmarks/results/steep-sides-trained/rule.md",
                                                 "results": results, "best_seed": seed, "checks": checks,
                                                 "chosen": chosen}, indent=1))


if __name__ == "__main__":
    main()
