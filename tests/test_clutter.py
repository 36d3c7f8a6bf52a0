"""Clutter quantization, the move/grasp rewards and the masks (paper III-B, III-D)."""

from __future__ import annotations

import numpy as np
import pytest

from flgd.clutter import (clutter_map, coverage_change, grasp_mask, grasp_reward, height_rise, judge_move,
                          move_mask)
from flgd.config import GripperConfig, RewardConfig

RC = RewardConfig()


def heightmap_with(blocks: list[tuple[int, int, int, int, float]], size: int = 224) -> np.ndarray:
    """Blocks given as (row, col, rows, cols, height) on an empty table."""
    hm = np.zeros((size, size), np.float32)
    for r, c, nr, nc, h in blocks:
        hm[r:r + nr, c:c + nc] = h
    return hm


# Four 5 cm blocks (25 px) packed in a 2x2 square, then scattered apart.
CLUSTERED = heightmap_with([(80, 80, 25, 25, 0.05), (80, 105, 25, 25, 0.05),
                            (105, 80, 25, 25, 0.05), (105, 105, 25, 25, 0.05)])
SCATTERED = heightmap_with([(30, 30, 25, 25, 0.05), (30, 150, 25, 25, 0.05),
                            (150, 30, 25, 25, 0.05), (150, 150, 25, 25, 0.05)])


def test_scattering_raises_eta_above_tau2_and_is_rewarded() -> None:
    eta = coverage_change(CLUSTERED, SCATTERED, RC)
    # Clustered: one (50+10)^2 dilated square; scattered: four (25+10)^2 squares.
    assert eta == 4 * 35 * 35 - 60 * 60
    assert eta > RC.tau2
    judged = judge_move(CLUSTERED, SCATTERED, RC)
    assert judged.reward == RC.move_reward and judged.eta == eta


def test_unchanged_scene_gives_zero_eta_and_no_reward() -> None:
    rng = np.random.default_rng(0)
    noisy = CLUSTERED + rng.normal(0, 0.001, CLUSTERED.shape).astype(np.float32)  # ~1 mm depth noise
    assert coverage_change(CLUSTERED, CLUSTERED, RC) == 0
    assert abs(coverage_change(CLUSTERED, noisy, RC)) <= 5
    judged = judge_move(CLUSTERED, noisy, RC)
    assert judged.reward == 0.0 and judged.mu == 0


def test_gathering_objects_lowers_eta() -> None:
    assert coverage_change(SCATTERED, CLUSTERED, RC) < 0


def test_mu_counts_exactly_pixels_raised_by_more_than_delta() -> None:
    before = np.zeros((50, 50), np.float32)
    after = before.copy()
    after[0:3, 0:4] = RC.delta + 0.001    # 12 raised clearly
    after[10, 10:15] = RC.delta            # 5 raised by exactly delta: not counted
    after[20, 0:7] = RC.delta - 0.001      # 7 raised by less: not counted
    after[30, 0:9] = -0.05                 # 9 lowered: not counted
    assert height_rise(before, after, RC.delta) == 12
    after[40, 0] = np.nan                   # a NaN reading counts as table, not as a rise
    assert height_rise(before, after, RC.delta) == 12


def test_mu_alone_triggers_the_move_reward() -> None:
    before = heightmap_with([(100, 100, 25, 25, 0.05)])
    after = heightmap_with([(100, 100, 25, 25, 0.05), (10, 10, 30, 30, 0.03)])  # 900 px appeared
    rc = RewardConfig(tau2=10_000)  # eta cannot fire
    judged = judge_move(before, after, rc)
    assert judged.mu == 900 and judged.reward == rc.move_reward
    assert judge_move(before, before, rc).reward == 0.0


def test_clutter_map_is_binarised_then_dilated() -> None:
    hm = heightmap_with([(50, 50, 6, 6, 0.02), (70, 70, 6, 6, RC.min_height / 2)])
    cm = clutter_map(hm, RC)
    k = RC.clutter_dilation
    assert cm.sum() == (6 + k - 1) ** 2  # only the block above min_height, grown by the k x k kernel
    assert cm[50, 50] == 1 and cm[71, 71] == 0


