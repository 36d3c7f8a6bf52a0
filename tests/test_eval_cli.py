"""``flgd eval`` end to end in sim_cell: reports, pictures, run-ending rules, modes and bad input.

VPG's test cases are read from <repo>/../shared/external/vpg (never copied into the repository).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flgd.cli import main as flgd_main
from flgd.config import load_config
from flgd.evaluation.evaluator import EvalOptions, Evaluator, evaluation_config
from flgd.evaluation.metrics import run_result
from flgd.evaluation.scene_sets import named_set, scene_from_argument
from flgd.learning.networks import build_network
from flgd.learning.policy_file import save_policy
from flgd.actions import Action
from tests.fakes.agents import ScriptedAgentBase, scripted_decision
from sim_cell.scenes import load_vpg_test_case

REPO = Path(__file__).resolve().parents[1]
SIM_CONFIG = REPO / "cell_config" / "sim.yaml"
VPG = REPO.parent / "shared" / "external" / "vpg"
VPG_CASE = VPG / "test-cases" / "test-10-obj-00.txt"
needs_vpg = pytest.mark.skipif(not VPG_CASE.is_file(), reason=f"VPG's files are not at {VPG}")

ONE_CUBE = """format: flgd-scene
version: 1
objects:
  - shape: cube
    size: [0.04]
    color: [0.9, 0.2, 0.2]
    position: [0.15, 0.15, 0.02]
    rpy: [0, 0, 0]
