"""exploration.finger_clearance: a grasp only where both open fingers come down free of what stands beside it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flgd.clutter import cell_action_masks, objects
from flgd.config import CellConfig, ConfigError, config_from_dict
from flgd.config.schema import RewardConfig
from flgd.finger_clearance import fingers_clear
from flgd.learning.agent import Agent
from flgd.learning.networks import build_network

N, R, RES, OPEN = 224, 16, 0.002, 0.085
ALONG_X, ALONG_Y = 0, 4      # rotation indices closing along x (columns) and along y (rows)


def config(clearance: float, **exploration) -> CellConfig:
    cfg = CellConfig()
    ex = dict(finger_clearance=clearance, epsilon_start=0.0, epsilon_end=0.0, curriculum_steps=0)
    ex.update(exploration)
    return dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, **ex),
                               learning=dataclasses.replace(cfg.learning, device="cpu"))


def free(height: np.ndarray, clearance: float) -> np.ndarray:
    return fingers_clear(height, objects(height, RewardConfig(), RES), R, RES, OPEN, clearance, 0.01)


def packed_pair(neighbour_height: float = 0.05) -> np.ndarray:
    """Two 40 x 30 mm blocks laid flush along x, 5 cm tall (the second ``neighbour_height``)."""
    h = np.zeros((N, N), np.float32)
    h[100:115, 80:100] = 0.05
    h[100:115, 100:120] = neighbour_height
    return h


def test_a_finger_landing_on_a_flush_neighbour_refuses_that_rotation_only():
    limited = free(packed_pair(), 0.01)
    # the first block's middle: closing along x brings one finger down on the neighbour, closing along y on table
    assert limited[ALONG_X, 107, 90] == 0 and limited[ALONG_X + R // 2, 107, 90] == 0
    assert limited[ALONG_Y, 107, 90] == 1 and limited[ALONG_Y + R // 2, 107, 90] == 1
    # the pair's middle closing along x: 80 mm between the outer faces, both fingers (42.5 mm out) on table
    assert limited[ALONG_X, 107, 100] == 1
    # the neighbour moved 6 cm away along x: beyond the finger (42.5 mm + 15 mm from the grasp), every rotation free
    apart = np.zeros((N, N), np.float32)
    apart[100:115, 80:100] = 0.05
    apart[100:115, 130:150] = 0.05
    assert free(apart, 0.01)[:, 107, 90].all()


def test_a_lower_neighbour_is_allowed_as_far_as_the_clearance_reaches():
    lower = packed_pair(neighbour_height=0.035)    # 15 mm below the grasped top
    assert free(lower, 0.01)[ALONG_X, 107, 90] == 1
    assert free(lower, 0.02)[ALONG_X, 107, 90] == 0


def test_a_low_object_needs_table_under_the_fingers():
    h = np.zeros((N, N), np.float32)
    h[100:110, 100:110] = 0.015            # 15 mm tall: 15 mm - 10 mm is below the 10 mm object threshold
    assert free(h, 0.01)[:, 105, 105].all()
    h[100:110, 120:140] = 0.012            # a flat part where the x-closing finger comes down
    limited = free(h, 0.01)
    assert limited[ALONG_X, 105, 105] == 0 and limited[ALONG_Y, 105, 105] == 1


def test_the_kernels_turn_with_the_closing_line_not_against_it():
    h = np.zeros((N, N), np.float32)
    h[100:110, 100:110] = 0.05
    h[120:126, 120:126] = 0.05             # a neighbour diagonally towards +x, +y (columns x, rows y)
    limited = free(h, 0.01)
    # closing at 45 degrees (rotation 2, and its twin 10) brings a finger down on it; at 135 degrees neither
    assert limited[2, 105, 105] == 0 and limited[10, 105, 105] == 0
    assert limited[6, 105, 105] == 1 and limited[14, 105, 105] == 1


def test_depth_specks_under_a_finger_refuse_nothing():
    h = np.zeros((N, N), np.float32)
    h[100:110, 100:110] = 0.05
    h[105, 129] = 0.05                     # one pixel where the x-closing finger comes down: noise, not an object
    h[104, 90] = np.nan                    # and an unknown height under the other finger
    assert free(h, 0.01)[ALONG_X, 105, 105] == 1


def wide_disc() -> np.ndarray:
    """A 19 cm disc, 5 cm tall: no grasp anywhere on it brings both fingers down beside it (a square's corner,
    or a smaller disc's rim, leaves a grasp straddling it)."""
    rows, cols = np.mgrid[0:N, 0:N]
    return np.where((rows - 112) ** 2 + (cols - 112) ** 2 <= 47.5 ** 2, 0.05, 0.0).astype(np.float32)


def test_an_object_with_no_free_grasp_is_still_pushed_and_the_agent_moves_there():
    h = wide_disc()
    cfg = config(0.01)
    rho_g, rho_m = cell_action_masks(h, cfg, R)
    assert not rho_g.any() and rho_m.any()
    off, off_m = cell_action_masks(h, config(0.0), R)
    assert off.any() and (off_m == rho_m).all()
    agent = Agent(cfg, build_network("fast", R, seed=0), seed=0)
    q = np.zeros((R, 2, N, N), np.float32)
    q[:, 0] = 1.0                          # grasps the better choice everywhere
    decision = agent.select(q, h, 0)
    assert decision is not None and decision.action.is_move


def test_the_agent_takes_the_best_free_grasp_over_a_better_valued_blocked_one():
    h = packed_pair()
    q = np.zeros((R, 2, N, N), np.float32)
    q[:, 1] = -1.0
    q[ALONG_X, 0, 107, 90] = 2.0           # the finger on the neighbour: the best value
    q[ALONG_Y, 0, 107, 90] = 1.0
    for clearance, rotation in ((0.0, ALONG_X), (0.01, ALONG_Y)):
        d = Agent(config(clearance), build_network("fast", R, seed=0), seed=0).select(q, h, 0)
        assert d is not None and (d.action.primitive, d.action.rotation, d.action.row, d.action.col) == \
            ("grasp", rotation, 107, 90)


def test_grasp_only_grasps_as_without_the_clearance_when_no_grasp_is_free():
    h = wide_disc()
    rho_g, _ = cell_action_masks(h, config(0.01, grasp_only=True), R)
    off, _ = cell_action_masks(h, config(0.0, grasp_only=True), R)
    assert rho_g.any() and (rho_g == off).all()


def test_a_clearance_deeper_than_the_grasp_is_refused_by_name():
    with pytest.raises(ConfigError, match=r"exploration.finger_clearance.*robot.grasp_depth"):
        config_from_dict({"exploration": {"finger_clearance": 0.04}, "robot": {"grasp_depth": 0.03}})
