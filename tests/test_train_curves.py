"""Learning-curve statistics and the learning bench's report, on hand-made action logs."""

from __future__ import annotations

import csv
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from benchmarks import learning as bench
from flgd.learning.agent import RULES
from flgd.training.actions_csv import COLUMNS
from flgd.training.curve import grasp_series, move_fraction, rolling_success, spread, steps_to_threshold, success_by_rule


def _rows(pattern: list[str]) -> list[dict]:
    """'G' = successful grasp, 'g' = failed grasp, 'p' = push, 'r' = refused grasp; one step each."""
    rows = []
    for step, ch in enumerate(pattern):
        if ch == "p":
            rows.append({"step": str(step), "outcome": "executed", "primitive": "push", "success": ""})
        else:
            rows.append({"step": str(step), "outcome": "refused" if ch == "r" else "executed",
                         "primitive": "grasp", "success": "1" if ch == "G" else "0"})
    return rows


def test_rolling_success_counts_full_windows_of_executed_grasps():
    rows = _rows(list("GgpGrG"))
    s = grasp_series(rows)
    assert s.steps.tolist() == [0, 1, 3, 5] and s.success.tolist() == [1, 0, 1, 1] and s.last_step == 5
    steps, rate = rolling_success(s, 2)
    assert steps.tolist() == [1, 3, 5] and rate.tolist() == [0.5, 0.5, 1.0]
    steps, rate = rolling_success(s, 2, full_only=False)
    assert steps.tolist() == [0, 1, 3, 5] and rate.tolist() == [1.0, 0.5, 0.5, 1.0]
    assert len(rolling_success(s, 10)[0]) == 0


def test_steps_to_threshold_is_the_first_full_window_at_or_above():
    # 10 failures, then successes: a window of 10 grasps reaches 80 % at the 8th success
    rows = _rows(["g"] * 10 + ["G"] * 20)
    s = grasp_series(rows)
    assert steps_to_threshold(s, 0.8, 10) == 18   # step 17 is the 18th action
    assert steps_to_threshold(s, 0.9, 10) == 19
    assert steps_to_threshold(s, 1.0, 10) == 20
    # early luck does not count: 3 of 3 at the start, window 10 not yet full
    lucky = grasp_series(_rows(["G"] * 3 + ["g"] * 7))
    assert steps_to_threshold(lucky, 0.9, 10) is None
    # moves between grasps stretch the step count, not the window
    spaced = grasp_series(_rows(["G", "p"] * 10))
    assert steps_to_threshold(spaced, 0.9, 10) == 19


def test_move_fraction_per_window_of_actions():
    steps, frac = move_fraction(_rows(list("GpGpGG")), 4)
    assert steps.tolist() == [3, 4, 5] and frac.tolist() == [0.5, 0.5, 0.25]


def test_success_by_rule_splits_greedy_from_random_grasps_over_the_last_steps():
    rows = _rows(["g", "g", "G", "p", "G", "g", "r", "G"])
    for r, rule in zip(rows, ["epsilon", "greedy", "greedy", "greedy", "epsilon", "greedy", "greedy", "greedy"]):
        r["rule"] = rule
    assert success_by_rule(rows) == {"epsilon": (1, 2), "greedy": (2, 4)}   # the push and the refusal left out
    assert success_by_rule(rows, last_steps=4) == {"epsilon": (1, 1), "greedy": (1, 2)}  # steps 4..7
    del rows[0]["rule"]
    assert success_by_rule(rows)["unknown"] == (0, 1)


def test_spread_ranks_never_reached_last():
    s = spread([400, 300, 500])
    assert (s.median, s.low, s.high, s.reached, s.total) == (400, 300, 500, 3, 3)
    s = spread([400, None, 300])
    assert (s.median, s.low, s.high, s.reached) == (400, 300, np.inf, 2)
    assert "2/3 runs reached" in s.text()
    s = spread([None, None, 350])
    assert s.median == np.inf and "not reached" in s.text().split("[")[0]
    assert spread([None]).text() == "not reached (0/1)"


