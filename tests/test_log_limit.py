"""The daemon's log filter: a message that repeats is cut to a few lines a minute and the count is kept."""

from __future__ import annotations

import logging

from flgd.log_limit import RepeatLimit


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _logger(limit: RepeatLimit) -> tuple[logging.Logger, list[str]]:
    lines: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.append(record.getMessage())

    handler = Collect()
    handler.addFilter(limit)
    logger = logging.getLogger(f"test-log-limit-{id(limit)}")
    logger.propagate = False
    logger.setLevel(logging.DEBUG)
    logger.handlers[:] = [handler]
    return logger, lines


def test_a_message_failing_on_every_try_passes_a_burst_per_window_and_reports_the_rest():
    clock = _Clock()
    logger, lines = _logger(RepeatLimit(burst=3, window=60.0, clock=clock))
    for i in range(10_000):
        clock.now = i * 0.001
        logger.error("accept failed: %s", "Too many open files")
    assert lines == ["accept failed: Too many open files"] * 3
    clock.now = 61.0
    logger.error("accept failed: %s", "Too many open files")
    assert lines[-1] == "accept failed: Too many open files [9997 more like this left out in the last 60 s]"


def test_different_messages_and_other_loggers_are_not_held_back_by_a_flood():
    clock = _Clock()
    limit = RepeatLimit(burst=2, window=60.0, clock=clock)
    logger, lines = _logger(limit)
    for _ in range(50):
        logger.warning("camera: no frame")
    logger.warning("stopping: %s", "operator")
    assert lines == ["camera: no frame", "camera: no frame", "stopping: operator"]


def test_messages_of_one_format_with_different_text_are_each_passed():
    clock = _Clock()
    logger, lines = _logger(RepeatLimit(burst=2, window=60.0, clock=clock))
    changes = [("IDLE", "RUNNING"), ("RUNNING", "PAUSED"), ("PAUSED", "RUNNING"), ("RUNNING", "STOPPING")]
    for old, new in changes:
        logger.info("%s -> %s", old, new)
    assert lines == [f"{old} -> {new}" for old, new in changes]