"""


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("policy") / "p.safetensors"
    save_policy(path, build_network("fast", rotations=16, seed=3), {"training_steps": 120, "cell": "test"})
    return path


@pytest.fixture(scope="module")
def config():
    return load_config(SIM_CONFIG)


# ----------------------------------------------------------------------------- the report, end to end

@pytest.mark.slow
@needs_vpg
def test_vpg_test_case_end_to_end_gives_a_well_formed_report(policy_file, tmp_path, capsys):
    out = tmp_path / "report.json"
    qdir = tmp_path / "qmaps"
    code = flgd_main(["eval", "--config", str(SIM_CONFIG), "--policy", str(policy_file), "--scenes", str(VPG_CASE),
                      "--runs", "2", "--max-actions", "2", "--json", str(out), "--save-qmaps", str(qdir), "--quiet"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    report = json.loads(out.read_text())
    assert {"format", "version", "policy", "config", "options", "scenes", "sets", "overall", "seconds"} <= set(report)
    assert report["format"] == "flgd-eval" and report["policy"]["training_steps"] == 120
    assert report["options"] == {"runs": 2, "seed": 0, "learn": False, "grasp_only": False, "max_actions": 2,
                                 "failure_limit": 10, "workers": 0, "run_seeds": "one stream per object set"}
    [scene] = report["scenes"]
    assert scene["scene"] == "test-10-obj-00" and scene["runs"] == 2 and len(scene["run_logs"]) == 2
    for key in ("completion", "grasp_success", "grasp_success_completed", "action_efficiency", "mean_actions",
                "moves", "grasp_attempts", "grasp_successes", "ends"):
        assert key in scene
    objects = len(load_vpg_test_case(VPG_CASE).objects)
    for row in scene["run_logs"]:
        assert row["objects"] == objects
        assert 1 <= row["actions"] <= 2
        assert row["grasp_attempts"] + row["push"] + row["shift"] + row["refused"] == row["actions"]
        assert row["objects_grasped"] == row["grasp_successes"]
        assert row["objects_left"] == objects - row["objects_grasped"] - row["objects_lost"]
        assert row["end"] == "action-limit" and row["completed"] is False
    assert scene["completion"] == 0.0 and scene["action_efficiency"] is None
    assert report["overall"]["grasp_attempts"] == scene["grasp_attempts"]
    # the terminal table has the scene row and the overall row
    assert "test-10-obj-00" in captured.out and "OVERALL" in captured.out
    # a summary PNG next to the JSON and one Q-map picture per action
    summary = cv2.imread(str(out.with_suffix(".png")))
    assert summary is not None and summary.std() > 10
    pictures = sorted(qdir.rglob("*.png"))
    assert len(pictures) == sum(r["actions"] for r in scene["run_logs"])
    first = cv2.imread(str(pictures[0]))
    assert first.shape[0] > 600 and first.shape[1] > 1500
    assert len(np.unique(first.reshape(-1, 3), axis=0)) > 500


def test_named_sets_resolve_without_simulating(tmp_path):
    presets = named_set("presets")
    assert len(presets) >= 4 and all(s.path is not None and s.path.suffix == ".yaml" for s in presets)
    iso = named_set("novel-isolated")
    assert [s.count for s in iso] == [1] * len(iso) and "duck alone" in [s.name for s in iso]
    [clutter] = named_set("novel-clutter", count=7)
    assert clutter.count == 7 and "teddy" in clutter.objects
    if VPG_CASE.is_file():
        hard = named_set("vpg-hard", VPG)
        assert len(hard) == 11 and all(s.vpg_meshes is not None for s in hard)
    # VPG's own repository layout: simulation/test-cases next to objects/blocks one level up
    if VPG_CASE.is_file():
        (tmp_path / "simulation" / "test-cases").mkdir(parents=True)
        (tmp_path / "objects").mkdir()
        (tmp_path / "objects" / "blocks").symlink_to(VPG / "objects" / "blocks")
        (tmp_path / "simulation" / "test-cases" / VPG_CASE.name).write_bytes(VPG_CASE.read_bytes())
        [case] = named_set("vpg-hard", tmp_path)
        assert case.vpg_meshes == tmp_path / "objects" / "blocks"


# ----------------------------------------------------------------------------- run-ending rules

class _GraspTheEmptyCorner(ScriptedAgentBase):
    """A scripted agent that always grasps the same empty table pixel: every action fails."""

    def __init__(self, rotations: int = 16) -> None:
        super().__init__()
        self.rotations = rotations
        self.decisions = 0

    pixel = (20, 20)

    def decide(self, heightmaps, step):
        self.decisions += 1
        return scripted_decision(Action("grasp", *self.pixel, 0, self.rotations), heightmaps, rule="greedy")


class _GraspAt(_GraspTheEmptyCorner):
    """A scripted agent that always grasps at one given pixel (an oracle when an object lies there)."""

    def __init__(self, row: int, col: int, rotations: int = 16) -> None:
        super().__init__(rotations)
        self.pixel = (row, col)


def test_a_run_stops_at_the_eleventh_consecutive_failure(config, tmp_path):
    scene = tmp_path / "one-cube.yaml"
    scene.write_text(ONE_CUBE)
    spec = scene_from_argument(str(scene))
    with Evaluator(config, build_network("fast", rotations=16, seed=0), EvalOptions(runs=1)) as ev:
        ev.runner.agent = _GraspTheEmptyCorner()
        log = ev.run(spec, 1)
    assert log.end == "failures"
    assert len(log.actions) == 11 and not any(a.success for a in log.actions)
    assert log.objects == 1 and log.objects_left == 1
    assert not run_result(log).completed


def test_action_limit_and_clearing_a_scene(config, tmp_path):
    scene = tmp_path / "one-cube.yaml"
    scene.write_text(ONE_CUBE)
    spec = scene_from_argument(str(scene))
    with Evaluator(config, build_network("fast", rotations=16, seed=0), EvalOptions(runs=1, max_actions=3)) as ev:
        ev.runner.agent = _GraspTheEmptyCorner()
        limited = ev.run(spec, 1)
        assert limited.end == "action-limit" and len(limited.actions) == 3
        # an oracle grasp across the cube clears the one-object scene: a completed run of one action
        cube = ev._cells[""].object_states()[0]
        from flgd.perception import base_to_pixel

        row, col = base_to_pixel(cube.position[0], cube.position[1], ev.config.workspace)
        ev.runner.agent = _GraspAt(int(row), int(col))
        cleared = ev.run(spec, 2)
    assert cleared.end == "cleared", cleared
    assert [a.success for a in cleared.actions] == [True]
    res = run_result(cleared)
    assert res.completed and res.action_efficiency == 1.0 and cleared.objects_grasped == 1


def test_a_block_dropped_on_the_way_to_the_place_is_a_failed_grasp_in_the_report(config, tmp_path, monkeypatch):
    """The width at home says held, then the grip gives way (the block weighs 20 kg from the moment the arm
    leaves home for the place pose): it falls out beyond the workspace.  The report counts a failed grasp
    and a dropped object, and the run is not completed."""
    import pybullet as p

    from flgd.evaluation.metrics import summarize
    from flgd.perception import base_to_pixel
    from sim_cell.cell import SimCell

    execute = SimCell.execute

    def grip_gives_way(self, plan):
        if plan.plan.primitive == "place":
            for body in self._world.held:
                p.changeDynamics(body, -1, mass=20.0, physicsClientId=self._client)
        return execute(self, plan)

    monkeypatch.setattr(SimCell, "execute", grip_gives_way)
    scene = tmp_path / "one-cube.yaml"
    scene.write_text(ONE_CUBE)
    spec = scene_from_argument(str(scene))
    with Evaluator(config, build_network("fast", rotations=16, seed=0), EvalOptions(runs=1, max_actions=1)) as ev:
        cell = ev._cell_for(spec)
        cell.load_scene(spec.path)
        cube = cell.object_states()[0]
        row, col = base_to_pixel(cube.position[0], cube.position[1], ev.config.workspace)
        ev.runner.agent = _GraspAt(int(row), int(col))
        log = ev.run(spec, 1)
    assert [a.success for a in log.actions] == [False]
    assert log.objects_grasped == 0 and log.dropped_lost == 1 and not run_result(log).completed
    summary = summarize([log])
    assert summary.grasp_attempts == 1 and summary.grasp_successes == 0 and summary.objects_dropped == 1


# ----------------------------------------------------------------------------- modes

@pytest.mark.slow
def test_frozen_evaluation_is_greedy_and_grasp_only_never_moves(config, tmp_path):
    frozen = evaluation_config(config, EvalOptions())
    assert frozen.exploration.epsilon_start == frozen.exploration.epsilon_end == 0.0
    assert frozen.exploration.curriculum_steps == 0 and frozen.exploration.top_m == config.exploration.top_m
    learning = evaluation_config(config, EvalOptions(learn=True, grasp_only=True))
    assert learning.exploration.epsilon_start == config.exploration.epsilon_start
    assert learning.exploration.grasp_only and not frozen.exploration.grasp_only

    out = tmp_path / "g.json"
    code = flgd_main(["eval", "--config", str(SIM_CONFIG), "--fresh", "--scenes", "pile-20-a", "--runs", "1",
                      "--max-actions", "6", "--grasp-only", "--json", str(out), "--quiet"])
    assert code == 0
    report = json.loads(out.read_text())
    assert report["options"]["grasp_only"] is True
    assert report["overall"]["moves"] == {"push": 0, "shift": 0}
    assert report["overall"]["grasp_attempts"] + report["overall"]["refused"] == 6


def test_learn_feeds_the_replay_and_no_learn_keeps_the_weights(config, tmp_path):
    scene = tmp_path / "one-cube.yaml"
    scene.write_text(ONE_CUBE)
    spec = scene_from_argument(str(scene))
    net = build_network("fast", rotations=16, seed=0)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    with Evaluator(config, net, EvalOptions(runs=1, max_actions=2)) as ev:
        assert ev.replay is None and ev.learner is None
        frozen = ev.run(spec, 1)
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    assert all(a.kind == "grasp" or a.kind in ("push", "shift") for a in frozen.actions)

    learning = dataclasses.replace(config, finetune=dataclasses.replace(config.finetune, min_replay=0))
    with Evaluator(learning, build_network("fast", rotations=16, seed=0),
                   EvalOptions(runs=1, max_actions=2, learn=True), training_steps=40) as ev:
        log = ev.run(spec, 1)
        assert len(ev.replay) == len(log.actions) >= 1
        assert ev.agent.exploration_offset == 40   # epsilon continues from the policy's steps
        assert ev.config.learning.learning_rate == config.finetune.learning_rate  # the daemon's fine-tuning
        assert ev.gate is not None and ev.gate.champion.origin == "the evaluated policy"
        assert ev.learner.wait_idle(timeout=60)
        assert ev.learner.updates + ev.learner.failed_updates >= 1


def test_learn_paced_the_gate_takes_a_cycles_hand_over_right_after_that_cycle(config, tmp_path):
    """``flgd eval --learn`` with ``learning.wait_for_updates``: as in the daemon, the gate takes the hand-over
    a cycle's update made right after that cycle, however long the update takes, so when a challenger comes
    depends on the update count and not on thread timing."""
    import time

    from flgd.learning.learner import UpdateStats

    scene = tmp_path / "one-cube.yaml"
    scene.write_text(ONE_CUBE)
    spec = scene_from_argument(str(scene))
    cfg = dataclasses.replace(
        config, finetune=dataclasses.replace(config.finetune, min_replay=0, updates_per_action=1),
        learning=dataclasses.replace(config.learning, wait_for_updates=True),
        gate=dataclasses.replace(config.gate, handover_every=1, min_attempts=500, max_attempts=500,
                                 drop_min_attempts=500))
    other = build_network("fast", rotations=16, seed=5)
    with Evaluator(cfg, build_network("fast", rotations=16, seed=0),
                   EvalOptions(runs=1, max_actions=1, learn=True)) as ev:
        learner = ev.learner

        def slow_update() -> UpdateStats:   # far slower than the gate's bookkeeping after a cycle
            with learner._update_lock:
                time.sleep(1.5)
                learner.online.load_state_dict(other.state_dict())
                learner.updates += 1
                return UpdateStats(update=learner.updates, loss=0.0, mean_abs_td=0.0, batch_size=1, beta=0.0,
                                   seconds=1.5)

        learner.update = slow_update
        log = ev.run(spec, 1)
        challengers = [e for e in ev.gate.history() if e["kind"] == "challenger"]
    assert len(log.actions) == 1
    assert len(challengers) == 1, ev.gate.history()   # unpaced, the one cycle ends before its update does


# ----------------------------------------------------------------------------- bad input

def _eval(capsys, *args: str) -> tuple[int, str]:
    code = flgd_main(["eval", "--config", str(SIM_CONFIG), *args])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def test_bad_scenes_are_clear_errors(capsys, tmp_path, policy_file):
    code, err = _eval(capsys, "--policy", str(policy_file), "--scenes", str(tmp_path / "nope.yaml"))
    assert code == 1 and "nope.yaml: file not found" in err
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: flgd-scene\nversion: 1\nobjects:\n  - shape: cube\n    size: [banana]\n")
    code, err = _eval(capsys, "--policy", str(policy_file), "--scenes", str(bad))
    assert code == 1 and "bad.yaml" in err and "objects[0]" in err
    txt = tmp_path / "test-cases" / "broken.txt"
    txt.parent.mkdir()
    txt.write_text("0.obj 1 0 0 -0.5 0.0\n")
    code, err = _eval(capsys, "--policy", str(policy_file), "--scenes", str(txt), "--vpg-meshes", str(tmp_path))
    assert code == 1 and "broken.txt, line 1" in err and "expected 10" in err
    code, err = _eval(capsys, "--policy", str(policy_file), "--scenes", str(txt))
    assert code == 1 and "block meshes not found" in err
    code, err = _eval(capsys, "--policy", str(policy_file), "--objects", "no_such_thing_*.urdf")
    assert code == 1 and "no_such_thing_*.urdf" in err
    code, err = _eval(capsys, "--policy", str(policy_file), "--set", "vpg-hard", "--vpg", str(tmp_path / "empty"))
    assert code == 1 and "no VPG test cases" in err
    code, err = _eval(capsys, "--policy", str(policy_file))
    assert code == 1 and "nothing to evaluate" in err


def test_bad_policy_and_config_are_clear_errors(capsys, tmp_path, policy_file):
    corrupt = tmp_path / "corrupt.safetensors"
    blob = bytearray(policy_file.read_bytes())
    blob[-100] ^= 0xFF
    corrupt.write_bytes(bytes(blob))
    code, err = _eval(capsys, "--policy", str(corrupt), "--scenes", "pile-20-a")
    assert code == 1 and "corrupt.safetensors" in err and "checksum" in err
    code, err = _eval(capsys, "--policy", str(tmp_path / "missing.safetensors"), "--scenes", "pile-20-a")
    assert code == 1 and "missing.safetensors" in err and "cannot read" in err
    code = flgd_main(["eval", "--config", str(REPO / "cell_config" / "ur5e-d415.yaml"), "--policy", str(policy_file),
                      "--scenes", "pile-20-a"])
    err = capsys.readouterr().err
    assert code == 1 and "backend: sim" in err and "Traceback" not in err


def test_the_installed_command_reports_a_corrupt_policy_without_a_traceback(tmp_path):
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x80\x04this is a pickle, not a policy")
    p = subprocess.run([sys.executable, "-m", "flgd.cli", "eval", "--config", str(SIM_CONFIG), "--policy", str(junk),
                        "--scenes", "pile-20-a"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 1
    assert "flgd eval: policy file" in p.stderr and "junk.safetensors" in p.stderr
    assert "Traceback" not in p.stderr


@pytest.mark.slow
def test_bench_eval_runs_the_novel_clutter_its_own_number_of_times(tmp_path, capsys):
    from benchmarks import eval as bench_eval

    assert bench_eval.main(["--fresh", "--clutter-runs", "0"]) == 2
    assert "--clutter-runs: got 0, expected >= 1" in capsys.readouterr().err
    out = tmp_path / "bench.json"
    assert bench_eval.main(["--fresh", "--parts", "novel", "--runs", "1", "--clutter-runs", "2",
                            "--max-actions", "1", "--json", str(out)]) == 0
    reports = json.loads(out.read_text())
    isolated, clutter = reports["novel objects, isolated"], reports["novel objects, clutter of 10"]
    assert {s["runs"] for s in isolated["scenes"]} == {1} and len(isolated["scenes"]) == 8
    assert [s["runs"] for s in clutter["scenes"]] == [2]
    assert "(2 of the novel clutter)" in capsys.readouterr().out


@pytest.mark.slow
def test_bench_eval_validation_runs_20_blocks_at_each_evaluation_seed_and_pools_them(tmp_path, capsys):
    from benchmarks import eval as bench_eval

    out = tmp_path / "validation.json"
    assert bench_eval.main(["--fresh", "--parts", "validation", "--validation-runs", "1", "--max-actions", "1",
                            "--json", str(out)]) == 0
    reports = json.loads(out.read_text())
    assert list(reports) == [f"validation: 20 random blocks, seed {s}" for s in bench_eval.VALIDATION_SEEDS]
    assert [r["options"]["seed"] for r in reports.values()] == list(bench_eval.VALIDATION_SEEDS)
    assert all(r["scenes"][0]["objects"] == 20 and r["scenes"][0]["runs"] == 1 for r in reports.values())
    successes, attempts, _, counted = bench_eval.validation_pooled(reports)
    assert attempts == sum(r["overall"]["grasp_attempts"] for r in reports.values()) and counted == 4
    printed = capsys.readouterr().out
    assert f"({successes}/{attempts})" in printed and "validation 1 run(s) at each of seeds 7, 8, 9, 10" in printed
    assert bench_eval.main(["--fresh", "--parts", "validation", "--validation-runs", "0"]) == 2
    assert "--validation-runs: got 0, expected >= 1" in capsys.readouterr().err


def test_bench_eval_validation_seeds_replace_the_evaluation_seeds(tmp_path, capsys):
    """A choice that needs seeds no earlier choice has seen names them; the pooled line covers those seeds."""
    from benchmarks import eval as bench_eval

    out = tmp_path / "fresh-seeds.json"
    assert bench_eval.main(["--fresh", "--parts", "validation", "--validation-seeds", "15,16", "--validation-runs",
                            "1", "--max-actions", "1", "--json", str(out)]) == 0
    reports = json.loads(out.read_text())
    assert list(reports) == ["validation: 20 random blocks, seed 15", "validation: 20 random blocks, seed 16"]
    assert [r["options"]["seed"] for r in reports.values()] == [15, 16]
    successes, attempts, _, counted = bench_eval.validation_pooled(reports, seeds=(15, 16))
    assert counted == 2 and attempts == sum(r["overall"]["grasp_attempts"] for r in reports.values())
    printed = capsys.readouterr().out
    assert "at each of seeds 15, 16" in printed and "seeds 15, 16 pooled): grasp success" in printed
    for bad in ("", "15,x", "15,15", "-1"):
        assert bench_eval.main(["--fresh", "--parts", "validation", "--validation-seeds", bad]) == 2
        assert f"--validation-seeds: got {bad!r}" in capsys.readouterr().err


def test_eval_variant_sets_the_masks_and_must_match_the_policy_head(tmp_path, capsys):
    """--variant is the method (masks on or off, FLG or VPG head), independent of the trunk."""
    shipped = REPO / "policies" / "flg-sim.safetensors"
    code = flgd_main(["eval", "--config", str(SIM_CONFIG), "--policy", str(shipped), "--variant", "rho-fcn",
                      "--objects", "blocks", "--count", "1", "--runs", "1", "--quiet"])
    assert code == 1
    err = capsys.readouterr().err
    assert "--variant rho-fcn" in err and "'fast'" in err and "flg or dpen" in err
    out = tmp_path / "fresh.json"
    code = flgd_main(["eval", "--config", str(SIM_CONFIG), "--fresh", "--variant", "rho-fcn", "--objects", "blocks",
                      "--count", "1", "--runs", "1", "--max-actions", "1", "--quiet", "--json", str(out)])
    assert code == 0, capsys.readouterr().err
    assert json.loads(out.read_text())["policy"]["variant"] == "rho-fcn-fast"