def _write_run(root: Path, name: str, pattern: list[str], status: str) -> None:
    d = root / name
    d.mkdir(parents=True)
    (d / "run.json").write_text(json.dumps({"settings": {}, "status": status}))  # a run.json always has settings
    with (d / "actions.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in _rows(pattern):
            w.writerow({k: r.get(k, "") for k in COLUMNS})


def test_bench_report_medians_over_seeds_and_marks_unfinished_runs(tmp_path):
    # window 200 needs 200 grasps: pad with failures before a run of successes
    _write_run(tmp_path, "flg-s0", ["g"] * 200 + ["G"] * 200, "finished")    # 80 % at 360, 90 % at 380
    _write_run(tmp_path, "flg-s1", ["g"] * 100 + ["G"] * 300, "finished")    # 80 % at 260, 90 % at 280
    _write_run(tmp_path, "flg-s2", ["g"] * 300 + ["G"] * 100, "finished")    # never
    _write_run(tmp_path, "dpen-s0", ["g"] * 150, "running")                  # unfinished
    specs = bench.run_specs(["flg", "dpen"], [0, 1, 2], table2=False)
    results = {s.name: r for s in specs if (r := bench.read_run(tmp_path / s.name, s, 400)) is not None}
    assert results["flg-s0"].complete and not results["dpen-s0"].complete
    out = bench.report(results, ["flg", "dpen"], [0, 1, 2], tmp_path, steps=400, objects=10, eval_runs=2)
    w200 = out["variants"]["flg"]["window_200"]
    assert w200["per_seed"]["flg-s0"]["0.8"] == 360 and w200["per_seed"]["flg-s1"]["0.9"] == 280
    assert w200["per_seed"]["flg-s2"]["0.8"] is None
    assert w200["steps_to_80"]["median"] == 360 and w200["steps_to_80"]["low"] == 260
    assert w200["steps_to_80"]["reached"] == 2 and w200["steps_to_80"]["total"] == 3
    text = (tmp_path / "report.md").read_text()
    assert "not yet (at 150)*" in text and "s2: > 400 / > 400" in text
    # hand-made logs carry no rule: their grasps are counted as such, not as greedy
    assert "| flg-s0 | - | - |" in text
    assert out["variants"]["flg"]["runs"]["flg-s0"]["grasps_by_rule_last_steps"]["unknown"] == {
        "successes": 200, "attempts": 200}
    assert (tmp_path / "curves.png").read_bytes()[:4] == b"\x89PNG"
    assert json.loads((tmp_path / "report.json").read_text())["variants"]["dpen"]["runs"]["dpen-s0"]["step"] == 150


def test_bench_report_names_each_runs_starting_weights_and_learner_settings(tmp_path):
    _write_run(tmp_path, "flg-s0", ["G"] * 10, "finished")
    _write_run(tmp_path, "flg-s1", ["G"] * 10, "finished")
    (tmp_path / "flg-s0" / "config.yaml").write_text(
        "learning: {init_trunk: /x/trunk.safetensors, learning_rate: 0.0005, updates_per_action: 6, batch_size: 4}\n")
    (tmp_path / "flg-s1" / "config.yaml").write_text(
        "learning: {init_trunk: '', learning_rate: 0.0001, updates_per_action: 1, batch_size: 4}\n")
    specs = bench.run_specs(["flg"], [0, 1], table2=False)
    results = {s.name: bench.read_run(tmp_path / s.name, s, 10) for s in specs}
    out = bench.report(results, ["flg"], [0, 1], tmp_path, steps=10, objects=10, eval_runs=1)
    text = (tmp_path / "report.md").read_text()
    assert ("learner settings (flg-s0): start trunk /x/trunk.safetensors; lr 0.0005, 6 updates/action, batch 4"
            in text)
    assert "learner settings (flg-s1): start random initial weights; lr 0.0001, 1 updates/action" in text
    assert len(out["settings"]) == 2


def test_bench_commands_use_one_thread_and_the_run_directory(tmp_path):
    spec = bench.run_specs(["rho-fcn"], [3], table2=True)
    assert [s.name for s in spec] == ["rho-fcn-s3"]  # Table II runs need the flg variant
    spec = bench.run_specs(["flg"], [1], table2=True)
    assert [s.name for s in spec] == ["flg-s1", "flg-grasponly-s1"]
    cmd = spec[1].args(Path("c.yaml"), 10, 700, tmp_path / "x")
    assert cmd[cmd.index("--threads") + 1] == "1" and "--grasp-only" in cmd
    assert cmd[cmd.index("--steps") + 1] == "700" and cmd[cmd.index("--out") + 1] == str(tmp_path / "x")


@pytest.mark.slow
def test_bench_trains_skips_finished_runs_and_continues_longer_ones(tmp_path, capsys):
    common = ["--root", str(tmp_path), "--variants", "flg", "--seeds", "0", "--no-table2", "--jobs", "1"]
    assert bench.main(common + ["--steps", "2"]) == 0
    out = capsys.readouterr().out
    assert "flg-s0: training to 2 steps" in out and "flg-s0: exit code 0" in out
    assert json.loads((tmp_path / "flg-s0" / "run.json").read_text())["status"] == "finished"
    assert bench.main(common + ["--steps", "2"]) == 0
    assert "flg-s0: finished (2 steps), skipped" in capsys.readouterr().out
    assert bench.main(common + ["--steps", "3"]) == 0        # a longer target continues the same run
    rows = (tmp_path / "flg-s0" / "actions.csv").read_text().splitlines()
    assert len(rows) == 1 + 3
    report = json.loads((tmp_path / "report.json").read_text())
    run = report["variants"]["flg"]["runs"]["flg-s0"]
    assert {k: run[k] for k in ("step", "status", "complete")} == {"step": 3, "status": "finished", "complete": True}
    # a real run's log carries its decision rules; every grasp is counted under one of them
    by_rule = run.get("grasps_by_rule_last_steps", {})
    logged = list(csv.DictReader((tmp_path / "flg-s0" / "actions.csv").open()))
    assert set(by_rule) <= set(RULES) and sum(v["attempts"] for v in by_rule.values()) == sum(
        1 for r in logged if r["primitive"] == "grasp" and r["outcome"] == "executed" and r["success"] != "")


class _SleepingRun(bench.RunSpec):
    """A run whose 'training' is a child process that sleeps until it gets SIGINT (stands in for flgd train)."""

    def args(self, config, objects, steps, out, workers=0):
        return [sys.executable, "-c",
                "import pathlib, sys, time\n"
                f"pathlib.Path({str(out)!r}, 'started').write_text('yes')\n"
                "try:\n    time.sleep(600)\nexcept KeyboardInterrupt:\n    sys.exit(130)\n"]


@pytest.mark.slow
def test_ctrl_c_stops_the_bench_runs_and_reports_the_interruption(tmp_path):
    specs = [_SleepingRun("a-s0", "flg", 0), _SleepingRun("b-s0", "dpen", 0), _SleepingRun("c-s0", "rho-fcn", 0)]
    interrupted_at = []

    def press_ctrl_c_once_both_run() -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not all((tmp_path / n / "started").exists() for n in ("a-s0", "b-s0")):
            time.sleep(0.05)
        interrupted_at.append(time.monotonic())
        os.kill(os.getpid(), signal.SIGINT)

    handler_before = signal.getsignal(signal.SIGINT)
    presser = threading.Thread(target=press_ctrl_c_once_both_run, daemon=True)
    presser.start()
    finished = bench.train_all(specs, tmp_path, tmp_path / "cfg.yaml", objects=3, steps=10, jobs=2)
    presser.join()
    assert finished is False
    assert time.monotonic() - interrupted_at[0] < 300, "the children were stopped, not waited out (they sleep 600 s)"
    assert (tmp_path / "a-s0" / "started").exists() and (tmp_path / "b-s0" / "started").exists()
    assert not (tmp_path / "c-s0").exists(), "no new run starts after Ctrl-C"
    assert signal.getsignal(signal.SIGINT) is handler_before, "the bench's own handler is removed again"
