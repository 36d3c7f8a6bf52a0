"""The daemon's states and the transitions allowed between them, each logged with its cause.

Why an explicit table: a robot that starts moving because of an unexpected
state change is a safety problem.  Every change goes through ``transition``,
which refuses anything not in ``ALLOWED`` and records who asked and why.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable

__all__ = ["State", "ALLOWED", "StateChange", "IllegalTransition", "StateMachine"]

log = logging.getLogger("flgd.state")


class State(str, enum.Enum):
    IDLE = "IDLE"          # connected, not acting
    RUNNING = "RUNNING"    # cycles run back to back
    PAUSED = "PAUSED"      # stopped between cycles by the operator
    FAULT = "FAULT"        # the cell or the store failed; no motion until reset
    STOPPING = "STOPPING"  # finishing the cycle in flight, then exiting


ALLOWED: dict[State, frozenset[State]] = {
    State.IDLE: frozenset({State.RUNNING, State.FAULT, State.STOPPING, State.IDLE}),
    State.RUNNING: frozenset({State.PAUSED, State.FAULT, State.STOPPING}),
    State.PAUSED: frozenset({State.RUNNING, State.IDLE, State.FAULT, State.STOPPING}),
    State.FAULT: frozenset({State.IDLE, State.FAULT, State.STOPPING}),
    State.STOPPING: frozenset(),
}


class IllegalTransition(RuntimeError):
    pass


@dataclass(frozen=True)
class StateChange:
    time: float
    old: State
    new: State
    cause: str


class StateMachine:
    """Thread-safe current state, with the history of changes and listeners."""

    def __init__(self, initial: State = State.IDLE, history: int = 100):
        self._state = initial
        self._cause = "started"
        self._since = time.time()
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._history: list[StateChange] = []
        self._history_len = history
        self._listeners: list[Callable[[StateChange], None]] = []

    @property
    def state(self) -> State:
        return self._state

    @property
    def cause(self) -> str:
        return self._cause

    @property
    def since(self) -> float:
        return self._since

    def history(self) -> list[StateChange]:
        with self._lock:
            return list(self._history)

    def add_listener(self, fn: Callable[[StateChange], None]) -> None:
        self._listeners.append(fn)

    def transition(self, new: State, cause: str, *, allowed_from: frozenset[State] | None = None) -> StateChange:
        """Move to ``new``; raise IllegalTransition if the table (or ``allowed_from``) forbids it."""
        with self._lock:
            old = self._state
            if allowed_from is not None and old not in allowed_from:
                raise IllegalTransition(f"not allowed in state {old.value}")
            if new not in ALLOWED[old]:
                raise IllegalTransition(f"cannot go from {old.value} to {new.value}")
            change = StateChange(time.time(), old, new, cause)
            self._state, self._cause, self._since = new, cause, change.time
            self._history.append(change)
            del self._history[:-self._history_len]
            self._changed.notify_all()
        log.info("state %s -> %s: %s", old.value, new.value, cause)
        for fn in self._listeners:
            try:
                fn(change)
            except Exception:  # a listener (notify, store) must not block a state change
                log.exception("state listener failed")
        return change

    def wait_change(self, timeout: float) -> State:
        """Block until the state changes or ``timeout`` passes; return the current state."""
        with self._lock:
            before = (self._state, self._since)
            self._changed.wait_for(lambda: (self._state, self._since) != before, timeout)
            return self._state
