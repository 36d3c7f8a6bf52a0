"""Dotted ``section.key=value`` overrides of a cell config, as the benches take them (``--set``, variants).

One reading for every caller: the value is YAML (numbers, true/false, text), except that a number in
exponent form without a dot (``3e-5``), which YAML 1.1 reads as text, is the float it looks like; and the
changed config is checked as any config is (``flgd.config.config_from_dict``).
"""

from __future__ import annotations

import re
from typing import Any

import yaml

from flgd.config import CellConfig, config_from_dict, config_to_dict

__all__ = ["parse_override", "yaml_value", "apply_overrides"]

# what YAML 1.1 leaves a string but is a float: 3e-5, 1E4, -2e+3 (1.0e-5 already reads as a float)
_EXPONENT_FLOAT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def yaml_value(text: str) -> Any:
    """``text`` read as YAML, with an exponent-form number a float."""
    value = yaml.safe_load(text)
    if isinstance(value, str) and _EXPONENT_FLOAT.fullmatch(value.strip()):
        return float(value)
    return value


def parse_override(item: str) -> tuple[str, Any]:
    """``section.key=value`` -> (``section.key``, value); ValueError when ``item`` is not that with a dotted key."""
    key, sep, text = item.partition("=")
    key = key.strip()
    if not sep or "." not in key or "" in key.split("."):
        raise ValueError(f"{item!r} is not KEY=VALUE with a dotted KEY (e.g. finetune.learning_rate=3e-5)")
    return key, yaml_value(text)


def apply_overrides(config: CellConfig, overrides: dict[str, Any], *, source: str, label: str = "") -> CellConfig:
    """``config`` with each dotted key set to its value, checked as a config file is (ConfigError, a ValueError).

    A key that names no config section or key is a ValueError (``label`` heads its message, e.g. ``--set ``)."""
    data = config_to_dict(config)
    for key, value in overrides.items():
        *parents, leaf = key.split(".")
        node = data
        for part in parents:
            node = node.get(part)
            if not isinstance(node, dict):
                raise ValueError(f"{label}{key}: {part} is not a config section")
        if leaf not in node:
            raise ValueError(f"{label}{key}: no such config key")
        node[leaf] = value
    return config_from_dict(data, source=source)
