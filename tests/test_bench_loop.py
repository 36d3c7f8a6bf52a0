"""``flgd bench loop``: variants parsed and checked before anything runs; a tiny run's report; resuming."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.loop import parse_variant, pooled, variant_config

REPO = Path(__file__).resolve().parents[1]


def test_variants_are_parsed_with_yaml_values_and_bad_ones_refused():
    assert parse_variant("base:") == ("base", {})
    name, settings = parse_variant("m:exploration.failure_memory=false,rewards.min_object_area=36,camera.depth_fill=none")
    assert name == "m" and settings == {"exploration.failure_memory": False, "rewards.min_object_area": 36,
                                        "camera.depth_fill": "none"}
    for bad in ("no colon=1", ":x.y=1", "m:nodot=1", "m:x.y"):
        with pytest.raises(ValueError):
            parse_variant(bad)


def test_a_variant_is_checked_as_a_config_is():
    cell = REPO / "cell_config" / "sim.yaml"
    assert variant_config(cell, {"rewards.min_object_area": 0}).rewards.min_object_area == 0
    with pytest.raises(ValueError, match="no such config key"):
        variant_config(cell, {"rewards.min_object_aera": 1})
    with pytest.raises(ValueError, match="min_object_area"):
        variant_config(cell, {"rewards.min_object_area": -1})


def test_pooled_numbers_leave_aborted_runs_out():
    rows = [{"end": "cleared", "grasp_attempts": 4, "grasp_successes": 3, "actions": 6, "completed": True,
             "longest_failure_streak": 2, "streak_actions": 0, "objects_lost": 1, "objects_dropped": 1},
            {"end": "stuck", "grasp_attempts": 2, "grasp_successes": 1, "actions": 16, "completed": False,
             "longest_failure_streak": 7, "streak_actions": 7, "objects_lost": 2, "objects_dropped": 0},
            {"end": "unstable", "grasp_attempts": 9, "grasp_successes": 0, "actions": 9, "completed": False,
             "longest_failure_streak": 9, "streak_actions": 9, "objects_lost": 5, "objects_dropped": 5}]
    got = pooled(rows)
    assert got["counted"] == 2 and got["grasp_success"] == 4 / 6 and got["picks_per_action"] == 4 / 22
    assert got["longest_failure_streak"] == 7 and got["streak_actions"] == 7 and got["stuck_runs"] == 1
    assert got["completion"] == 0.5
    assert got["objects_lost"] == 3 and got["objects_dropped"] == 1
    # rows kept in --root from before drops were counted: the drops are unknown, not zero
    old = [{k: v for k, v in r.items() if k != "objects_dropped"} for r in rows]
    assert pooled(old)["objects_dropped"] is None and pooled(old)["objects_lost"] == 3


@pytest.mark.slow
def test_a_tiny_run_reports_every_variant_and_a_second_call_reuses_it(tmp_path):
    cmd = [sys.executable, "-m", "flgd.cli", "bench", "loop", "--root", str(tmp_path), "--seeds", "5", "--runs", "1",
           "--count", "2", "--cells", str(REPO / "cell_config" / "sim.yaml"),
           "--variants", "paper:exploration.failure_memory=false,rewards.min_object_area=0", "shipped:",
           "--out", str(tmp_path / "out.json")]
    r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    out = json.loads((tmp_path / "out.json").read_text())
    assert set(out["variants"]) == {"paper", "shipped"}
    for v in out["variants"].values():
        cell = v["cells"]["sim"]
        assert cell["runs"] == 1 and cell["grasp_attempts"] >= cell["grasp_successes"]
        assert set(v["mean"]) >= {"grasp_success", "picks_per_action", "longest_failure_streak", "stuck_runs"}
    done = sorted(p.name for p in tmp_path.glob("*--sim--5.json"))
    assert done == ["paper--sim--5.json", "shipped--sim--5.json"]
    again = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "seed 5:" not in again.stderr   # nothing ran again
    assert json.loads((tmp_path / "out.json").read_text())["variants"] == out["variants"]


def test_a_bad_variant_is_one_line_before_anything_runs(tmp_path):
    r = subprocess.run([sys.executable, "-m", "flgd.cli", "bench", "loop", "--root", str(tmp_path),
                        "--variants", "x:rewards.min_object_area=-5"], cwd=REPO, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "min_object_area" in r.stderr and "Traceback" not in r.stderr
    assert list(tmp_path.iterdir()) == []