def test_masks() -> None:
    hm = heightmap_with([(100, 100, 10, 10, 0.03)])
    g = grasp_mask(hm, RC)
    m = move_mask(hm, RC)
    assert g.dtype == np.uint8 and g.sum() == 100
    assert m.sum() == (10 + RC.move_mask_dilation - 1) ** 2
    assert ((m == 1) | (g == 0)).all()  # rho_m contains rho_g
    assert grasp_mask(np.zeros((20, 20), np.float32), RC).sum() == 0


@pytest.mark.parametrize("width,expected", [(0.0, 0.0), (0.004, 0.0), (0.006, 1.0), (0.08, 1.0),
                                            (float("nan"), 0.0)])
def test_grasp_reward_from_width(width: float, expected: float) -> None:
    assert grasp_reward(width, GripperConfig(success_threshold=0.005)) == expected


# --- objects, not pixels (rewards.min_object_area) ---------------------------------------------------------------

def _specks(n: int, seed: int = 0, size: int = 224, height: float = 0.015) -> np.ndarray:
    """``n`` single-pixel spikes above min_height on an empty table, none touching another."""
    rng = np.random.default_rng(seed)
    hm = np.zeros((size, size), np.float32)
    placed = 0
    while placed < n:
        r, c = (int(v) for v in rng.integers(2, size - 2, 2))
        if hm[r - 1:r + 2, c - 1:c + 2].any():
            continue
        hm[r, c] = height
        placed += 1
    return hm


def test_scattered_one_pixel_spikes_on_an_empty_table_give_empty_masks() -> None:
    hm = _specks(200)
    assert grasp_mask(hm, RC).sum() == 0
    assert move_mask(hm, RC).sum() == 0
    assert clutter_map(hm, RC).sum() == 0
    # the filter is what empties them: every speck is an "object" with it off
    off = RewardConfig(min_object_area=0.0)
    assert grasp_mask(hm, off).sum() == 200 and move_mask(hm, off).sum() > 200 * 100


def test_a_blocks_masks_are_unchanged_by_the_filter_even_with_specks_around_it() -> None:
    block = heightmap_with([(100, 100, 12, 15, 0.03), (30, 150, 5, 6, 0.02)])  # a block, and a 1 x 1.2 cm bar
    off = RewardConfig(min_object_area=0.0)
    for f in (grasp_mask, move_mask, clutter_map):
        assert np.array_equal(f(block, RC), f(block, off)), f.__name__
    specks = _specks(150, seed=1)
    specks[95:118, 95:120] = 0   # none touching the block (a speck on its edge is part of it)
    specks[25:40, 145:160] = 0
    noisy = np.maximum(block, specks)
    assert np.array_equal(grasp_mask(noisy, RC), grasp_mask(block, off))
    assert np.array_equal(move_mask(noisy, RC), move_mask(block, off))


def test_the_filter_is_sized_in_square_millimetres_at_the_heightmap_resolution() -> None:
    from flgd.clutter import min_region_pixels

    rc = RewardConfig(min_object_area=36.0)
    assert min_region_pixels(rc, 0.002) == 9      # 2 mm pixels: 3 x 3 px
    assert min_region_pixels(rc, 0.001) == 36     # 1 mm pixels
    assert min_region_pixels(RewardConfig(min_object_area=0.0), 0.002) == 0
    two_by_two = heightmap_with([(50, 50, 2, 2, 0.02)])   # 16 mm^2 at 2 mm/px: noise
    three_by_three = heightmap_with([(50, 50, 3, 3, 0.02)])
    assert grasp_mask(two_by_two, rc, 0.002).sum() == 0 and grasp_mask(three_by_three, rc, 0.002).sum() == 9
    assert grasp_mask(two_by_two, rc, 0.001).sum() == 0 and grasp_mask(three_by_three, rc, 0.001).sum() == 0


def test_new_specks_are_no_clutter_change_and_no_height_rise() -> None:
    before = heightmap_with([(100, 100, 25, 25, 0.05)])
    after = np.maximum(before, _specks(40, seed=2))
    judged = judge_move(before, after, RC)
    assert judged.eta == 0 and judged.mu == 0 and judged.reward == 0.0
    off = judge_move(before, after, RewardConfig(min_object_area=0.0))
    assert off.eta > RC.tau2 and off.reward == RC.move_reward   # unfiltered, noise alone "moved the clutter"
