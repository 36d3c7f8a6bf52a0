"""Ray's fault paths without a cluster: the caller's SIGTERM handler survives ``ray.init`` (which installs its
own), and a worker lost more than ``MAX_REPLACEMENTS`` times in a row stops the run instead of being replaced
for ever.  (A killed driver's processes: tests/test_train_workers.py.)"""

from __future__ import annotations

import signal
import sys
import types

import pytest

from flgd.training import ray_engine
from flgd.training.ray_collector import MAX_REPLACEMENTS, RayCollector


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


def _collector() -> tuple[RayCollector, dict[str, list]]:
    """A collector of two workers whose Ray, run and spawning are recorded, not real: what ``_replace`` uses."""
    seen: dict[str, list] = {"lines": [], "events": [], "spawned": [], "killed": []}
    collector = RayCollector(2)
    collector.engine = types.SimpleNamespace(ray=types.SimpleNamespace(kill=seen["killed"].append))
    collector._start = types.SimpleNamespace(say=seen["lines"].append,
                                             store_event=lambda kind, msg: seen["events"].append((kind, msg)))
    collector._spawn = lambda slot: seen["spawned"].append(slot.index)
    return collector, seen


def test_a_worker_lost_more_than_the_limit_in_a_row_stops_the_run_instead_of_a_new_incarnation():
    assert MAX_REPLACEMENTS == 3
    collector, seen = _collector()
    slot = collector.slots[1]
    slot.actor = object()
    lost = RuntimeError("The actor died unexpectedly before finishing this task.")
    for _ in range(MAX_REPLACEMENTS):
        collector._replace(slot, lost)
    assert seen["spawned"] == [1] * MAX_REPLACEMENTS and slot.replacements == MAX_REPLACEMENTS
    assert len(seen["events"]) == MAX_REPLACEMENTS and all(k == "worker" for k, _ in seen["events"])
    with pytest.raises(RuntimeError, match=f"worker 1 lost .*replaced {MAX_REPLACEMENTS} times in a row without a "
                                           "completed cycle: stopping the run"):
        collector._replace(slot, lost)
    assert len(seen["spawned"]) == MAX_REPLACEMENTS  # no fifth incarnation
