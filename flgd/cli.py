"""The ``flgd`` command: one entry point, subcommands implemented in their own modules.

Subcommands are looked up lazily ("module:function") so that ``flgd check-config``
works on a machine where the hardware libraries or torch fail to import, and a
subcommand's heavy imports are paid only when it runs.  Each function takes the
remaining argv and returns an exit code.
"""

from __future__ import annotations

import importlib
import sys

_COMMANDS: dict[str, tuple[str, str]] = {
    "check-config": ("flgd.check_config:main", "validate a cell config and print the effective values"),
    "bench": ("flgd.cli:bench_main", "run a benchmark: flgd bench NAME [options]"),
    "calibrate": ("flgd.hardware.calibration:main", "camera-to-base calibration on the real cell"),
    "run": ("flgd.daemon.run:main", "run the cell-controller daemon (foreground; systemd: Type=notify)"),
    "eval": ("flgd.evaluation.cli:main", "evaluate a policy in simulation (VPG's metrics, scene sets, Q-maps)"),
    "train": ("flgd.training.command:main", "train a policy headless in sim_cell (resumable run directory)"),
    "pretrain": ("flgd.training.pretrain:main", "pre-train the network's perception trunk on sim ground truth"),
    "prior-sample": ("flgd.learning.prior_sample:main", "write a prior sample (finetune.prior_sample) from a store"),
    "emulate": ("sim_cell.emulator.main:main", "play the real cell's UR5e, RG2 and D415 on the simulated cell"),
}


def register_command(name: str, target: str, summary: str) -> None:
    _COMMANDS[name] = (target, summary)


def _usage() -> str:
    lines = ["usage: flgd COMMAND [options]", "", "commands:"]
    for name, (_, summary) in _COMMANDS.items():
        lines.append(f"  {name:<14} {summary}")
    lines.append("")
    lines.append("`flgd COMMAND --help` describes a command.")
    return "\n".join(lines)


def _resolve(target: str):
    module_name, _, func = target.partition(":")
    return getattr(importlib.import_module(module_name), func)


def bench_main(argv: list[str]) -> int:
    """``flgd bench NAME``: benchmarks live in the ``benchmarks`` package, one module each."""
    import pkgutil

    import benchmarks

    names = sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__) if not m.name.startswith("_"))
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: flgd bench NAME [options]\n\nbenchmarks: " + ", ".join(names))
        return 0 if argv else 2
    name = argv[0].replace("-", "_")
    if name not in names:
        print(f"flgd bench: unknown benchmark {argv[0]!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    return int(importlib.import_module(f"benchmarks.{name}").main(argv[1:]) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in _COMMANDS:
        print(f"flgd: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    try:
        return int(_resolve(_COMMANDS[name][0])(rest) or 0)
    except BrokenPipeError:  # the reader went away (``| head -1``): quiet, like Unix tools
        from flgd.closed_pipe import stdout_to_devnull

        stdout_to_devnull()
        return 1


if __name__ == "__main__":
    sys.exit(main())
