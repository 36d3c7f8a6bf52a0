"""A log that cannot be flooded: the same message at most a few times a minute.

Why: a daemon that runs for weeks meets conditions that fail on every try -- a
disk that is full, a camera that is gone, a port that is attacked.  One line
per failure turns a three-minute episode into a 54 MB journal and buries the
first line, the one that says what happened.  This filter passes the first
``burst`` records of each message (same logger, level and text) in a
``window``; the rest are counted, and the next one that passes says how many
were left out.  Messages that differ in their text (a state change, a
step number) are never held back by each other -- except on a logger whose
messages carry a counter that changes on every failure (the learner's "failed
at update N"): there ``by_template`` keys on the message's format string, and
``quiet`` replaces the traceback of environmental errors (a full disk, a
read-only directory) with the error's one-line text, which says all of it.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

__all__ = ["RepeatLimit", "BURST", "WINDOW"]

BURST = 10
WINDOW = 60.0  # seconds


class RepeatLimit(logging.Filter):
    """Pass at most ``burst`` records of one message per ``window`` seconds; report what was dropped."""

    def __init__(self, burst: int = BURST, window: float = WINDOW, clock: Callable[[], float] = time.monotonic,
                 *, by_template: bool = False, quiet: tuple[type[BaseException], ...] = ()):
        super().__init__()
        self.burst = burst
        self.window = window
        self.clock = clock
        self.by_template = by_template
        self.quiet = quiet
        self._lock = threading.Lock()
        self._seen: dict[tuple[str, int, str], list] = {}  # key -> [window start, passed, dropped]

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            text = record.getMessage()
        except Exception:  # a record whose arguments do not fit its format: the handler will report it
            return True
        key = (record.name, record.levelno, str(record.msg) if self.by_template else text)
        now = self.clock()
        exc = record.exc_info[1] if record.exc_info else None
        if self.quiet and isinstance(exc, self.quiet):
            text = f"{text}: {type(exc).__name__}: {exc}"
            record.msg, record.args, record.exc_info, record.exc_text = text, None, None, None
        with self._lock:
            entry = self._seen.get(key)
            if entry is None or now - entry[0] >= self.window:
                dropped = entry[2] if entry else 0
                self._seen[key] = [now, 1, 0]
                if len(self._seen) > 1000:  # messages seen long ago are forgotten, so the table stays small
                    self._forget_before(now - self.window)
                if dropped:
                    record.msg = f"{text} [{dropped} more like this left out in the last {self.window:g} s]"
                    record.args = None
                return True
            if entry[1] < self.burst:
                entry[1] += 1
                return True
            entry[2] += 1
            return False

    def _forget_before(self, cutoff: float) -> None:
        for key in [k for k, v in self._seen.items() if v[0] < cutoff and not v[2]]:
            del self._seen[key]
