"""How a finished cycle is kept -- the one way for the daemon, ``flgd train`` and both of its collectors.

The action-log row and the transition go into the store (one SQLite transaction, which completes the
write-ahead intent of the same step), the transition into the replay under the store's id, and the learner is
told, which schedules its ``learning.updates_per_action`` updates.  The time it took is the cycle's ``t_store``.
A training worker's cycle is kept the same way, by the learner's process, once the worker sent it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from flgd.cycle_parts import CycleLearner, CycleReplay, CycleStore
    from flgd.learning.replay import Transition

__all__ = ["Committed", "commit_cycle"]


@dataclass(frozen=True)
class Committed:
    transition_id: int | None   # the store's id of the transition (None: no transition, or no store)
    seconds: float              # store + replay + learner notice


def commit_cycle(row: dict[str, Any], transition: Transition | None, *, store: CycleStore | None,
                 replay: CycleReplay | None, learner: CycleLearner | None) -> Committed:
    """Keep one cycle (module doc); the row's ``step`` is the step it is kept under."""
    t0 = time.perf_counter()
    tid = store.commit_cycle(row, transition) if store is not None else None
    if transition is not None and replay is not None:
        replay.add(transition, tag=tid)
        if learner is not None:
            learner.notify_new_transition()
    seconds = time.perf_counter() - t0
    if store is not None and row.get("step") is not None:
        store.note_store_time(int(row["step"]), seconds)
    return Committed(tid, seconds)
