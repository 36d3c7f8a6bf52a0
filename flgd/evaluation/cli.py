"""``flgd eval``: evaluate a policy in the simulated cell on scene files, random clutter or named scene sets.

Bad input (config, policy file, scene file -- its syntax, missing mesh or URDF
files, objects outside the config's workspace --, object set, output path) is
reported as ``flgd eval: <what is wrong>`` with exit code 1 before anything is
simulated.

Finished runs are never lost: with ``--json`` the report is rewritten
atomically after every finished run (``status: in-progress``).  If the
evaluation stops early -- Ctrl-C, SIGTERM, or an error in a run (named by scene
and run) -- the table of the finished runs is printed and the report saved,
marked partial (``status`` interrupted/failed, ``runs_finished`` of
``runs_planned``), before the exit.

Exit codes (``EXIT_*``): 0 every run finished and the report was written;
1 bad input, an error stopped the evaluation (partial report saved), or the
report could not be written; 2 usage error; 130 interrupted by Ctrl-C (SIGINT);
143 terminated by SIGTERM (partial report saved in both cases).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

__all__ = ["main", "EXIT_OK", "EXIT_ERROR", "EXIT_USAGE", "EXIT_INTERRUPTED", "EXIT_TERMINATED", "Terminated"]

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143
_EXIT_CODES = (f"exit codes: {EXIT_OK} every run finished; {EXIT_ERROR} bad input, an error stopped the evaluation "
               f"(partial report saved) or the report could not be written; {EXIT_USAGE} usage error; "
               f"{EXIT_INTERRUPTED} Ctrl-C, {EXIT_TERMINATED} SIGTERM (partial report saved). With --json the "
               "report is rewritten after every finished run.")


class Terminated(BaseException):
    """SIGTERM, raised in the main thread so that the evaluation unwinds as it does on Ctrl-C.

    A BaseException like KeyboardInterrupt, so ``except Exception`` inside a run cannot swallow it.
    """


def _parser() -> argparse.ArgumentParser:
    from flgd.evaluation.evaluator import DEFAULT_ACTIONS_PER_OBJECT, MIN_DEFAULT_ACTIONS
    from flgd.evaluation.metrics import FAILURE_LIMIT
    from flgd.evaluation.scene_sets import CLUTTER_COUNT, SCENE_SETS

    sets = "; ".join(f"{k}: {v}" for k, v in SCENE_SETS.items())
    p = argparse.ArgumentParser(
        prog="flgd eval",
        description="Evaluate a policy in the simulated cell with VPG's metrics: completion (cleared without more "
                    f"than {FAILURE_LIMIT} consecutive failed actions), grasp success (successful grasps / "
                    "attempts), action efficiency (objects / actions over completed runs), moves by kind.",
        epilog=f"scene sets: {sets}. {_EXIT_CODES}")
    p.add_argument("--config", required=True, help="cell config YAML (backend: sim)")
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--policy", help="policy file (.safetensors) to evaluate")
    who.add_argument("--fresh", action="store_true",
                     help="evaluate an untrained network of the config's learning.network (a baseline)")
    p.add_argument("--scenes", nargs="+", default=[], metavar="FILE",
                   help="scene files: the project's YAML, preset names (pile-20-a) or VPG test cases (.txt)")
    p.add_argument("--objects", metavar="GLOB",
                   help="random clutter of these objects: 'blocks', pybullet_data globs "
                        "('random_urdfs/0[0-9][0-9]/*.urdf') or names ('duck,teddy,mug')")
    p.add_argument("--count", type=int, default=CLUTTER_COUNT,
                   help=f"objects per random clutter (--objects, novel-clutter, urdf-clutter; default {CLUTTER_COUNT})")
    p.add_argument("--set", dest="sets", action="append", default=[], choices=list(SCENE_SETS), metavar="NAME",
                   help="a named scene set (repeatable): " + ", ".join(SCENE_SETS))
    p.add_argument("--vpg", metavar="DIR", default=os.environ.get("FLGD_VPG_DIR"),
                   help="a copy of VPG's files (test-cases/ and objects/blocks/) for --set vpg-hard "
                        "(default: $FLGD_VPG_DIR)")
    p.add_argument("--vpg-meshes", metavar="DIR",
                   help="VPG's block meshes for .txt scenes (default: objects/blocks next to the test cases)")
    p.add_argument("--runs", type=int, default=3, help="runs per scene (default 3)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scenes, sensor noise and policy (default 0)")
    learn = p.add_mutually_exclusive_group()
    learn.add_argument("--learn", dest="learn", action="store_true",
                       help="explore and learn online as the daemon does (epsilon from the policy's training steps)")
    learn.add_argument("--no-learn", dest="learn", action="store_false",
                       help="frozen policy, greedy (epsilon 0; anti-repeat and two-failures rules on) [default]")
    p.set_defaults(learn=False)
    p.add_argument("--variant", choices=("dpen", "flg", "rho-fcn"),
                   help="the method, independent of the trunk: flg and rho-fcn act with the masks, dpen without "
                        "(default: the config's exploration.masks); with --fresh it also picks the head on the "
                        "trunk of the config's learning.network; a --policy must have the variant's head")
    p.add_argument("--grasp-only", action="store_true",
                   help="never move (exploration.grasp_only: the paper's Grasping-only mode, Table II)")
    p.add_argument("--max-actions", type=int,
                   help=f"actions per run before it is stopped (default {DEFAULT_ACTIONS_PER_OBJECT} per object, "
                        f"at least {MIN_DEFAULT_ACTIONS})")
    p.add_argument("--json", metavar="OUT", help="write the report as JSON")
    p.add_argument("--png", metavar="OUT", help="write the summary bars as PNG (default: next to --json)")
    p.add_argument("--save-qmaps", metavar="DIR", help="write a Q-map picture of every action into DIR")
    p.add_argument("--quiet", action="store_true", help="no per-run progress lines")
    p.add_argument("--workers", type=int, default=0, metavar="N",
                   help="spread the runs over N Ray workers of one CPU each (frozen evaluation only); each run then "
                        "gets its own seed from --seed, the scene and the run number, so the report is the same "
                        "for every N but not the one-process report of the same --seed (default 0: one process)")
    p.add_argument("--address", metavar="HOST:PORT",
                   help="with --workers: join the Ray cluster at this address instead of starting a local one")
    return p


def _fail(message: str) -> int:
    print(f"flgd eval: {message}", file=sys.stderr)
    return EXIT_ERROR


def _collect_scenes(args: argparse.Namespace, config: Any) -> list[Any]:
    """Every scene asked for, each checked against ``config``'s workspace before anything is simulated."""
    from flgd.evaluation.scene_sets import check_scene, clutter_scene, named_set, scene_from_argument

    scenes = [scene_from_argument(s, args.vpg_meshes) for s in args.scenes]
    if args.objects is not None:
        scenes.append(clutter_scene(args.objects, args.count))
    for name in args.sets:
        scenes.extend(named_set(name, args.vpg, args.count))
    for spec in scenes:
        check_scene(spec, config.workspace, str(config.source))
    return scenes


