"""Replay transitions as rows: heightmaps encoded into ``states``, actions and rewards into ``transitions``.

Each state is stored once, zlib-compressed: colour HxWx3 uint8, height as uint16 in units of
``HEIGHT_QUANTUM`` (0.1 mm); the next state of a transition is the state of the following one.
"""

from __future__ import annotations

import sqlite3
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from flgd.actions import Action
from flgd.perception import Heightmaps

if TYPE_CHECKING:
    from flgd.learning.replay import Transition

HEIGHT_QUANTUM = 1e-4  # metres per stored height unit


@dataclass(frozen=True)
class StoredTransition:
    """A transition as read back from the store (converted to the replay's type by the caller)."""

    id: int
    step: int
    state: Heightmaps
    action: Action
    reward: float
    next_state: Heightmaps | None
    done: bool
    priority: float | None


def encode_heightmaps(hm: Heightmaps) -> tuple[int, int, bytes, bytes]:
    color = np.ascontiguousarray(hm.color, dtype=np.uint8)
    height = np.asarray(hm.height, dtype=np.float32)
    rows, cols = height.shape
    if color.shape != (rows, cols, 3):
        raise ValueError(f"heightmaps: colour {color.shape} does not match height {height.shape}")
    q = np.clip(np.nan_to_num(height, nan=0.0) / HEIGHT_QUANTUM, 0, np.iinfo(np.uint16).max)
    q = np.rint(q).astype("<u2")
    return rows, cols, zlib.compress(color.tobytes(), 1), zlib.compress(q.tobytes(), 1)


def decode_heightmaps(rows: int, cols: int, color: bytes, height: bytes) -> Heightmaps:
    c = np.frombuffer(zlib.decompress(color), dtype=np.uint8).reshape(rows, cols, 3).copy()
    h = np.frombuffer(zlib.decompress(height), dtype="<u2").reshape(rows, cols)
    return Heightmaps(color=c, height=(h.astype(np.float32) * np.float32(HEIGHT_QUANTUM)))


def insert_transition(db: sqlite3.Connection, step: int, state_id: int, next_state_id: int | None,
                      transition: Transition, priority: float | None) -> int:
    """Write ``transition`` (``action``, ``reward``, ``done``) of ``step`` between stored states; returns its id."""
    a = transition.action
    cur = db.execute(
        "INSERT INTO transitions(step, state_id, next_state_id, primitive, row, col, rotation, "
        "rotations, reward, done, priority) VALUES(?,?,?,?,?,?,?,?,?,?,?)",
        (step, state_id, next_state_id, a.primitive, int(a.row), int(a.col), int(a.rotation),
         int(a.rotations), float(transition.reward), int(bool(transition.done)),
         None if priority is None else float(priority)))
    return int(cur.lastrowid)
