"""``flgd bench emulated``'s figures, from constructed action logs."""

from __future__ import annotations

import pytest

from benchmarks.emulated import _policy_summary


def _row(step: int, success: int | None, duration: float, t_execute: float, cell_time: float | None,
         primitive: str = "grasp", outcome: str = "executed", gripper_time: float | None = None) -> dict:
    return {"step": step, "outcome": outcome, "primitive": primitive, "success": success, "duration": duration,
            "t_execute": t_execute, "cell_time": cell_time, "gripper_time": gripper_time,
            **{p: 0.01 for p in ("t_capture", "t_perceive", "t_decide", "t_plan", "t_judge", "t_store")}}


def test_picks_per_hour_on_the_cells_clock_count_the_arms_time_not_the_busy_pcs():
    """The emulator ran at half speed: each 10 s motion took 20 s of the wall clock.  On the cell's clock a cycle
    is the controller's 0.5 s plus the arm's 10 s; a push counts its time but is no pick."""
    rows = [_row(0, 1, 20.5, 20.0, 10.0, gripper_time=1.0), _row(1, 0, 20.5, 20.0, 10.0, gripper_time=1.5),
            _row(2, 1, 20.5, 20.0, 10.0, gripper_time=1.0), _row(3, None, 20.5, 20.0, 10.0, primitive="push")]
    s = _policy_summary(rows, 4)
    assert s["picks"] == 2 and s["grasp_success"] == pytest.approx(2 / 3)
    assert s["median_cycle_s"] == pytest.approx(20.5) and s["median_cycle_cell_clock_s"] == pytest.approx(10.5)
    assert s["picks_per_hour_wall"] == pytest.approx(2 * 3600 / 82.0)
    assert s["picks_per_hour_cell_clock"] == pytest.approx(2 * 3600 / 42.0)
    assert (s["median_motion_s"], s["median_gripper_s"]) == pytest.approx((9.0, 1.0))   # the push: no gripper
    assert s["median_waiting_s"] == pytest.approx(0.5)


def test_the_share_of_decision_time_hidden_behind_the_place_is_reported():
    rows = [_row(0, 1, 10.5, 10.0, 10.0), _row(1, 1, 10.5, 10.0, 10.0), _row(2, 1, 10.5, 10.0, 10.0)]
    for row, hidden in zip(rows, (None, 0.01, 0.005)):   # each decision 0.01 s: none, all and half of it hidden
        row["decide_hidden"] = hidden
    assert _policy_summary(rows, 3)["decide_hidden_share"] == pytest.approx(0.5)


def test_a_log_written_before_the_cell_clock_counts_its_wall_time():
    rows = [_row(0, 1, 12.0, 11.0, None), _row(1, 1, 12.0, 11.0, 9.0)]
    s = _policy_summary(rows, 2)
    assert s["picks_per_hour_cell_clock"] == pytest.approx(2 * 3600 / (12.0 + 10.0))


def test_free_space_speed_and_acceleration_are_written_with_the_safety_caps_they_need(tmp_path):
    from benchmarks.emulated import _write_config
    from flgd.config import load_config

    cfg = load_config(_write_config(tmp_path, "ur5e", "127.0.0.1", {"speed": 1.0, "acceleration": 2.5,
                                                                     "raise_speed": 1.2}))
    assert (cfg.robot.speed, cfg.robot.acceleration, cfg.robot.raise_speed) == (1.0, 2.5, 1.2)
    assert (cfg.safety.max_speed, cfg.safety.max_acceleration) == (1.2, 2.5)
    assert cfg.robot.approach_speed == 0.08 and cfg.robot.decide_while_placing


def test_a_seed_lays_out_other_scenes_on_both_cells(tmp_path):
    from benchmarks.emulated import _write_config
    from flgd.config import load_config

    for backend in ("sim", "ur5e"):
        assert load_config(_write_config(tmp_path / backend, backend, "127.0.0.1", seed=3)).sim.seed == 3
    assert load_config(_write_config(tmp_path / "default", "ur5e", "127.0.0.1")).sim.seed == 0