def prepare_output(path: str | None, what: str) -> Path | None:
    """An output path checked before hours of evaluation rather than after: its directory is created if
    missing and must be writable, the path must not be a directory.  OSError naming ``what`` otherwise."""
    if path is None:
        return None
    out = Path(path)
    blocking = next((d for d in [out.parent, *out.parent.parents] if d.exists()), None)
    if blocking is not None and not blocking.is_dir():
        raise OSError(f"{what} {out}: {blocking} is a file, not a directory")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"{what} {out}: cannot create its directory ({exc.strerror or exc})") from None
    if out.is_dir():
        raise OSError(f"{what} {out}: is a directory, expected a file path")
    if not os.access(out.parent, os.W_OK):
        raise OSError(f"{what} {out}: directory {out.parent} is not writable")
    return out


def _progress(quiet: bool, runs: int) -> Callable[[Any, Any], None]:
    """The per-run progress line (runs counted from 1, as in the JSON and the --save-qmaps folders)."""
    def show(spec: Any, log: Any) -> None:
        if quiet:
            return
        from flgd.evaluation.report import run_line

        print(f"  {run_line(spec.name, log, runs)}", file=sys.stderr, flush=True)
    return show


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    from flgd.config import ConfigError, load_config
    from flgd.evaluation.evaluator import EvalOptions, EvaluationError, Evaluator
    from flgd.evaluation.report import build_report
    from flgd.evaluation.scene_sets import SceneSetError

    if not (args.scenes or args.objects is not None or args.sets):
        return _fail("nothing to evaluate: give --scenes FILE..., --objects GLOB [--count N] or --set NAME")
    for name, value, lo in (("--runs", args.runs, 1), ("--max-actions", args.max_actions, 1),
                            ("--seed", args.seed, 0), ("--workers", args.workers, 0)):
        if value is not None and value < lo:
            return _fail(f"{name}: got {value}, expected >= {lo}")
    if args.workers and args.learn:
        return _fail("--workers: a learning evaluation (--learn) runs in one process; drop one of the two")
    if args.address and not args.workers:
        return _fail("--address: joins a Ray cluster for --workers N; give --workers too")
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        return _fail(str(exc))
    if args.variant:
        import dataclasses

        from flgd.training.run import TRAIN_VARIANTS, variant_network

        config = dataclasses.replace(
            config, exploration=dataclasses.replace(config.exploration, masks=TRAIN_VARIANTS[args.variant][1]))
        if args.fresh:
            config = dataclasses.replace(config, learning=dataclasses.replace(
                config.learning, network=variant_network(args.variant, config.learning.network)))
    try:
        scenes = _collect_scenes(args, config)
    except SceneSetError as exc:
        return _fail(str(exc))
    try:
        json_out = prepare_output(args.json, "--json")
        png_out = prepare_output(args.png, "--png") or (json_out.with_suffix(".png") if json_out else None)
        qmap_dir = Path(args.save_qmaps) if args.save_qmaps else None
        if qmap_dir is not None:
            qmap_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return _fail(str(exc))

    network, policy = _load_network(args, config)
    if network is None:
        return _fail(policy["error"])
    if args.variant and args.policy:
        from flgd.training.run import variant_network

        if variant_network(args.variant, policy["variant"]) != policy["variant"]:
            return _fail(f"--variant {args.variant}: the policy {args.policy} is a {policy['variant']!r} network, "
                         f"whose head is not the {args.variant} head; expected --variant "
                         f"{'rho-fcn' if policy['variant'].startswith('rho-fcn') else 'flg or dpen'}")
    options = EvalOptions(runs=args.runs, seed=args.seed, learn=args.learn, grasp_only=args.grasp_only,
                          max_actions=args.max_actions, save_qmaps=qmap_dir)
    t0 = time.perf_counter()
    planned = len(scenes) * options.runs
    option_fields = {"runs": options.runs, "seed": options.seed, "learn": options.learn,
                     "grasp_only": options.grasp_only, "max_actions": options.max_actions,
                     "failure_limit": options.failure_limit, "workers": args.workers,
                     "run_seeds": "per run, from (seed, scene, run)" if args.workers else "one stream per object set"}

    def report_of(results: list, status: str, stopped: str = "") -> dict[str, Any]:
        return build_report(results, policy=policy, config=str(args.config), options=option_fields,
                            seconds=time.perf_counter() - t0, status=status, runs_planned=planned, stopped=stopped)

    show = _progress(args.quiet, options.runs)
    evaluator = None
    code, status, stopped = EXIT_OK, "complete", ""
    with _sigterm_raises():
        try:
            try:
                if args.workers:
                    from flgd.evaluation.parallel import ParallelEvaluator

                    evaluator = ParallelEvaluator(config, network, options,
                                                  training_steps=int(policy.get("training_steps", 0)),
                                                  workers=args.workers, address=args.address)
                else:
                    evaluator = Evaluator(config, network, options,
                                          training_steps=int(policy.get("training_steps", 0)))
            except (EvaluationError, ValueError) as exc:
                return _fail(str(exc))

            def after_run(spec: Any, log: Any) -> None:
                show(spec, log)
                if json_out is not None:
                    _checkpoint(json_out, report_of(evaluator.results, "in-progress"))

            evaluator.progress = after_run
            evaluator.evaluate(scenes)
        except KeyboardInterrupt:
            code, status, stopped = EXIT_INTERRUPTED, "interrupted", "interrupted by Ctrl-C (SIGINT)"
        except Terminated:
            code, status, stopped = EXIT_TERMINATED, "interrupted", "terminated by SIGTERM"
        except (EvaluationError, ValueError) as exc:
            code, status, stopped = EXIT_ERROR, "failed", str(exc)
        except RuntimeError as exc:  # the Ray engine could not start (flgd.training.ray_engine.EngineError)
            code, status, stopped = EXIT_ERROR, "failed", str(exc)
        try:
            with _signals_ignored():   # a second Ctrl-C must not cut the final report short
                results = evaluator.results if evaluator is not None else []
                if stopped:
                    print(f"flgd eval: {stopped}", file=sys.stderr, flush=True)
                write_code = _finish(report_of(results, status, stopped), json_out, png_out)
        finally:
            if evaluator is not None:
                try:
                    evaluator.close()
                except KeyboardInterrupt:   # the report is saved; only the clean-up was cut short
                    code = code or EXIT_INTERRUPTED
                except Terminated:
                    code = code or EXIT_TERMINATED
    return code or write_code


