"""What a rule's ``decide.py`` does with ``flgd bench eval --json`` files: pool a variant's parts, apply the rule's
checks of each candidate against the baseline, print the table and write the decision.

The checks are each rule's own (a function of two variants' pooled parts); pooling, the choice among qualifying
candidates and the record are the same for every rule, so two rules never count a part differently.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType
from typing import Callable

__all__ = ["KEYS", "pool", "rates", "variant", "decide", "rule_script"]

RESULTS = Path(__file__).resolve().parent / "results"

KEYS = ("successes", "attempts", "actions", "dropped", "completed", "runs", "moves", "streak")
Parts = dict[str, tuple[str, str | None]]   # part name -> (file stem after "VARIANT-", report name prefix or None: all)
Checks = Callable[[dict, dict], dict[str, bool]]


def rates(total: dict) -> dict:
    """The counts with grasp success per grasp and picks per action beside them."""
    return dict(total, grasp_success=total["successes"] / max(1, total["attempts"]),
                picks_per_action=total["successes"] / max(1, total["actions"]))


def pool(path: Path, prefix: str | None) -> dict:
    """Grasps, actions, moves, completions and drops summed over the reports of one ``flgd bench eval --json`` whose
    names start with ``prefix`` (None: every report); the longest failure streak is the longest of any."""
    total = dict.fromkeys(KEYS, 0)
    for name, report in json.loads(Path(path).read_text()).items():
        if prefix is not None and not name.startswith(prefix):
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


def variant(evals: Path, name: str, parts: Parts, pooled: tuple[str, ...] | None) -> dict:
    """Every part of variant ``name`` (files ``evals/NAME-STEM.json``) and, as "pooled", the sum of the parts named
    in ``pooled`` (None: no pooled part)."""
    out = {part: pool(Path(evals) / f"{name}-{stem}.json", prefix) for part, (stem, prefix) in parts.items()}
    if pooled is not None:
        out["pooled"] = rates({k: sum(out[p][k] for p in pooled) for k in ("successes", "attempts", "actions")})
    return out


def rule_script(folder: str) -> ModuleType:
    """The ``decide.py`` of ``benchmarks/results/FOLDER`` as a module: a later rule that keeps an earlier rule's
    checks calls them instead of restating them."""
    spec = importlib.util.spec_from_file_location(f"decide_{folder.replace('-', '_')}", RESULTS / folder / "decide.py")
    if spec is None or spec.loader is None:
        raise ImportError(f"no decide.py in {RESULTS / folder}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def decide(evals: Path, variants: tuple[str, ...], parts: Parts, pooled: tuple[str, ...] | None, checks: Checks,
           rule: str, out: str | None, choose_by: str = "pooled") -> dict:
    """Pool every variant (the first is the baseline), check the others against it, choose the qualifying one with
    the highest grasp success in part ``choose_by`` (None if none qualifies), print it all and write it to ``out``
    if given."""
    results = {v: variant(evals, v, parts, pooled) for v in variants}
    for v, found in results.items():
        for part, t in found.items():
            print(f"{v:5s} {part:24s} {100 * t['grasp_success']:5.1f} % ({t['successes']}/{t['attempts']}) "
                  f"picks/action {t['picks_per_action']:.3f} moves {t.get('moves')} "
                  f"completed {t.get('completed')}/{t.get('runs')} dropped {t.get('dropped')} streak {t.get('streak')}")
    checked = {v: checks(results[v], results[variants[0]]) for v in variants[1:]}
    ok = [v for v, c in checked.items() if all(c.values())]
    chosen = max(ok, key=lambda v: results[v][choose_by]["grasp_success"]) if ok else None
    for v, c in checked.items():
        print(v, c)
    print("chosen:", chosen)
    decision = {"rule": rule, "results": results, "checks": checked, "chosen": chosen}
    if out:
        Path(out).write_text(json.dumps(decision, indent=1))
    return decision
