"""Reading the JSON records a run directory keeps (run.json, pretrain.json) without guessing.

A record that does not parse must never be taken for "no record": the caller would start a new run over
the old one's store and checkpoints.  So a damaged file is an error naming the file and what to do.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["read_json_record"]


def read_json_record(path: Path, fix: str) -> Any:
    """The parsed content of ``path``; ValueError "<path>: <problem>; <fix>" when it cannot be read or parsed."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc.msg}: line {exc.lineno} column {exc.colno}; "
                         f"truncated?); {fix}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot be read ({exc}); {fix}") from None
