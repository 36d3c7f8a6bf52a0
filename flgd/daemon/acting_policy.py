"""What will act once ``flgctl reset`` succeeds, for a daemon whose store could not be opened.

Why: with no store there is no gate, and nothing acts; the policy the learner resumed from (a checkpoint) or
the configured file is not what acts after the reset either -- the gate's stored champion is, and only on a
first start the configured policy (which then becomes champion #1).  ``flgctl status`` names that one.  The
champion is read from the store without writing anything (SQLite's immutable read-only mode), which works on a
read-only or full state directory; if even that fails, the status says so.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from flgd.store import DB_NAME

__all__ = ["acting_after_reset"]


def acting_after_reset(state_dir: str | Path, configured: str | None) -> str:
    """The policy the gate will act with after a reset, in words."""
    db_path = Path(state_dir) / DB_NAME
    if db_path.exists():
        try:
            db = sqlite3.connect(f"file:{db_path}?mode=ro&immutable=1", uri=True)
            try:
                row = db.execute("SELECT id, origin FROM policies WHERE role='champion' ORDER BY id DESC "
                                 "LIMIT 1").fetchone()
            finally:
                db.close()
        except sqlite3.Error as exc:
            return f"none acting; after flgctl reset the gate's stored champion (the store cannot be read now: {exc})"
        if row is not None:
            return f"none acting; after flgctl reset champion #{row[0]}: {row[1]}"
    if configured:
        return f"none acting; after flgctl reset policy {configured} (it becomes the champion)"
    return "none acting; after flgctl reset a fresh network (it becomes the champion)"
