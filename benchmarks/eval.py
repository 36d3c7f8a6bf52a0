"""``flgd bench eval``: the standard evaluation of a policy file, as reported in BENCHMARKS.md.

Three parts, all frozen and greedy (``flgd eval`` defaults), each with
``--runs`` runs per scene (the novel-object clutter, a single scene, ``--clutter-runs``):

1. VPG's 11 hard test cases (read from ``--vpg``, default <repo>/../shared/external/vpg)
   -- targets: completion 100 %, grasp success >= 90 % (VPG: 82.7 %, 77.2 %);
2. the preset cluttered piles, grasp-only vs grasp-and-move (paper Table II)
   -- target: grasp-and-move has the higher grasp success;
3. held-out novel objects alone and in clutter (paper Table III)
   -- target: grasp success >= 90 % in clutter.

and, only when asked for (``--parts validation``), the check for choosing
between policies: random clutter of 20 blocks, ``--validation-runs`` runs at
each of the evaluation seeds 7, 8, 9 and 10 (never training seeds; another set
with ``--validation-seeds``, for a choice that needs seeds no earlier choice
has seen), pooled -- target: grasp success >= 92 %.  It touches neither VPG's scenes nor the
held-out objects, so a choice made on it does not tune on test data.
``--parts packed`` is its companion for hard arrangements: packed scenes of our
blocks (``flgd eval --set packed``: rows laid flush, a new one every run),
``--validation-runs`` runs at each of the same seeds, pooled.

The same ``Evaluator`` as ``flgd eval`` runs every part (one cycle, one
definition of the metrics).  ``--json`` writes the reports, atomically,
after each part, so a bench cut short keeps the parts it finished.

Bad input (arguments, config, policy, scene sets, an unwritable --json, a
config the evaluator refuses) exits 2 before anything is simulated; an
evaluation that fails part-way exits 1, Ctrl-C 130.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "cell_config" / "sim.yaml"
DEFAULT_VPG = REPO.parent / "shared" / "external" / "vpg"
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
PARTS = ("vpg", "presets", "novel", "validation", "packed")
VALIDATION_SEEDS = (7, 8, 9, 10)   # evaluation seeds: no training run uses them (training seeds are 0-2)
VALIDATION_OBJECTS, VALIDATION_COUNT = "blocks", 20


def _fail(message: str, code: int = EXIT_USAGE) -> int:
    print(f"flgd bench eval: {message}", file=sys.stderr)
    return code


def _write_reports(out: Path, reports: dict) -> None:
    from flgd.atomic_file import write_atomically

    write_atomically(out, (json.dumps(reports, indent=2) + "\n").encode("utf-8"), mode=0o644)


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def _evaluate(config: Any, network: Any, policy: dict, scenes: list, runs: int, seed: int, grasp_only: bool,
              max_actions: int | None) -> dict:
    from flgd.evaluation.evaluator import EvalOptions, Evaluator
    from flgd.evaluation.report import build_report

    options = EvalOptions(runs=runs, seed=seed, grasp_only=grasp_only, max_actions=max_actions)
    t0 = time.perf_counter()

    def progress(spec: Any, log: Any) -> None:
        from flgd.evaluation.report import run_line

        print(f"    {run_line(spec.name, log, runs)}", file=sys.stderr, flush=True)

    with Evaluator(config, network, options, progress=progress) as ev:
        results = ev.evaluate(scenes)
    return build_report(results, policy=policy, config=str(config.source),
                        options={"runs": runs, "seed": seed, "learn": False, "grasp_only": grasp_only,
                                 "max_actions": max_actions, "failure_limit": options.failure_limit},
                        seconds=time.perf_counter() - t0)


def _validation_name(seed: int) -> str:
    return f"validation: {VALIDATION_COUNT} random {VALIDATION_OBJECTS}, seed {seed}"


def _packed_name(seed: int) -> str:
    return f"packed arrangements, seed {seed}"


def validation_pooled(reports: dict[str, dict], name_of=_validation_name,
                      seeds: tuple[int, ...] = VALIDATION_SEEDS) -> tuple[int, int, int, int] | None:
    """(grasp successes, grasp attempts, completed runs, counted runs) summed over the validation seeds
    present in ``reports`` (``name_of(seed)`` names a seed's report: the 20-block or the packed part);
    None when none is.  Pooled counts, not a mean of rates: seeds whose runs took more grasps weigh
    more, as every grasp is one trial."""
    parts = [reports[name_of(s)]["overall"] for s in seeds if name_of(s) in reports]
    if not parts:
        return None
    return (sum(p["grasp_successes"] for p in parts), sum(p["grasp_attempts"] for p in parts),
            sum(p["completed_runs"] for p in parts), sum(p["counted_runs"] for p in parts))


def _line(name: str, s: dict) -> str:
    ppa = s.get("picks_per_action")
    return (f"| {name} | {s['counted_runs']} | {_pct(s['completion'])} | {_pct(s['grasp_success'])} "
            f"({s['grasp_successes']}/{s['grasp_attempts']}) | {'-' if ppa is None else f'{ppa:.2f}'} | "
            f"{_pct(s['action_efficiency'])} | {s['mean_actions'] or 0:.1f} | {s['moves']['push']} / "
            f"{s['moves']['shift']} | {s.get('longest_failure_streak', '-')} / {s.get('stuck_runs', '-')} | "
            f"{s['aborted']} |")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="flgd bench eval", description=__doc__.split("\n\n")[0])
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--policy", help="policy file to evaluate")
    who.add_argument("--fresh", action="store_true", help="an untrained network (to try the benchmark)")
    ap.add_argument("--config", default=str(DEFAULT_CONFIG))
    ap.add_argument("--vpg", default=str(DEFAULT_VPG), help="a copy of VPG's test cases and block meshes")
    ap.add_argument("--runs", type=int, default=3, help="runs per scene (default 3)")
    ap.add_argument("--clutter-runs", type=int, default=10,
                    help="runs of the novel-object clutter, one scene (default 10: about 100 objects, so that "
                         "its grasp success is known to a few points, not to ten)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-actions", type=int, help="cap per run (default: flgd eval's)")
    ap.add_argument("--validation-runs", type=int, default=5,
                    help="runs of 20 random blocks (and of packed arrangements) per validation seed "
                         f"(default 5; seeds {', '.join(map(str, VALIDATION_SEEDS))})")
    ap.add_argument("--validation-seeds", default=",".join(map(str, VALIDATION_SEEDS)),
                    help="comma list of the seeds of the validation and packed parts (default "
                         f"{','.join(map(str, VALIDATION_SEEDS))}); choose seeds no training run and no earlier choice used")
    ap.add_argument("--parts", default="vpg,presets,novel",
                    help="comma list of vpg, presets, novel, validation, packed (default: the first three)")
    ap.add_argument("--json", help="write the reports here")
    args = ap.parse_args(argv)

    from flgd.config import ConfigError, load_config
    from flgd.evaluation.evaluator import EvalOptions, EvaluationError, Evaluator
    from flgd.evaluation.cli import prepare_output
    from flgd.evaluation.scene_sets import SceneSetError, clutter_scene, named_set
    from flgd.learning.policy_file import PolicyFileError, load_policy
    from flgd.learning.trunk import TrunkFileError

    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        return _fail(f"--parts: unknown {unknown}, expected some of {', '.join(PARTS)}")
    for flag, value in (("--runs", args.runs), ("--clutter-runs", args.clutter_runs),
                        ("--validation-runs", args.validation_runs)):
        if value < 1:
            return _fail(f"{flag}: got {value}, expected >= 1")
    if args.max_actions is not None and args.max_actions < 1:
        return _fail(f"--max-actions: got {args.max_actions}, expected >= 1")
    try:
        validation_seeds = tuple(int(s) for s in args.validation_seeds.split(","))
    except ValueError:
        validation_seeds = ()
    if not validation_seeds or len(set(validation_seeds)) != len(validation_seeds) \
            or min(validation_seeds) < 0:
        return _fail(f"--validation-seeds: got {args.validation_seeds!r}, expected a comma list of distinct "
                     f"seeds >= 0, e.g. {','.join(map(str, VALIDATION_SEEDS))}")
    try:
        json_out = prepare_output(args.json, "--json")
    except OSError as exc:
        return _fail(str(exc))
    try:
        config = load_config(args.config)
        if args.fresh:
            from flgd.wiring import fresh_network

            network, source = fresh_network(config, args.seed)
            policy = {"path": source, "training_steps": 0}
        else:
            loaded = load_policy(args.policy)
            network = loaded.network
            policy = {"path": args.policy, "variant": loaded.metadata["variant"],
                      "training_steps": loaded.metadata["training_steps"],
                      "weights_sha256": loaded.metadata["weights_sha256"]}
        # (name, scenes, grasp-only, runs, seed)
        suites: list[tuple[str, list, bool, int, int]] = []
        if "vpg" in parts:
            suites.append(("VPG hard test cases", named_set("vpg-hard", args.vpg), False, args.runs, args.seed))
        if "presets" in parts:
            presets = named_set("presets")
            suites.append(("presets, grasp-only", presets, True, args.runs, args.seed))
            suites.append(("presets, grasp-and-move", presets, False, args.runs, args.seed))
        if "novel" in parts:
            suites.append(("novel objects, isolated", named_set("novel-isolated"), False, args.runs, args.seed))
            suites.append(("novel objects, clutter of 10", named_set("novel-clutter"), False, args.clutter_runs,
                           args.seed))
        if "validation" in parts:
            blocks = [clutter_scene(VALIDATION_OBJECTS, VALIDATION_COUNT)]
            for seed in validation_seeds:
                suites.append((_validation_name(seed), blocks, False, args.validation_runs, seed))
        if "packed" in parts:
            packed = named_set("packed")
            for seed in validation_seeds:
                suites.append((_packed_name(seed), packed, False, args.validation_runs, seed))
        # what the Evaluator refuses (a real-cell config, --max-actions 0), refused now rather than as a
        # traceback: it is built per part, and building it is cheap (no simulator until a scene runs)
        with Evaluator(config, network, EvalOptions(runs=args.runs, seed=args.seed, max_actions=args.max_actions)):
            pass
    except (ConfigError, PolicyFileError, SceneSetError, TrunkFileError, EvaluationError, ValueError) as exc:
        return _fail(str(exc))

    print(f"# flgd bench eval {' '.join(argv)}")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, python "
          f"{platform.python_version()}; config {args.config}; policy {policy['path']} "
          f"({policy.get('training_steps', 0)} training steps); {args.runs} run(s) per scene "
          f"({args.clutter_runs} of the novel clutter), seed {args.seed}"
          + (f"; validation {args.validation_runs} run(s) at each of seeds {', '.join(map(str, validation_seeds))}"
             if {"validation", "packed"} & set(parts) else ""))
    reports: dict[str, dict] = {}
    write_error = ""
    t0 = time.perf_counter()
    for name, scenes, grasp_only, runs, seed in suites:
        print(f"  {name} ...", file=sys.stderr, flush=True)
        kept = f"; the parts done are in {json_out}" if json_out is not None and reports else ""
        try:
            reports[name] = _evaluate(config, network, policy, scenes, runs, seed, grasp_only,
                                      args.max_actions)
        except KeyboardInterrupt:
            return _fail(f"interrupted during {name!r}{kept}", EXIT_INTERRUPTED)
        except (EvaluationError, ValueError) as exc:
            return _fail(f"{name}: {exc}{kept}", EXIT_FAILED)
        if json_out is not None:
            try:
                _write_reports(json_out, reports)
                write_error = ""
            except OSError as exc:  # the evaluation goes on (the next part retries); the table is printed below
                write_error = f"--json {json_out}: cannot write ({exc})"
                print(f"flgd bench eval: {write_error}", file=sys.stderr)
    print("\n| evaluation | runs | completion | grasp success | picks / action | action efficiency | actions/run "
          "| push / shift | longest failure streak / stuck runs | aborted |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, report in reports.items():
        print(_line(name, report["overall"]))
    if "novel objects, isolated" in reports:
        print("\nnovel objects alone (grasp success per object, Table III isolation): " + ", ".join(
            f"{sc['scene'].replace(' alone', '')} {_pct(sc['grasp_success'])}"
            for sc in reports["novel objects, isolated"]["scenes"]))
    print()
    if "VPG hard test cases" in reports:
        s = reports["VPG hard test cases"]["overall"]
        print(f"target VPG hard: completion {_pct(s['completion'])} (target 100 %), grasp success "
              f"{_pct(s['grasp_success'])} / VPG's per-completed-run mean {_pct(s['grasp_success_completed'])} "
              f"(target >= 90 %; VPG 82.7 % completion, 77.2 % grasp success)")
    if "presets, grasp-only" in reports:
        g = reports["presets, grasp-only"]["overall"]["grasp_success"]
        m = reports["presets, grasp-and-move"]["overall"]["grasp_success"]
        ratio = f"{m / g:.2f}" if g and m is not None else "-"
        print(f"target presets: grasp-and-move {_pct(m)} vs grasp-only {_pct(g)} grasp success (ratio {ratio}; "
              "target > 1)")
    if "novel objects, clutter of 10" in reports:
        s = reports["novel objects, clutter of 10"]["overall"]
        print(f"target novel clutter: grasp success {_pct(s['grasp_success'])} (target >= 90 %; paper 94.7 %)")
    seeds = ', '.join(map(str, validation_seeds))
    for label, name_of, target in ((f"validation (20 random blocks, seeds {seeds} pooled)", _validation_name,
                                    " (target >= 92 % grasp success)"),
                                   (f"packed arrangements (seeds {seeds} pooled)", _packed_name, "")):
        pooled = validation_pooled(reports, name_of, validation_seeds)
        if pooled is not None:
            successes, attempts, cleared, counted = pooled
            rate = successes / attempts if attempts else None
            print(f"{label}: grasp success {_pct(rate)} ({successes}/{attempts}), completion "
                  f"{_pct(cleared / counted if counted else None)}{target}")
    print(f"total time {time.perf_counter() - t0:.0f} s")
    return _fail(write_error, EXIT_FAILED) if write_error else EXIT_OK
