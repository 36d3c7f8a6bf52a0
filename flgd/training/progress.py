"""Progress of a training run for people: a progress bar on a terminal, plain periodic lines in a log.

The bar is tqdm's (steps done of the run's ``--steps``, its rate and time left) with the run's fields after it:
rolling grasp success, actions/s, learner updates and, for ``--workers``, the workers alive.  Where standard
error is not a terminal (systemd, CI, a redirect) a bar's carriage returns would only garble the log, so the
same fields are written as one line every ``every_steps`` steps or ``every_seconds`` seconds.
"""

from __future__ import annotations

import os
import time
from typing import Any, TextIO

__all__ = ["LineProgress", "BarProgress", "make_progress"]


def _text(step: int, total: int, fields: dict[str, str]) -> str:
    return " | ".join([f"step {step}/{total}"] + [f"{k} {v}" for k, v in fields.items()])


class LineProgress:
    """Periodic plain lines (or, with ``live``, one line rewritten in place without a library)."""

    def __init__(self, stream: TextIO, live: bool, every_steps: int = 25, every_seconds: float = 60.0) -> None:
        self.stream, self.live = stream, live
        self.every_steps, self.every_seconds = every_steps, every_seconds
        self.last_print = 0.0
        self.last_step = -1
        self.total = 0

    def start(self, initial: int, total: int) -> None:
        self.total = total

    def show(self, step: int, fields: dict[str, str], force: bool = False) -> None:
        text = _text(step, self.total, fields)
        now = time.monotonic()
        if self.live:
            try:
                width = os.get_terminal_size(self.stream.fileno()).columns - 1
            except OSError:
                width = 120
            self.stream.write("\r\033[K" + text[:max(20, width)])
            self.stream.flush()
        elif force or step - self.last_step >= self.every_steps or now - self.last_print >= self.every_seconds:
            self.stream.write(text + "\n")
            self.stream.flush()
            self.last_print, self.last_step = now, step

    def message(self, text: str) -> None:
        self.stream.write(("\r\033[K" if self.live else "") + text + "\n")
        self.stream.flush()

    def finish(self) -> None:
        if self.live:
            self.stream.write("\n")
            self.stream.flush()


class BarProgress:
    """tqdm's bar on a terminal; messages are written above it."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.bar: Any = None

    def start(self, initial: int, total: int) -> None:
        from tqdm import tqdm

        try:
            size = os.get_terminal_size(self.stream.fileno())
            width, lines = size.columns, size.lines
        except (OSError, ValueError, AttributeError):
            width = lines = 0
        # a terminal that reports no size (a pty nobody sized) would otherwise get no bar at all
        self.bar = tqdm(total=total, initial=initial, unit="action", file=self.stream, dynamic_ncols=width > 0,
                        ncols=None if width > 0 else 120, nrows=None if lines > 0 else 24, smoothing=0.05,
                        leave=True)

    def show(self, step: int, fields: dict[str, str], force: bool = False) -> None:
        if self.bar is None:
            return
        if step != self.bar.n:
            self.bar.update(step - self.bar.n)
        shown = {k: v for k, v in fields.items() if k not in ("actions/s", "ETA")}  # the bar shows its own
        self.bar.set_postfix_str(" | ".join(f"{k} {v}" for k, v in shown.items()), refresh=force)

    def message(self, text: str) -> None:
        if self.bar is None:
            self.stream.write(text + "\n")
            self.stream.flush()
        else:
            self.bar.write(text, file=self.stream)

    def finish(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def make_progress(stream: TextIO, every_steps: int = 25) -> LineProgress | BarProgress:
    """The bar on a terminal, plain lines elsewhere (module doc)."""
    return BarProgress(stream) if stream.isatty() else LineProgress(stream, False, every_steps=every_steps)
