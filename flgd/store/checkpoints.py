"""Policy checkpoints: files in ``<state_dir>/checkpoints`` named by learner update count.

Each is written atomically by ``flgd.learning.policy_file.save_policy``; the last ``keep`` are kept.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Callable

from flgd.store.errors import StoreError, explain

_CKPT_RE = re.compile(r"^checkpoint-(\d{10})\.safetensors$")


class CheckpointDir:
    """Policy checkpoints named by learner update count; the newest ``keep`` are kept."""

    def __init__(self, directory: str | os.PathLike, keep: int = 3):
        if keep < 1:
            raise ValueError(f"CheckpointDir.keep: got {keep!r}, expected >= 1")
        self.directory = Path(directory)
        self.keep = keep

    def path_for(self, updates: int) -> Path:
        return self.directory / f"checkpoint-{int(updates):010d}.safetensors"

    def write(self, save: Callable[[Path], None], updates: int) -> Path:
        """Write a checkpoint with ``save(path)`` (which must write atomically), then prune."""
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            path = self.path_for(updates)
            save(path)
            for old in self.checkpoints()[self.keep:]:
                old.unlink(missing_ok=True)
            return path
        except OSError as exc:
            raise StoreError(explain(exc, self.directory)) from exc

    def remove_temporary(self) -> int:
        """Delete temporary files of checkpoint writes interrupted by a kill (never a finished checkpoint)."""
        if not self.directory.is_dir():
            return 0
        stale = [p for p in self.directory.iterdir() if p.name.startswith(".checkpoint-") and p.name.endswith(".tmp")]
        for p in stale:
            p.unlink(missing_ok=True)
        return len(stale)

    def checkpoints(self) -> list[Path]:
        """Existing checkpoints, newest first."""
        if not self.directory.is_dir():
            return []
        found = [p for p in self.directory.iterdir() if _CKPT_RE.match(p.name)]
        return sorted(found, key=lambda p: p.name, reverse=True)

    @staticmethod
    def updates_of(path: Path) -> int:
        m = _CKPT_RE.match(path.name)
        if not m:
            raise ValueError(f"{path}: not a checkpoint name")
        return int(m.group(1))
