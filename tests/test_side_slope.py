"""exploration.side_taper: a grasp only where the pads close on sides that stand up, not on sides that slope."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flgd.clutter import cell_action_masks
from flgd.config import CellConfig
from flgd.learning.agent import Agent
from flgd.learning.networks import build_network
from flgd.side_slope import SIDE_RISE, side_tapers, steep_sides
from tests.test_finger_clearance import config as clearance_config

N, R, RES, OPEN, DEPTH, FLOOR = 224, 16, 0.002, 0.085, 0.03, 0.004
ALONG_X, ALONG_Y = 0, 4      # rotation indices closing along x (columns) and along y (rows)


def config(limit: float, **exploration) -> CellConfig:
    return clearance_config(exploration.pop("finger_clearance", 0.0), side_taper=limit, **exploration)


def prism(h: np.ndarray, row: int, col: int) -> None:
    """A triangular prism lying on a face, its ridge along y (rows): 40 mm wide at its base, 35 mm high."""
    for c in range(col - 10, col + 11):
        h[row - 15:row + 15, c] = np.maximum(h[row - 15:row + 15, c], 0.035 * (1 - abs(c - col) / 10.0))


def box(h: np.ndarray, row: int, col: int) -> None:
    """A 40 x 40 mm block, 30 mm high."""
    h[row - 10:row + 10, col - 10:col + 10] = 0.03


def taper(h: np.ndarray, row: int, col: int, rotation: int) -> tuple[float, float]:
    return side_tapers(h, row, col, 2 * math.pi * rotation / R, RES, OPEN, DEPTH, SIDE_RISE, FLOOR)


def test_a_prism_gripped_across_its_ridge_tapers_and_along_it_does_not():
    h = np.zeros((N, N), np.float32)
    prism(h, 100, 100)
    across, along = taper(h, 100, 100, ALONG_X), taper(h, 100, 100, ALONG_Y)
    # 1 cm up a side falling 35 mm over 20 mm, the side has come about 5.7 mm nearer the ridge
    assert across[0] == pytest.approx(0.006, abs=0.0021) and across[1] == pytest.approx(0.006, abs=0.0021)
    assert along == (0.0, 0.0)


def test_a_block_has_upright_sides_at_every_rotation():
    h = np.zeros((N, N), np.float32)
    box(h, 100, 100)
    assert all(taper(h, 100, 100, r) == (0.0, 0.0) for r in range(R))


def test_the_mask_is_the_tapers_limit_at_every_pixel_and_rotation():
    rng = np.random.default_rng(3)
    h = np.zeros((N, N), np.float32)
    for _ in range(12):
        r, c = rng.integers(20, N - 20, 2)
        (prism if rng.random() < 0.5 else box)(h, int(r), int(c))
    h += rng.normal(0.0, 0.001, h.shape).astype(np.float32) * (h > 0)
    mask = steep_sides(h, R, RES, OPEN, DEPTH, SIDE_RISE, FLOOR, 0.004)
    for _ in range(2000):
        r, c, i = int(rng.integers(0, N)), int(rng.integers(0, N)), int(rng.integers(0, R))
        assert bool(mask[i, r, c]) == (max(taper(h, r, c, i)) <= 0.004 + 1e-9), (r, c, i)


def test_the_agent_grasps_a_prism_along_its_ridge_over_a_better_valued_grasp_across_it():
    h = np.zeros((N, N), np.float32)
    prism(h, 100, 100)
    q = np.zeros((R, 2, N, N), np.float32)
    q[:, 1] = -1.0
    q[ALONG_X, 0, 100, 100] = 2.0          # across the ridge: the best value
    q[ALONG_Y, 0, 100, 100] = 1.0
    for limit, rotation in ((0.0, ALONG_X), (0.004, ALONG_Y)):
        d = Agent(config(limit), build_network("fast", R, seed=0), seed=0).select(q, h, 0)
        assert d is not None and (d.action.primitive, d.action.rotation, d.action.row, d.action.col) == \
            ("grasp", rotation, 100, 100)


def test_an_object_sloping_every_way_is_still_grasped_when_nothing_else_is_left():
    h = np.zeros((N, N), np.float32)
    rows, cols = np.mgrid[0:N, 0:N]
    h[:] = np.clip(0.035 - 0.0025 * np.hypot(rows - 100, cols - 100), 0.0, None)   # a cone
    mask = steep_sides(h, R, RES, OPEN, DEPTH, SIDE_RISE, FLOOR, 0.001)
    assert not (mask & (h > 0.01)).any()     # the limit alone refuses every grasp on it
    with_block = h.copy()
    box(with_block, 170, 170)
    rho_g, _ = cell_action_masks(with_block, config(0.001, grasp_only=True), R)
    assert rho_g[:, 150:190, 150:190].any() and not rho_g[:, :140, :140].any()   # the limit holds while it can
    rho_g, _ = cell_action_masks(h, config(0.001, grasp_only=True), R)
    off, _ = cell_action_masks(h, config(0.0, grasp_only=True), R)
    assert rho_g.any() and (rho_g == off).all()


def test_with_the_finger_clearance_too_the_side_limit_is_lifted_first():
    h = np.zeros((N, N), np.float32)
    rows, cols = np.mgrid[0:N, 0:N]
    for col in (100, 125):   # two cones 5 cm apart: every side slopes, and a finger may land on the other
        h[:] = np.maximum(h, np.clip(0.035 - 0.0025 * np.hypot(rows - 100, cols - col), 0.0, None))
    both, _ = cell_action_masks(h, config(0.001, grasp_only=True, finger_clearance=0.01), R)
    clearance, _ = cell_action_masks(h, config(0.0, grasp_only=True, finger_clearance=0.01), R)
    off, _ = cell_action_masks(h, config(0.0, grasp_only=True), R)
    assert clearance.any() and (both == clearance).all() and (clearance != off).any()
