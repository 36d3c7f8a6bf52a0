"""The emulated arm's press rule: the protective stop and the TCP force count what the gripper squeezes an object
into what it rests on *since it touched it*, not how far pybullet's pile already let it sink."""

from __future__ import annotations

import dataclasses

import pytest

from flgd.config import load_config
from sim_cell.emulator.arm import PRESS_DEPTH, SQUEEZE_STIFFNESS, EmulatedArm, SafetyMode
from sim_cell.emulator.world import EmulatorWorld
from tests.fakes.realsense import SIM_CONFIG


@pytest.fixture
def arm():
    cfg = load_config(SIM_CONFIG)
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, objects=0))
    with EmulatorWorld(cfg) as world:
        yield EmulatedArm(world)


def _touching(arm: EmulatedArm, monkeypatch, depths: list[dict[int, float]]) -> None:
    """What the gripper touches, tick after tick: {object: its deepest penetration}."""
    readings = iter(depths)
    monkeypatch.setattr(arm.world.cell._arm.contacts, "pressing_by_object", lambda: (5.0, next(readings)))


def test_touching_an_object_that_already_sinks_into_the_pile_is_no_press(arm, monkeypatch):
    sunk = PRESS_DEPTH + 0.002  # beyond the stop's depth before the gripper came
    _touching(arm, monkeypatch, [{7: sunk}, {7: sunk + 0.0005}, {}])
    arm._measure_squeeze()
    arm._check_press()
    assert arm.safety_mode == SafetyMode.NORMAL
    assert arm._squeeze == 0.0 and arm._tcp_force()[2] == 0.0  # its sinking is not the gripper's push
    arm._measure_squeeze()
    assert arm._squeeze == pytest.approx(0.0005)
    assert arm._tcp_force()[2] == pytest.approx(SQUEEZE_STIFFNESS * 0.0005, rel=0.01)  # 12.5 N: the guard's cue
    arm._check_press()
    assert arm.safety_mode == SafetyMode.NORMAL
    arm._measure_squeeze()  # let go: the next touch of it starts from its depth then
    assert arm._squeeze == 0.0 and arm._touch_depth == {}


def test_pressing_an_object_past_the_press_depth_since_the_touch_is_a_protective_stop(arm, monkeypatch):
    _touching(arm, monkeypatch, [{3: 0.001}, {3: 0.001 + PRESS_DEPTH + 0.0005}])
    arm._measure_squeeze()
    arm._check_press()
    assert arm.safety_mode == SafetyMode.NORMAL
    arm._measure_squeeze()
    assert arm._tcp_force()[2] > 150.0  # the guard felt it long before: 150 N at the press depth
    arm._check_press()
    assert arm.safety_mode == SafetyMode.PROTECTIVE_STOP
    assert "mm into an object" in arm.faults[-1], arm.faults
