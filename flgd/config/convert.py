"""From parsed YAML to the schema's dataclasses: types, ranges and unknown keys, each problem worded for an engineer.

Every problem is recorded (with the dotted key, the value and what was expected) rather than raised, so that one
run reports them all; unknown keys get a did-you-mean suggestion, because a typo in a safety limit must never be
silently ignored on a real robot.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from typing import Any, Literal

from flgd.config.messages import MAX_QUOTE, quote

__all__ = ["build"]


def _key_name(raw_key: Any) -> str:
    name = str(raw_key) if not isinstance(raw_key, int) or raw_key.bit_length() <= 200 else quote(raw_key)
    return name if len(name) <= MAX_QUOTE else name[:MAX_QUOTE - 3] + "..."


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        return f"a list of {len(args)} {_type_name(args[0])}s"
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return {float: "number", int: "integer", bool: "boolean (true/false)", str: "string"}.get(tp, str(tp))


def _describe_limits(meta: dict) -> str:
    parts = []
    for key, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
        if meta.get(key) is not None:
            parts.append(f"{op} {meta[key]}")
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    return (" " + " and ".join(parts) + unit) if parts else unit


def _convert(value: Any, tp: Any, key: str, meta: dict, problems: list[str], source: str) -> Any:
    """Convert one YAML value to ``tp``; on failure record a problem and return MISSING."""
    origin = typing.get_origin(tp)
    expected = _type_name(tp) + _describe_limits(meta)

    def bad(why: str = "") -> Any:
        extra = f" ({why})" if why else ""
        problems.append(f"{key}: got {quote(value)}, expected {expected}{extra}")
        return dataclasses.MISSING

    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            return bad()
        return build(tp, value, key, problems, source)
    if origin is Literal:
        return value if value in typing.get_args(tp) else bad()
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            return bad()
        out = []
        for i, (v, a) in enumerate(zip(value, args)):
            c = _convert(v, a, f"{key}[{i}]", meta, problems, source)
            if c is dataclasses.MISSING:
                return dataclasses.MISSING
            out.append(c)
        return tuple(out)
    if tp is bool:
        return value if isinstance(value, bool) else bad()
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            return bad()
        if not -2**63 <= value < 2**63:
            return bad("does not fit a 64-bit integer")
        return _check_range(value, key, meta, expected, problems)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return bad()
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an integer with hundreds of digits does not fit a float
            finite = False
        if not finite:
            return bad("not a finite number")
        return _check_range(float(value), key, meta, expected, problems)
    if tp is str:
        if isinstance(value, str):
            return value if "\x00" not in value else bad("a NUL character (\\x00) cannot be part of a path or name")
        # A camera serial number or a host written without quotes is read by YAML as a number or a date.
        return bad("quote the value to make it a string" if isinstance(value, (int, float)) and
                   not isinstance(value, bool) else "")
    raise TypeError(f"unsupported config field type {tp!r} at {key}")


def _check_range(value: float, key: str, meta: dict, expected: str, problems: list[str]) -> Any:
    checks = (("gt", lambda v, b: v > b), ("ge", lambda v, b: v >= b),
              ("lt", lambda v, b: v < b), ("le", lambda v, b: v <= b))
    for name, ok in checks:
        bound = meta.get(name)
        if bound is not None and not ok(value, bound):
            problems.append(f"{key}: got {quote(value)}, expected {expected}")
            return dataclasses.MISSING
    return value


def build(cls: type, data: dict, prefix: str, problems: list[str], source: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for raw_key, value in data.items():
        key = f"{prefix}.{_key_name(raw_key)}" if prefix else _key_name(raw_key)
        if raw_key not in fields or raw_key == "source":
            close = difflib.get_close_matches(_key_name(raw_key), [n for n in fields if n != "source"], n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            valid = ", ".join(n for n in fields if n != "source")
            problems.append(f"{key}: unknown key{hint} (valid keys here: {valid})")
            continue
        f = fields[raw_key]
        converted = _convert(value, hints[raw_key], key, dict(f.metadata), problems, source)
        if converted is not dataclasses.MISSING:
            kwargs[raw_key] = converted
    try:
        return cls(**kwargs)
    except TypeError as exc:  # a field without default that was not given
        problems.append(f"{prefix or '<top>'}: {exc}")
        return dataclasses.MISSING