def _checkpoint(json_out: Path, report: dict[str, Any]) -> None:
    """Rewrite the JSON report after a finished run; a failure is a warning (retried after the next run)."""
    try:
        _write_json(json_out, report)
    except OSError as exc:
        print(f"flgd eval: warning: cannot save the report so far to {json_out} ({exc}); "
              "trying again after the next run", file=sys.stderr, flush=True)


def _write_json(path: Path, report: dict[str, Any]) -> None:
    from flgd.atomic_file import write_atomically
    from flgd.visualize import output_mode

    write_atomically(path, (json.dumps(report, indent=2) + "\n").encode("utf-8"), mode=output_mode(path))


def _finish(report: dict[str, Any], json_out: Path | None, png_out: Path | None) -> int:
    """Print the table and write the report of the runs that finished; EXIT_ERROR if it cannot be written.

    Nothing is printed or written when no run finished: an earlier report at the same path stays.
    """
    from flgd.evaluation.report import format_table, summary_picture

    if report["runs_finished"] == 0:
        if json_out is not None or png_out is not None:
            print("flgd eval: no run finished; no report written", file=sys.stderr)
        return EXIT_OK
    print(format_table(report), flush=True)
    try:
        if json_out is not None:
            _write_json(json_out, report)
        if png_out is not None:
            from flgd.visualize import write_png

            write_png(png_out, summary_picture(report))
    except OSError as exc:
        return _fail(f"cannot write the report: {exc}")
    return EXIT_OK


@contextlib.contextmanager
def _sigterm_raises() -> Iterator[None]:
    """While inside, SIGTERM raises Terminated in the main thread (it has no Python handler by default,
    so it would kill the process and every finished run with it)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _signals_ignored() -> Iterator[None]:
    """Ignore SIGINT and SIGTERM while the final report is written (it takes well under a second)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _load_network(args: argparse.Namespace, config: Any) -> tuple[Any, dict[str, Any]]:
    """(network, policy description) or (None, {"error": message})."""
    if args.fresh:
        from flgd.learning.trunk import TrunkFileError
        from flgd.wiring import fresh_network

        try:
            net, source = fresh_network(config, args.seed)
        except TrunkFileError as exc:
            return None, {"error": f"learning.init_trunk: {exc}"}
        return net, {"path": source, "variant": config.learning.network, "training_steps": 0}
    from flgd.learning.policy_file import PolicyFileError, load_policy

    try:
        loaded = load_policy(args.policy)
    except PolicyFileError as exc:
        return None, {"error": str(exc)}
    meta = loaded.metadata
    return loaded.network, {"path": str(args.policy), "variant": meta["variant"],
                            "training_steps": meta["training_steps"], "weights_sha256": meta["weights_sha256"]}
