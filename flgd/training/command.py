"""``flgd train``'s command line: check the arguments and the config, build the run (one process, or one learner
with Ray workers), route Ctrl-C and SIGTERM to a clean stop, and turn the outcome into an exit code."""

from __future__ import annotations

import logging
import os
import signal
import sys
from pathlib import Path

from flgd.config import ConfigError, load_sim_config
from flgd.overrides import apply_overrides, parse_override
from flgd.training.progress import make_progress
from flgd.training.collector import Collector, LocalCollector
from flgd.training.run import CONFIG_FILE, EXIT_ERROR, EXIT_INTERRUPTED, EXIT_USAGE, TrainingCellError, TrainingRun
from flgd.training.settings import (RunFileError, command_line, effective_config, read_run_info,
                                    settings_from_command_line, variant_network)

__all__ = ["main"]


def main(argv: list[str]) -> int:
    args = command_line().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    out = Path(args.out).resolve()
    try:
        previous_info = read_run_info(out)
    except RunFileError as exc:
        print(f"flgd train: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        settings = settings_from_command_line(args, previous_info.get("settings") if previous_info else None)
        for name in ("objects", "steps", "seed", "give_up_after"):
            v = getattr(settings, name)
            if v < 0 or (name == "objects" and not 1 <= v <= 60):
                raise ValueError(f"--{name.replace('_', '-')}: got {v!r}, expected "
                                 + ("1..60" if name == "objects" else ">= 0"))
        if args.threads is not None and args.threads < 0:
            raise ValueError(f"--threads: got {args.threads!r}, expected >= 0")
        if args.workers < 0:
            raise ValueError(f"--workers: got {args.workers!r}, expected >= 0 (0 = one process, no Ray)")
        if args.address and not args.workers:
            raise ValueError("--address: joins a Ray cluster for --workers N; give --workers too")
    except ValueError as exc:
        print(f"flgd train: {exc}", file=sys.stderr)
        return EXIT_USAGE
    config_path = args.config or (str(out / CONFIG_FILE) if previous_info else None)
    if config_path is None:
        print("flgd train: --config is required for a new run", file=sys.stderr)
        return EXIT_USAGE
    try:
        base = load_sim_config(config_path, "training runs in sim_cell; fine-tune on a real cell with `flgd run`")
        if settings.overrides:   # every start: a resume from --config as well as from the run's config.yaml
            base = apply_overrides(base, dict(parse_override(item) for item in settings.overrides),
                                   source=f"{config_path} with --set {' '.join(settings.overrides)}", label="--set ")
    except (ConfigError, ValueError) as exc:
        print(f"flgd train: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        network = variant_network(settings.variant, base.learning.network)
        if settings.init_policy and not previous_info:
            from flgd.learning.policy_file import PolicyFileError, load_policy
            try:
                load_policy(settings.init_policy, expected_variant=network)
            except PolicyFileError as exc:
                raise ValueError(f"--init-policy: {exc}") from None
    except ValueError as exc:
        print(f"flgd train: {config_path}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if base.learning.init_trunk and not previous_info and not settings.init_policy:
        from flgd.learning.trunk import TrunkFileError
        from flgd.wiring import fresh_network
        try:  # a new run would start from it: refuse a trunk that does not fit before anything starts
            fresh_network(effective_config(base, settings, out), None)
        except TrunkFileError as exc:
            print(f"flgd train: {config_path}: learning.init_trunk: {exc}", file=sys.stderr)
            return EXIT_USAGE

    progress = make_progress(sys.stderr, every_steps=max(1, args.log_every))
    collector: Collector = LocalCollector()
    if args.workers:
        from flgd.training.ray_collector import RayCollector

        collector = RayCollector(args.workers, args.address or "")
    run = TrainingRun(out, settings, base, progress, threads=args.threads, collector=collector)

    def on_signal(signum, _frame) -> None:
        run.stop_signals.append(signum)
        if len(run.stop_signals) > 1:
            sys.stderr.write("\nflgd train: second interrupt, exiting now (the store and checkpoints are "
                             "consistent; the updates since the last checkpoint are lost)\n")
            sys.stderr.flush()
            os._exit(EXIT_INTERRUPTED)
        progress.message("flgd train: stopping after the current step (Ctrl-C again to exit at once)")

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        run.setup()
        return run.train()
    except Exception as exc:
        progress.finish()
        # a cell's error names its own type
        print(f"flgd train: {exc}" if isinstance(exc, TrainingCellError) else f"flgd train: {type(exc).__name__}: {exc}",
              file=sys.stderr)
        try:
            run.record_failure()
        except Exception as exc2:
            print(f"flgd train: final checkpoint failed: {exc2}", file=sys.stderr)
        return EXIT_ERROR
    finally:
        run.close()
        for sig, handler in previous.items():  # called in-process (tests, scripts): leave no handler behind
            signal.signal(sig, handler)
