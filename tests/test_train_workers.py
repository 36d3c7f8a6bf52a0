"""``flgd train --workers N`` on a local Ray cluster: the run directory, a worker killed mid-run, the learner's
updates per collected action, a killed driver resumed, and nothing of Ray left behind."""

from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from flgd.config import load_config
from flgd.store import Store
from flgd.training.actions_csv import read_rows
from flgd.training.ray_reaper import _descendants, _is_ray, _start_time
from flgd.training.command import main as train_main

pytest.importorskip("ray")

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "cell_config" / "sim.yaml"

pytestmark = pytest.mark.slow  # each test starts a Ray cluster and simulated cells


def _config(tmp_path: Path, updates_per_action: int, sync_every: int = 0) -> str:
    """sim.yaml with the learner's updates per action and the workers' weight sync changed."""
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["learning"].update({"updates_per_action": updates_per_action, "sync_every": sync_every})
    cfg["learning"]["init_trunk"] = load_config(str(CONFIG)).learning.init_trunk
    cfg["policy"] = ""
    path = tmp_path / "workers.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


def _still_running(processes: dict[int, str]) -> set[int]:
    """Of ``processes`` (pid -> start time), those that still run: same pid and start time, not a zombie."""
    alive = set()
    for pid, started in processes.items():
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z" and _start_time(pid) == started:
            alive.add(pid)
    return alive


def test_two_workers_fill_one_run_directory_survive_a_killed_worker_and_resume_in_one_process(tmp_path, monkeypatch):
    from flgd.training.progress import LineProgress
    from flgd.training.ray_collector import RayCollector
    from flgd.training.run import TrainingRun
    from flgd.training.settings import RunSettings

    out = tmp_path / "run"
    config = load_config(_config(tmp_path, updates_per_action=2))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})   # two cores: the workers and the learner share them
    said = io.StringIO()
    collector = RayCollector(2)
    run = TrainingRun(out, RunSettings(steps=6, seed=3), config, LineProgress(said, False), threads=1,
                      collector=collector)
    killed: list[int] = []
    keep = run._keep

    def keep_and_kill_worker_1(report):
        kept = keep(report)
        if not killed and run.step >= 2:  # mid-run: worker 1's process is killed (its cycle in flight is lost)
            pid = collector.engine.ray.get(collector.slots[1].actor.pid.remote())
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
        return kept

    run._keep = keep_and_kill_worker_1
    try:
        run.setup()
        assert run.train() == 0
    finally:
        run.close()
    assert killed

    assert "2 workers and the learner on 2 cores" in said.getvalue()
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "finished" and info["step"] == 6
    assert info["segments"][0]["workers"] == 2
    workers = {w["worker"]: w for w in info["segments"][0]["worker_stats"]}
    assert workers[1]["replacements"] == 1 and "lost" not in workers[0]["last_error"]
    assert workers[1]["last_error"] and workers[0]["replacements"] == 0
    assert sum(w["cycles"] for w in workers.values()) == 6

    rows = read_rows(out / "actions.csv")
    assert [int(r["step"]) for r in rows] == list(range(6))
    store = Store(out)
    try:
        assert store.transition_count() == 6
        assert any(e["message"].startswith("worker 1 lost") for e in store.events("worker"))
        steps = [int(r[0]) for r in store.query("SELECT step FROM actions ORDER BY step")]
    finally:
        store.close()
    assert steps == list(range(6))
    # the learner ran exactly the config's updates for every collected action, whichever worker sent it
    assert info["updates"] == 2 * 6
    assert [int(r["updates"]) for r in rows] == [2 * (i + 1) for i in range(6)]
    assert (out / "curve.png").stat().st_size > 0 and sorted((out / "checkpoints").glob("*.safetensors"))

    # the same run directory goes on in one process (no Ray)
    assert train_main(["--out", str(out), "--steps", "8", "--threads", "1"]) == 0
    info = json.loads((out / "run.json").read_text())
    assert info["step"] == 8 and info["updates"] == 2 * 8 and len(info["segments"]) == 2
    # the workers' record stays with the segment they ran in; the one-process segment has none
    assert sum(w["cycles"] for w in info["segments"][0]["worker_stats"]) == 6
    assert "worker_stats" not in info["segments"][1] and "workers" not in info
    assert [int(r["step"]) for r in read_rows(out / "actions.csv")] == list(range(8))


