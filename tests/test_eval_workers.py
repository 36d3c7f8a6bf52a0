"""``flgd eval --workers N``: the same report for any N, a killed worker's run redone, what it refuses."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

from flgd.evaluation.cli import main as eval_main

pytest.importorskip("ray")

REPO = Path(__file__).resolve().parents[1]
CONFIG = str(REPO / "cell_config" / "sim.yaml")
POLICY = str(REPO / "policies" / "flg-sim.safetensors")

pytestmark = pytest.mark.slow


def _runs(report: dict) -> list[dict]:
    """Every run's record without its wall time."""
    return [{k: v for k, v in r.items() if k != "seconds"} for s in report["scenes"] for r in s["run_logs"]]


def _eval(out: Path, *extra: str) -> dict:
    code = eval_main(["--config", CONFIG, "--policy", POLICY, "--objects", "blocks", "--count", "3", "--runs", "2",
                      "--seed", "11", "--quiet", "--json", str(out), *extra])
    assert code == 0
    return json.loads(out.read_text())


def test_the_report_does_not_depend_on_the_number_of_workers_and_a_killed_worker_is_replaced(tmp_path, monkeypatch):
    from flgd.evaluation import parallel
    from flgd.training.ray_reaper import _descendants

    one = _eval(tmp_path / "one.json", "--workers", "1")
    assert one["options"]["workers"] == 1 and one["runs_finished"] == 2

    killed: list[int] = []
    spawn = parallel.ParallelEvaluator._spawn

    def spawn_then_kill_the_first(self, actor_class, network_ref):
        actor = spawn(self, actor_class, network_ref)
        if not killed:  # the first worker's process is killed once it is up: its run must be redone elsewhere
            pid = self.engine.ray.get(actor.__ray_ready__.remote()) and _worker_pid(_descendants(os.getpid()))
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
        return actor

    monkeypatch.setattr(parallel.ParallelEvaluator, "_spawn", spawn_then_kill_the_first)
    two = _eval(tmp_path / "two.json", "--workers", "2")
    assert killed
    assert two["runs_finished"] == 2 and two["status"] == "complete"
    assert _runs(two) == _runs(one)


def test_workers_refuse_learning_and_an_address_needs_workers(tmp_path, capsys):
    base = ["--config", CONFIG, "--policy", POLICY, "--objects", "blocks", "--runs", "1"]
    assert eval_main(base + ["--workers", "2", "--learn"]) == 1
    assert "--learn) runs in one process" in capsys.readouterr().err
    assert eval_main(base + ["--address", "127.0.0.1:6379"]) == 1
    assert "give --workers too" in capsys.readouterr().err


def _worker_pid(pids: set[int]) -> int:
    for pid in sorted(pids):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if b"EvalWorker" in cmd:
            return pid
    raise AssertionError("no EvalWorker process found")
