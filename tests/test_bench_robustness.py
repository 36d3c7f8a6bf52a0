"""Benchmarks against bad input and damaged files: ``bench eval`` refuses what would fail hours later before
anything runs and keeps finished parts; ``bench learning`` redoes an unreadable Table II evaluation instead of
crashing on it; ``bench overhead`` runs only in sim and counts the store commit once."""

from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from benchmarks import eval as bench_eval
from benchmarks import learning as bench_learning
from benchmarks import overhead as bench_overhead

REPO = Path(__file__).resolve().parents[1]
REAL_CELL_CONFIG = str(REPO / "cell_config" / "ur5e-d415.yaml")


def _report(grasp_success: float) -> dict:
    """The part of a flgd eval report that bench eval prints."""
    overall = {"counted_runs": 1, "completion": 1.0, "grasp_success": grasp_success, "grasp_successes": 9,
               "grasp_attempts": 10, "action_efficiency": 0.9, "mean_actions": 10.0,
               "moves": {"push": 1, "shift": 0}, "aborted": 0, "runs": 1}
    return {"overall": overall, "scenes": []}


@pytest.fixture
def evaluations(monkeypatch):
    """Replaces the hours of evaluation: records each part's call, returns ``results`` in turn (an exception
    is raised)."""
    calls, results = [], []

    def fake(config, network, policy, scenes, runs, seed, grasp_only, max_actions):
        calls.append(grasp_only)
        result = results.pop(0)
        if isinstance(result, Exception):
            raise result
        return result

    monkeypatch.setattr(bench_eval, "_evaluate", fake)
    return SimpleNamespace(calls=calls, results=results)


# ------------------------------------------------------------------------------------------ bench eval

@pytest.mark.parametrize("where", ["under a file", "a directory"])
def test_bench_eval_refuses_an_unwritable_json_before_anything_runs(tmp_path, capsys, evaluations, where):
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    target = tmp_path / ("afile/report.json" if where == "under a file" else "adir")
    assert bench_eval.main(["--fresh", "--parts", "presets", "--json", str(target)]) == 2
    err = capsys.readouterr().err
    assert f"--json {target}: " in err and "Traceback" not in err
    assert evaluations.calls == []


@pytest.mark.parametrize("argv, problem", [
    (["--config", REAL_CELL_CONFIG], "backend 'ur5e'"),  # raised by the Evaluator: it runs only in sim
    (["--max-actions", "0"], "--max-actions: got 0, expected >= 1"),
])
def test_bench_eval_refuses_what_the_evaluator_would_refuse_before_anything_runs(tmp_path, capsys, evaluations,
                                                                                argv, problem):
    assert bench_eval.main(["--fresh", "--parts", "presets", "--json", str(tmp_path / "r.json"), *argv]) == 2
    err = capsys.readouterr().err
    assert problem in err and "Traceback" not in err
    assert evaluations.calls == [] and not (tmp_path / "r.json").exists()


def test_bench_eval_writes_the_json_after_each_part_and_keeps_them_when_one_fails(tmp_path, capsys, evaluations):
    from flgd.evaluation.evaluator import EvaluationError

    out = tmp_path / "not" / "yet" / "r.json"  # created up front, as flgd eval does
    evaluations.results += [_report(0.5), EvaluationError("cannot create the simulated cell: boom (injected)")]
    assert bench_eval.main(["--fresh", "--parts", "presets", "--json", str(out)]) == 1
    err = capsys.readouterr().err
    assert "presets, grasp-and-move: cannot create the simulated cell" in err and str(out) in err
    assert json.loads(out.read_text()) == {"presets, grasp-only": _report(0.5)}
    assert sorted(p.name for p in out.parent.iterdir()) == ["r.json"]  # no temporary left

    evaluations.results += [_report(0.5), _report(0.8)]
    assert bench_eval.main(["--fresh", "--parts", "presets", "--json", str(out)]) == 0
    assert json.loads(out.read_text()) == {"presets, grasp-only": _report(0.5),
                                           "presets, grasp-and-move": _report(0.8)}
    assert "grasp-and-move 80.0 % vs grasp-only 50.0 %" in capsys.readouterr().out


# -------------------------------------------------------------------------------------- bench learning

def _finished_run(root: Path, name: str, checkpoint: str = "checkpoint-0000000010") -> Path:
    d = root / name
    (d / "checkpoints").mkdir(parents=True)
    (d / "checkpoints" / f"{checkpoint}.safetensors").write_bytes(b"weights")
    (d / "run.json").write_text(json.dumps({"settings": {"variant": "flg", "seed": 0}, "status": "finished"}))
    return d


