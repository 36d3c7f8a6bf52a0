"""Reading a cell config file: the strict YAML loader, its size caps, and load, build and dump of a config.

Every problem is a ``ConfigError`` naming the file, so a wrong or hostile file ends in a message, never in a
traceback or a loader that hangs.
"""

from __future__ import annotations

import dataclasses
import os
import re
import sys
from pathlib import Path
from typing import Any

import yaml

from flgd.config.convert import build
from flgd.config.messages import ConfigError, quote
from flgd.config.rules import check_relations
from flgd.config.schema import CellConfig

__all__ = ["MAX_CONFIG_BYTES", "MAX_CONFIG_VALUES", "config_from_dict", "config_to_dict", "dump_config",
           "load_config", "load_sim_config"]

# A cell config is a few KiB; the caps keep a wrong or hostile file from hanging check-config or the daemon
# (PyYAML parses ~200 KiB/s, and a few lines of YAML aliases can stand for billions of values).
MAX_CONFIG_BYTES = 256 * 1024
MAX_CONFIG_VALUES = 20000  # scalars, lists and mappings after expanding aliases; sim.yaml has ~250


_MERGE_TAG = "tag:yaml.org,2002:merge"


def _check_expansion(root: yaml.Node, limit: int) -> None:
    """Refuse a document that stands for more than ``limit`` values once its aliases are expanded, or whose
    aliases refer to themselves, before anything is built from it (counted per distinct node, so the check
    itself stays as small as the file)."""
    sizes: dict[int, int] = {}
    open_nodes: set[int] = set()

    def size(node: yaml.Node) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in open_nodes:
            raise yaml.constructor.ConstructorError(
                None, None, "an alias refers to the node that contains it, expected a finite config",
                node.start_mark)
        open_nodes.add(key)
        total = 1
        if isinstance(node, yaml.SequenceNode):
            children = node.value
        elif isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        else:
            children = []
        for child in children:
            total += size(child)
            if total > limit:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the document stands for more than {limit} values once its aliases (*name) are "
                                "expanded, expected a cell config (a few hundred values)", node.start_mark)
        open_nodes.discard(key)
        sizes[key] = total
        return total

    size(root)


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys (with plain YAML the last one silently wins), alias bombs and
    integers too long to read; merge keys (``<<: *defaults``) work, their keys overridden by explicit ones."""

    def construct_document(self, node):
        _check_expansion(node, MAX_CONFIG_VALUES)
        return super().construct_document(node)

    def construct_yaml_int(self, node):
        try:
            return super().construct_yaml_int(node)
        except ValueError:  # more digits than Python converts (sys.get_int_max_str_digits)
            raise yaml.constructor.ConstructorError(
                None, None, f"an integer of {len(str(node.value))} characters is too long, expected a number of "
                            f"at most {sys.get_int_max_str_digits()} digits", node.start_mark) from None

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:
                continue  # merged keys may be overridden; only explicit keys must be unique
            key = self.construct_object(key_node, deep=deep)
            try:
                hash(key)
            except TypeError:  # "? [a, b]" or "? {a: 1}": a list or mapping as a key is never a config key
                raise yaml.constructor.ConstructorError(
                    None, None, f"a {type(key).__name__} cannot be a key, expected a plain name",
                    key_node.start_mark) from None
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {quote(key)} (first at line {seen[key] + 1})", key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_constructor("tag:yaml.org,2002:int", _StrictLoader.construct_yaml_int)


# YAML 1.1 (PyYAML) reads ``5e-4`` as a string; engineers write learning rates that way, so
# exponent floats without a dot are numbers here too, as in YAML 1.2.
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def config_from_dict(data: Any, source: str = "<dict>") -> CellConfig:
    """Build and validate a config from parsed YAML; raises ConfigError listing every problem."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(source, [f"<top>: got {type(data).__name__}, expected a mapping of sections"])
    problems: list[str] = []
    cfg = build(CellConfig, data, "", problems, source)
    if cfg is dataclasses.MISSING or problems:
        raise ConfigError(source, problems or ["could not build the config"])
    check_relations(cfg, problems)
    if problems:
        raise ConfigError(source, problems)
    return dataclasses.replace(cfg, source=source)


