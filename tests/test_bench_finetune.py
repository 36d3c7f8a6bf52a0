"""``flgd bench finetune``: the rows' configs, the report's arithmetic, and a tiny real run end to end."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import yaml

from benchmarks import finetune

REPO = Path(__file__).resolve().parents[1]


def test_actions_to_level_counts_actions_until_the_last_100_grasps_reach_it():
    outcomes = [0] * 50 + [1] * 200
    steps = [2 * i for i in range(len(outcomes))]          # a move between every two grasps
    # the window of the last 100 grasps first holds 80 successes at grasp index 129 (grasps 30..129)
    assert finetune.actions_to_level(outcomes, steps, 0.8) == steps[129] + 1
    assert finetune.actions_to_level(outcomes, steps, 0.9) == steps[139] + 1
    assert finetune.actions_to_level([1] * 99, list(range(99)), 0.5) is None   # fewer than 100 grasps
    assert finetune.actions_to_level([1, 0] * 100, list(range(200)), 0.9) is None


def test_median_ranks_never_above_every_number():
    assert finetune._median_or_none([300, None, 500]) == 500
    assert finetune._median_or_none([300, None, None]) is None
    assert finetune._median_or_none([300, 400, 600, None]) == 500
    assert finetune._median_or_none([300, None, 600, None]) is None


@pytest.mark.parametrize("item, needle", [
    ("finetune.learning_rate", "expected KEY=VALUE"),
    ("sim.depth_noise_std=0.01", "only learner settings"),
    ("=3", "expected KEY=VALUE"),
])
def test_bad_settings_are_refused(item, needle):
    with pytest.raises(ValueError, match=needle):
        finetune.parse_settings([item])


def test_row_configs(tmp_path):
    settings = finetune.parse_settings(["finetune.learning_rate=3e-5", "gate.share=0.3"])
    frozen = finetune.row_config("shifted-frozen", 5, tmp_path / "a", finetune.SHIFTED_CONFIG, settings)
    gate = finetune.row_config("shifted-gate", 5, tmp_path / "b", finetune.SHIFTED_CONFIG, settings)
    scratch = finetune.row_config("shifted-scratch", 5, tmp_path / "c", finetune.SHIFTED_CONFIG, settings)
    train = finetune.row_config("train-gate", 5, tmp_path / "d", finetune.SHIFTED_CONFIG, {})
    for cfg in (frozen, gate, scratch, train):
        assert cfg.learning.wait_for_updates and cfg.sim.seed == 5 and cfg.learning.seed == 5
    assert frozen.finetune.updates_per_action == 0 and frozen.finetune.learning_rate != 3e-5   # no settings
    assert gate.finetune.learning_rate == 3e-5 and gate.gate.share == 0.3 and gate.gate.enabled
    assert scratch.policy == "" and not scratch.gate.enabled
    assert gate.sim.camera_pose_error.position != (0.0, 0.0, 0.0)        # the second cell
    assert train.sim.camera_pose_error.position == (0.0, 0.0, 0.0)       # the training cell
    assert Path(gate.policy) == Path(train.policy)
    assert finetune.run_name("shifted-frozen", 5, "lr3") == "shifted-frozen-s5"
    assert finetune.run_name("shifted-gate", 5, "lr3") == "lr3-shifted-gate-s5"


def test_a_resumed_run_continues_with_new_seeds_instead_of_replaying_its_start(tmp_path):
    """A cell rebuilt from the run's seed would deal the run's first scenes again (measured: actions 300-359 of a
    run extended from 300 to 1,000 repeated actions 0-59 outcome for outcome)."""
    from flgd.wiring import continuing_config

    cfg = finetune.row_config("shifted-frozen", 100, tmp_path, finetune.SHIFTED_CONFIG, {})
    assert continuing_config(cfg, 0) is cfg
    later = continuing_config(cfg, 300)
    assert later.sim.seed != cfg.sim.seed and later.learning.seed != cfg.learning.seed
    assert later.sim.seed == continuing_config(cfg, 300).sim.seed           # the same continuation every time
    assert continuing_config(cfg, 301).sim.seed != later.sim.seed
    assert later.sim.seed >= 0 and later.finetune == cfg.finetune


def test_learning_rows_bring_the_frozen_row_of_their_cell():
    assert finetune.with_references(["shifted-gate"]) == ["shifted-frozen", "shifted-gate"]
    assert finetune.with_references(["train-gate", "shifted-scratch"]) == [
        "shifted-frozen", "shifted-scratch", "train-frozen", "train-gate"]
    assert finetune.with_references(["train-frozen"]) == ["train-frozen"]


def test_a_setting_out_of_range_is_one_line_before_anything_runs(tmp_path):
    r = subprocess.run([sys.executable, "-m", "flgd.cli", "bench", "finetune", "--root", str(tmp_path), "--tag", "x",
                        "--set", "finetune.learning_rate=-1", "--actions", "2", "--seeds", "0"],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "finetune.learning_rate: got -1" in r.stderr
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
def test_tiny_run_writes_a_well_formed_report_and_png(tmp_path):
    out = tmp_path / "report.json"
    rows = ["shifted-frozen", "shifted-gate", "shifted-scratch"]
    r = subprocess.run([sys.executable, "-m", "flgd.cli", "bench", "finetune", "--root", str(tmp_path / "runs"),
                        "--actions", "3", "--seeds", "0", "--rows", *rows, "--jobs", "2", "--out", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    report = json.loads(out.read_text())
    assert report["actions"] == 3 and report["seeds"] == [0] and list(report["rows"]) == rows
    for name in rows:
        row = report["rows"][name]
        assert row["missing"] == []
        seed = row["per_seed"]["0"]
        assert 0 <= seed["grasp_attempts"] <= 3 and len(seed["windows"]) == (1 if seed["grasp_attempts"] else 0)
        assert seed["actions_to_80"] is None            # fewer than 100 grasps
        # what each run actually ran with
        cfg = yaml.safe_load((tmp_path / "runs" / f"{name}-s0" / "config.yaml").read_text())
        assert cfg["learning"]["wait_for_updates"] is True
        assert cfg["sim"]["camera_pose_error"]["position"] == [0.010, -0.008, 0.004]
    assert (yaml.safe_load((tmp_path / "runs" / "shifted-scratch-s0" / "config.yaml").read_text())["policy"]
            == "")
    img = cv2.imread(str(out.with_suffix(".png")))
    assert img is not None and img.shape == (400, 720, 3)
    # a second call with the runs complete starts nothing and reports the same
    again = subprocess.run([sys.executable, "-m", "flgd.cli", "bench", "finetune", "--root", str(tmp_path / "runs"),
                            "--actions", "3", "--seeds", "0", "--rows", *rows, "--out", str(out)],
                           cwd=REPO, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "started" not in again.stdout
    assert json.loads(out.read_text())["rows"] == report["rows"]


def test_the_second_cell_differs_from_the_training_cell_only_in_its_sim_section():
    """Its learner, gate, robot and safety settings are the training cell's, so that a row on either cell measures
    the same daemon; only what the simulated world looks and behaves like differs."""
    from flgd.config import config_to_dict, load_config

    train = config_to_dict(load_config(finetune.TRAIN_CONFIG))
    shifted = config_to_dict(load_config(finetune.SHIFTED_CONFIG))
    differs = sorted(k for k in train if train[k] != shifted[k])
    assert differs == ["name", "sim", "state_dir"]
    assert sorted(k for k in train["sim"] if train["sim"][k] != shifted["sim"][k]) == [
        "camera_pose_error", "depth_dropout", "depth_edge_holes", "depth_noise_std", "light_ambient", "light_diffuse",
        "object_color_shift", "object_friction", "object_mass_scale", "object_set", "table_shade"]


def test_the_worst_window_of_a_policy_that_changed_nothing_is_below_zero_by_chance_and_less_so_with_more_seeds():
    """The issue's "no window more than 3 points below frozen" is read against this band: with 3 seeds of nine
    windows an unchanged policy's worst window is several points below frozen, more so when the frozen runs'
    windows spread more."""
    steady = [[0.74] * 9, [0.73, 0.75] * 4 + [0.74], [0.72, 0.76] * 4 + [0.74]]
    spread = [[0.60, 0.88] * 4 + [0.74], [0.66, 0.82] * 4 + [0.74], [0.70, 0.78] * 4 + [0.74]]
    narrow = finetune.null_worst_window(steady, seeds=3, windows=9, trials=4000)
    wide = finetune.null_worst_window(spread, seeds=3, windows=9, trials=4000)
    many = finetune.null_worst_window(spread, seeds=30, windows=9, trials=2000)
    assert -0.04 <= narrow["median"] < 0.0
    assert wide["median"] < narrow["median"] - 0.03 and wide["p05"] < wide["median"]
    assert wide["p_at_least_minus_3"] < 0.3
    assert wide["median"] < many["median"]
    assert finetune.null_worst_window([], seeds=3, windows=9) == {}


def test_loop_counts_read_picks_per_action_streaks_and_stuck_events_from_a_runs_store(tmp_path):
    from benchmarks._daemon_runs import action_rows, loop_counts
    from flgd.store import Store

    store = Store(tmp_path)
    # grasp ok, 6 failed actions (a push that changed nothing among them), a push that moved the clutter, a pick
    kinds = [("grasp", 1.0), *[("grasp", 0.0)] * 4, ("push", 0.0), ("grasp", 0.0), ("push", 0.5), ("grasp", 1.0)]
    for step, (prim, reward) in enumerate(kinds):
        store.commit_cycle({"step": step, "time": float(step), "backend": "sim", "outcome": "executed",
                            "primitive": prim, "kind": prim, "row": 1, "col": 1, "rotation": 0, "reward": reward,
                            "success": int(reward > 0) if prim == "grasp" else None, "rule": "greedy",
                            "done": 0, "duration": 1.0}, None)
    store.record_event("stuck", "stuck after step 6: ...; the scene was laid out anew")
    store.close()
    got = loop_counts(tmp_path, action_rows(tmp_path, 100))
    assert got == {"picks_per_action": 2 / 9, "longest_failure_streak": 6, "streak_actions": 6, "stuck": 1}