def test_an_unreadable_table2_json_is_reported_as_missing_not_a_crash(tmp_path, capsys):
    d = _finished_run(tmp_path, "flg-s0")
    cut = d / "table2-checkpoint-0000000010-r2.json"
    cut.write_text('{"overall": {"completion": 1.0, "grasp_su')  # a bench interrupted while it was written
    assert bench_learning.read_table2(cut)[0] is None
    assert bench_learning.main(["--root", str(tmp_path), "--report-only", "--variants", "flg", "--seeds", "0"]) == 0
    report = (tmp_path / "report.md").read_text()
    assert f"| Grasping-Moving | 0 | {cut.name} unreadable (JSONDecodeError" in report
    assert "will be redone" in report
    assert json.loads((tmp_path / "report.json").read_text())["table2"] == []


def test_an_unreadable_table2_json_is_evaluated_again_and_replaced_whole(tmp_path, monkeypatch):
    d = _finished_run(tmp_path, "flg-s0")
    out = d / "table2-checkpoint-0000000010-r1.json"
    out.write_text('{"overall": {"compl')
    commands = []

    def fake_eval(cmd, **_kw):  # flgd eval as a subprocess: writes the --json it is given
        commands.append(cmd)
        Path(cmd[cmd.index("--json") + 1]).write_text(json.dumps(_report(0.7)) if len(commands) == 1 else "{")
        return SimpleNamespace(returncode=0 if len(commands) == 1 else 1)

    monkeypatch.setattr(bench_learning.subprocess, "run", fake_eval)
    spec = bench_learning.RunSpec("flg-s0", "flg", 0)
    results = {"flg-s0": bench_learning.RunResult(spec, d, [], 5, 5, "finished")}
    bench_learning.evaluate_table2(results, tmp_path, 1, [0])
    assert len(commands) == 1
    assert commands[0][commands[0].index("--json") + 1] != str(out)  # never written in place
    assert commands[0][commands[0].index("--png") + 1] == str(out.with_suffix(".png"))
    assert bench_learning.read_table2(out) == (_report(0.7)["overall"], "")
    bench_learning.evaluate_table2(results, tmp_path, 1, [0])  # readable now: not evaluated again
    assert len(commands) == 1

    # an evaluation that fails leaves no table2 file behind that would count as done
    out.unlink()
    bench_learning.evaluate_table2(results, tmp_path, 1, [0])
    assert len(commands) == 2 and not out.exists()
    assert sorted(p.name for p in d.iterdir()) == ["checkpoints", "run.json"]


def test_bench_learning_names_a_damaged_run_json_and_stops(tmp_path, capsys):
    d = _finished_run(tmp_path, "flg-s0")
    (d / "run.json").write_text('{"settings": {"variant": "fl')
    assert bench_learning.main(["--root", str(tmp_path), "--report-only", "--variants", "flg", "--seeds", "0"]) == 2
    err = capsys.readouterr().err
    assert f"{d / 'run.json'}: not valid JSON" in err and "Traceback" not in err
    assert not (tmp_path / "report.md").exists()


# -------------------------------------------------------------------------------------- bench overhead

def test_bench_overhead_refuses_a_real_cell_config(capsys, monkeypatch):
    def never(*_a, **_kw):
        raise AssertionError("a cell was built from a real-cell config")

    monkeypatch.setattr(bench_overhead, "_one_run", never)
    assert bench_overhead.main(["--config", REAL_CELL_CONFIG, "--runs", "1", "--cycles", "1"]) == 2
    assert "expected 'sim'" in capsys.readouterr().err


class SlowStore:
    """Stands for the SQLite store with a slow disk: each commit takes 0.2 s."""

    def __init__(self):
        self.ids = 0

    def commit_cycle(self, row, transition):
        time.sleep(0.2)
        self.ids += 1
        return self.ids

    def note_store_time(self, step, seconds):
        pass

    def forget_last_state(self):
        pass

    def check_space(self):
        pass

    def record_intent(self, row):
        pass

    def record_event(self, kind, message):
        pass


def test_controller_time_counts_the_store_commit_once():
    """The controller time of a cycle can never exceed its wall time less the motions, whatever the store
    takes (it did by the store time when the commit was added to a duration that already held it)."""
    import torch

    from flgd.cell import make_cell
    from flgd.config import load_config
    from flgd.cycle import CycleRunner
    from flgd.learning.agent import Agent
    from flgd.learning.networks import build_network

    torch.set_num_threads(1)
    cfg = load_config(REPO / "cell_config" / "sim.yaml")
    cell = make_cell(cfg, "sim")
    try:
        runner = CycleRunner(cfg, cell, Agent(cfg, build_network("fast", cfg.learning.rotations, seed=0)),
                             store=SlowStore())
        for _ in range(3):
            t0 = time.perf_counter()
            rec = runner.run_once()
            wall = time.perf_counter() - t0
            if rec.outcome != "empty":
                break
    finally:
        cell.close()
    assert rec.outcome in ("executed", "refused") and rec.timings["store"] >= 0.2
    controller = bench_overhead.controller_time(rec)
    assert rec.timings["store"] <= controller <= wall - rec.timings.get("execute", 0.0)