def load_config(path: str | os.PathLike) -> CellConfig:
    """Read, parse and validate a YAML config file."""
    p = Path(path)
    source = str(p)
    text = _read_config_text(p)
    try:
        data = yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(source, [f"invalid YAML{where}: {problem}"]) from None
    except RecursionError:  # PyYAML parses recursively: thousands of nested brackets exhaust the stack
        raise ConfigError(source, ["invalid YAML: nested too deeply, expected a mapping of sections"]) from None
    if data is None:  # not defaults: an empty file would run the cell against /var/lib/flgd
        raise ConfigError(source, ["the file is empty (or only comments), expected a mapping of sections such as "
                                   "backend, state_dir, workspace (see cell_config/sim.yaml)"])
    cfg = config_from_dict(data, source)
    # A relative state directory or policy file is relative to the config file, not to the cwd.
    if not os.path.isabs(cfg.state_dir):
        cfg = dataclasses.replace(cfg, state_dir=str((p.parent / cfg.state_dir).resolve()))
    if cfg.policy and not os.path.isabs(cfg.policy):
        cfg = dataclasses.replace(cfg, policy=str((p.parent / cfg.policy).resolve()))
    if cfg.finetune.prior_sample and not os.path.isabs(cfg.finetune.prior_sample):
        cfg = dataclasses.replace(cfg, finetune=dataclasses.replace(
            cfg.finetune, prior_sample=str((p.parent / cfg.finetune.prior_sample).resolve())))
    if cfg.learning.init_trunk and not os.path.isabs(cfg.learning.init_trunk):
        cfg = dataclasses.replace(cfg, learning=dataclasses.replace(
            cfg.learning, init_trunk=str((p.parent / cfg.learning.init_trunk).resolve())))
    return cfg


def _read_config_text(p: Path) -> str:
    """The file's text, refusing (ConfigError) a directory, a file over MAX_CONFIG_BYTES or one not UTF-8.

    At most the cap is ever read, so a device or a file that grows cannot hold the loader.
    """
    source = str(p)
    cap_text = f"at most {MAX_CONFIG_BYTES // 1024} KiB (a cell config is a few KiB)"
    try:
        size = p.stat().st_size if p.is_file() else 0
        if size > MAX_CONFIG_BYTES:
            raise ConfigError(source, [f"is {size / 1024:.0f} KiB, expected a YAML file of {cap_text}"])
        with open(p, "rb") as f:
            data = f.read(MAX_CONFIG_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(source, ["file not found"]) from None
    except IsADirectoryError:
        raise ConfigError(source, ["is a directory, expected a YAML file"]) from None
    except OSError as exc:
        raise ConfigError(source, [f"cannot read: {exc.strerror or exc}"]) from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(source, [f"holds more than {MAX_CONFIG_BYTES // 1024} KiB, expected a YAML file of "
                                   f"{cap_text}"])
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(source, [f"cannot read: not UTF-8 text ({exc.reason} at byte {exc.start})"]) from None


def load_sim_config(path: str | os.PathLike, why: str) -> CellConfig:
    """``load_config`` for commands that only run in sim_cell: any other backend is a ``ConfigError`` saying
    ``why``."""
    cfg = load_config(path)
    if cfg.backend != "sim":
        raise ConfigError(str(path), [f"backend: got {cfg.backend!r}, expected 'sim' ({why})"])
    return cfg


def config_to_dict(cfg: Any) -> Any:
    """The effective config as plain YAML-able data (tuples become lists)."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)
                if f.name != "source"}
    if isinstance(cfg, tuple):
        return [config_to_dict(v) for v in cfg]
    return cfg


def dump_config(cfg: CellConfig) -> str:
    return yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=None)