def test_a_killed_driver_leaves_no_ray_process_and_the_same_command_resumes(tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "flgd.cli", "train", "--config", _config(tmp_path, updates_per_action=1),
           "--out", str(out), "--seed", "4", "--threads", "1", "--workers", "1"]
    driver = subprocess.Popen(cmd + ["--steps", "200"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              cwd=REPO, start_new_session=True)
    deadline = time.monotonic() + 240
    try:
        while time.monotonic() < deadline and len(read_rows(out / "actions.csv")) < 2:
            assert driver.poll() is None, driver.stderr.read().decode()
            time.sleep(0.5)
        assert len(read_rows(out / "actions.csv")) >= 2
        under_driver = _descendant_processes(driver.pid)
        assert any(_is_ray(pid) for pid in under_driver)  # the local cluster runs under the driver
        driver.kill()
        driver.wait(30)
    finally:
        if driver.poll() is None:
            driver.kill()
    gone_by = time.monotonic() + 30
    while time.monotonic() < gone_by and _still_running(under_driver):
        time.sleep(0.5)
    # every process the driver had started, judged by parentage, not by the reaper's own idea of a Ray process
    left = _still_running(under_driver)
    assert not left, f"processes of the killed driver live on: {sorted(left)}"

    done = len(read_rows(out / "actions.csv"))
    resumed = subprocess.run(cmd + ["--steps", str(done + 2)], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert "resumed at step" in resumed.stderr
    info = json.loads((out / "run.json").read_text())
    assert info["step"] == done + 2 and info["status"] == "finished" and len(info["segments"]) == 2
    assert [int(r["step"]) for r in read_rows(out / "actions.csv")] == list(range(done + 2))


def test_workers_and_address_are_checked_before_anything_starts(tmp_path, capsys):
    out = tmp_path / "run"
    assert train_main(["--config", str(CONFIG), "--out", str(out), "--workers", "-1"]) == 2
    assert "--workers: got -1" in capsys.readouterr().err
    assert train_main(["--config", str(CONFIG), "--out", str(out), "--address", "127.0.0.1:6379"]) == 2
    assert "give --workers too" in capsys.readouterr().err
    # nothing listens there: said at once (Ray itself would retry for minutes), the run directory not made
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    assert train_main(["--config", str(CONFIG), "--out", str(out), "--workers", "1",
                       "--address", f"127.0.0.1:{free}"]) == 1
    assert f"--address 127.0.0.1:{free}: no Ray cluster answers there" in capsys.readouterr().err
    assert not out.exists()


def _descendant_processes(root: int) -> dict[int, str]:
    """Every process under ``root`` (pid -> start time), Ray's or not."""
    return {pid: _start_time(pid) for pid in _descendants(root)}


def test_an_error_in_a_workers_cycle_stops_the_run_after_storing_its_rows(tmp_path):
    """A cycle that raised in the worker ("N cell faults in a row") is not a lost worker to replace for ever: the
    rows it sent are stored, then the run stops, as it does in one process."""
    from flgd.training.progress import LineProgress
    from flgd.training.ray_collector import RayCollector
    from flgd.training.run import TrainingRun
    from flgd.training.settings import RunSettings

    out = tmp_path / "run"
    collector = RayCollector(1)
    run = TrainingRun(out, RunSettings(steps=5, seed=2), load_config(_config(tmp_path, 1)),
                      LineProgress(io.StringIO(), False), threads=1, collector=collector)
    try:
        run.setup()
        slot = collector.slots[0]
        report = collector.engine.ray.get(slot.actor.collect.remote(0))
        assert len(report.cycles) == 1 and not report.error
        # the worker's decision reaches the learner's double-DQN target cache, as the agent's does in one process
        [(key, version, _)] = report.decisions
        assert version == 0 and key not in run.learner._next_argmax
        report.error = "RuntimeError: 5 cell faults in a row; last: bodies 0 and 11 overlap"
        with pytest.raises(RuntimeError, match="worker 0: RuntimeError: 5 cell faults in a row"):
            run._keep(report)
        assert run.step == 1 and run.learner.updates == 1 and slot.replacements == 0
        assert key in run.learner._next_argmax
    finally:
        run.close()
    store = Store(out)
    try:
        assert store.transition_count() == 1
    finally:
        store.close()
