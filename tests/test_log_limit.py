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


def test_a_full_disk_under_the_learner_gives_at_most_ten_log_lines_a_minute():
    """The real learner, every priority write and checkpoint failing as on a full disk, logged through the
    daemon's filters (``flgd.daemon.run``): 12 updates, each failing twice, are at most 10 lines in all,
    tracebacks included."""
    import errno

    from flgd.actions import Action
    from flgd.daemon.run import LEARNER_LOGGER, limit_learner_log
    from flgd.learning.learner import Learner
    from flgd.learning.networks import build_network
    from flgd.learning.replay import PrioritizedReplay, Transition
    from flgd.store.errors import StoreError
    from tests.fakes.learning import block_scene, learner_config

    def full_disk_store(tagged):
        raise StoreError("cannot write replay priorities: database or disk is full")

    def full_disk_checkpoint(net, updates):
        raise OSError(errno.ENOSPC, "No space left on device")

    cfg = learner_config(checkpoint_every=1)
    replay = PrioritizedReplay.from_config(cfg.learning)
    for i in range(3):
        replay.add(Transition(block_scene(i), Action("grasp", 12, 12, i), 1.0, None, True), tag=i)
    lrn = Learner(cfg, build_network("fast", 16, seed=0), replay, checkpoint_callback=full_disk_checkpoint,
                  priority_sink=full_disk_store)
    lines: list[str] = []

    class Journal(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.extend(self.format(record).splitlines())

    journal = Journal()
    journal.addFilter(RepeatLimit())  # what flgd run puts on its handler
    learner_log = logging.getLogger(LEARNER_LOGGER)
    limit = limit_learner_log()
    learner_log.addHandler(journal)
    try:
        for _ in range(12):
            lrn.update()
    finally:
        learner_log.removeHandler(journal)
        learner_log.removeFilter(limit)
    assert lrn.updates == 12 and "checkpoint at update 12" in lrn.last_error
    assert 2 <= len(lines) <= 10, "\n".join(lines)
    assert any("database or disk is full" in line for line in lines)
    assert any("No space left on device" in line for line in lines)
    assert not any(line.startswith("Traceback") for line in lines)
