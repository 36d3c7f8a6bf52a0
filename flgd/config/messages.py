"""How a config problem is reported: ``ConfigError`` and the short quotation of an offending value.

Why apart: the converter, the cross-key rules and the YAML loader all word their problems this way, and a value
of megabytes must never flood a message whichever of them finds it.
"""

from __future__ import annotations

import math
import reprlib
from typing import Any

__all__ = ["ConfigError", "MAX_QUOTE", "quote"]


class ConfigError(ValueError):
    """A config file is unusable; ``problems`` lists every problem found."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = problems
        lines = "\n".join(f"  - {p}" for p in problems)
        super().__init__(f"invalid config {source}:\n{lines}")


MAX_QUOTE = 80  # characters of a value quoted in an error message

_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = _REPR.maxlong = 60
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 6
_REPR.maxlevel = 3


def quote(value: Any) -> str:
    """A short repr for error messages: a value of megabytes, or a list of millions, is summarised."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 200:
        try:
            return f"an integer of {len(str(abs(value)))} digits"
        except ValueError:  # beyond what str() converts
            return f"an integer of about {int(value.bit_length() * math.log10(2)) + 1} digits"
    try:
        text = _REPR.repr(value)
    except Exception:  # a repr that fails must not hide the actual problem
        text = f"<{type(value).__name__}>"
    return text if len(text) <= MAX_QUOTE else text[:MAX_QUOTE - 3] + "..."
