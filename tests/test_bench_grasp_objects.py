"""The per-object grasp tally of ``flgd bench grasp_objects``."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from benchmarks.grasp_objects import GraspTally, aimed_object


@dataclass
class _State:
    label: str
    points: np.ndarray


def _box(label: str, x0: float, y0: float, size: float = 0.04) -> _State:
    pts = np.array([[x0 + dx, y0 + dy, 0.0] for dx in (0, size) for dy in (0, size)])
    return _State(label, pts)


def test_a_grasp_aims_at_the_object_under_it_else_the_nearest():
    states = [_box("a", 0.0, 0.0), _box("b", 0.10, 0.0)]
    assert aimed_object(states, 0.02, 0.02) == ("a", True)
    assert aimed_object(states, 0.12, 0.01) == ("b", True)
    assert aimed_object(states, 0.075, 0.02) == ("b", False)    # between them, 2.5 cm from b, 3.5 cm from a
    assert aimed_object([], 0.0, 0.0) is None


@dataclass
class _Plan:
    primitive: str
    target: tuple


@dataclass
class _Checked:
    plan: _Plan


@dataclass
class _Result:
    widths: list


@dataclass
class _Gripper:
    success_threshold: float = 0.005


@dataclass
class _Config:
    gripper: _Gripper = field(default_factory=_Gripper)


class FakeSimCell:
    """A fake of SimCell's execute/object_states (the bench only observes them): a grasp on "wide" closes
    empty, any other grasp holds; a move has no width; the fault case is a grasp that reports no width."""

    config = _Config()

    def object_states(self):
        return [_box("wide", 0.0, 0.0), _box("small", 0.10, 0.0)]

    def execute(self, checked):
        plan = checked.plan
        if plan.primitive != "grasp":
            return _Result([])
        if plan.target[0] > 0.2:
            return _Result([])               # the fault: nothing measured
        return _Result([0.0 if plan.target[0] < 0.05 else 0.03])


def test_the_tally_counts_grasps_per_object_and_restores_the_cell():
    tally = GraspTally()
    original = tally.wrap(FakeSimCell)
    try:
        cell = FakeSimCell()
        for target in ((0.02, 0.02), (0.02, 0.01), (0.12, 0.02), (0.3, 0.0)):
            cell.execute(_Checked(_Plan("grasp", target)))
        cell.execute(_Checked(_Plan("push", (0.02, 0.02))))
    finally:
        FakeSimCell.execute = original
    assert tally.rows() == [("small", 1, 2), ("wide", 0, 2)]   # the unmeasured grasp is a failure on "small"
    assert tally.off_object == 1
    assert FakeSimCell.execute is original


def test_bad_arguments_are_clear_errors_before_any_simulation(capsys, tmp_path):
    from benchmarks.grasp_objects import REPO, main

    shipped = str(REPO / "policies" / "flg-sim.safetensors")
    assert main(["--policy", str(tmp_path / "missing.safetensors")]) == 1
    assert "missing.safetensors" in capsys.readouterr().err
    assert main(["--policy", shipped, "--objects", "nothing_like_this_*.urdf"]) == 1
    assert "matches no URDF" in capsys.readouterr().err
    assert main(["--policy", shipped, "--runs", "0"]) == 1
    assert "--runs and --count must be >= 1" in capsys.readouterr().err
