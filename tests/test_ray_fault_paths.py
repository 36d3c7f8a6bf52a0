"""Ray's fault paths without a cluster: the caller's SIGTERM handler survives ``ray.init`` (which installs its
own), and a worker lost more than ``MAX_REPLACEMENTS`` times in a row stops the run instead of being replaced
for ever.  (A killed driver's processes: tests/test_train_workers.py.)"""

from __future__ import annotations

import signal
import sys
import types

import pytest

from flgd.training import ray_engine
from flgd.training.distributed import MAX_REPLACEMENTS, DistributedTrainingRun, _WorkerSlot


def _fake_ray(init_fails: bool) -> types.ModuleType:
    """A ``ray`` whose ``init`` does what Ray's does to SIGTERM (a handler that exits at once)."""
    ray = types.ModuleType("ray")
    ray.installed = []

    def init(**kwargs):
        handler = lambda signum, frame: sys.exit(1)  # noqa: E731
        signal.signal(signal.SIGTERM, handler)
        ray.installed.append(handler)
        if init_fails:
            raise ConnectionError("no cluster")

    ray.init = init
    ray.is_initialized = lambda: False
    ray.shutdown = lambda: None
    ray.cluster_resources = lambda: {"CPU": 4.0}
    return ray


@pytest.mark.parametrize("init_fails", [False, True])
def test_the_callers_sigterm_handler_is_put_back_after_ray_init_whether_it_succeeds_or_not(monkeypatch, init_fails):
    def checkpoint_first(signum, frame):  # what flgd train installs: a checkpoint and a report before exiting
        pass

    monkeypatch.setitem(sys.modules, "ray", _fake_ray(init_fails))
    monkeypatch.setattr(ray_engine, "_check_reachable", lambda address, timeout=5.0: None)
    previous = signal.signal(signal.SIGTERM, checkpoint_first)
    try:
        if init_fails:
            with pytest.raises(ray_engine.EngineError, match="could not start or join"):
                ray_engine.start_engine("127.0.0.1:6379", 1)
        else:
            engine = ray_engine.start_engine("127.0.0.1:6379", 1)
            assert engine.cpus == 4.0
        assert sys.modules["ray"].installed, "the fake ray.init ran and replaced the handler"
        assert signal.getsignal(signal.SIGTERM) is checkpoint_first
    finally:
        signal.signal(signal.SIGTERM, previous)


class _Driver:
    """What ``DistributedTrainingRun._replace`` uses of the run: progress lines, events, Ray, a spawn."""

    def __init__(self):
        self.lines: list[str] = []
        self.events: list[tuple[str, str]] = []
        self.spawned = 0
        self.killed = 0
        self._last_states: dict = {}
        self.progress = types.SimpleNamespace(message=self.lines.append)
        self.store = types.SimpleNamespace(record_event=lambda kind, msg: self.events.append((kind, msg)))
        self.engine = types.SimpleNamespace(ray=types.SimpleNamespace(kill=self._kill))

    def _kill(self, actor) -> None:
        self.killed += 1

    def _spawn(self, slot) -> None:
        self.spawned += 1


def test_a_worker_lost_more_than_the_limit_in_a_row_stops_the_run_instead_of_a_new_incarnation():
    assert MAX_REPLACEMENTS == 3
    driver, slot = _Driver(), _WorkerSlot(index=1, actor=object())
    lost = RuntimeError("The actor died unexpectedly before finishing this task.")
    for _ in range(MAX_REPLACEMENTS):
        DistributedTrainingRun._replace(driver, slot, lost)
    assert driver.spawned == MAX_REPLACEMENTS and slot.replacements == MAX_REPLACEMENTS
    assert len(driver.events) == MAX_REPLACEMENTS and all(k == "worker" for k, _ in driver.events)
    with pytest.raises(RuntimeError, match=f"worker 1 lost .*replaced {MAX_REPLACEMENTS} times in a row without a "
                                           "completed cycle: stopping the run"):
        DistributedTrainingRun._replace(driver, slot, lost)
    assert driver.spawned == MAX_REPLACEMENTS  # no fifth incarnation

