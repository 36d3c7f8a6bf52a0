"""``flgd check-config FILE``: validate a cell config and print what will actually be used."""

from __future__ import annotations

import argparse
import json
import sys

from flgd.config import ConfigError, config_to_dict, dump_config, fine_tunes, load_config


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="flgd check-config", description=__doc__)
    parser.add_argument("file", help="cell config YAML")
    parser.add_argument("--json", action="store_true", help="print the effective config as JSON")
    args = parser.parse_args(argv)
    try:
        cfg = load_config(args.file)
    except ConfigError as exc:
        print(f"flgd check-config: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(config_to_dict(cfg), indent=2))
    else:
        rows, cols = cfg.workspace.shape
        print(f"# {cfg.source}: OK ({cfg.backend} cell, heightmap {rows}x{cols} px at "
              f"{cfg.workspace.resolution} m/px)")
        fine_tune, why = fine_tunes(cfg)
        print(f"# learner settings that apply in flgd run and flgd eval --learn: "
              f"{'finetune' if fine_tune else 'learning'} ({why}); flgd train uses learning")
        gate = ("on: learned weights act only after the champion/challenger gate promotes them" if cfg.gate.enabled
                else "OFF: the learner's weights act as soon as they are handed over, unvetted")
        print(f"# gate {gate}")
        print(dump_config(cfg), end="")
    return 0
