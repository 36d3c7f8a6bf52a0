"""``flgd check-config FILE``: validate a cell config and print what will actually be used."""

from __future__ import annotations

import argparse
import json
import sys

from flgd.config import ConfigError, config_to_dict, dump_config, load_config


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
        print(dump_config(cfg), end="")
    return 0
