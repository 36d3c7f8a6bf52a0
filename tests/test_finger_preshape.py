"""The opening a grasp comes down with (``flgd.finger_preshape``)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from flgd.finger_preshape import preshape_width
from flgd.grasp_view import FINGER_DEPTH, FINGER_HALF_WIDTH

RES = 0.002
OPEN = 0.085
MARGIN = 0.01


def block(h: np.ndarray, rows: tuple[int, int], cols: tuple[int, int], height: float = 0.03) -> np.ndarray:
    h[rows[0]:rows[1], cols[0]:cols[1]] = height
    return h


def band_blocked(h: np.ndarray, row: float, col: float, angle: float, fingertips: float, width: float) -> bool:
    """A restatement for one opening: anything higher than ``fingertips`` whose pixel's extent along the closing
    line reaches into the ``MARGIN`` inside either pad face, or into a finger (``FINGER_DEPTH`` beyond its pad
    face) while standing higher than anything under the fully open fingers; ``FINGER_HALF_WIDTH`` across."""
    c, s = math.cos(angle), math.sin(angle)
    half = RES / 2 * (abs(c) + abs(s))
    pixels = []
    for r, col_ in zip(*np.nonzero(h > 0.0)):
        dx, dy = (col_ - col) * RES, (r - row) * RES
        along, across = abs(dx * c + dy * s), abs(-dx * s + dy * c)
        if across - half <= FINGER_HALF_WIDTH:
            pixels.append((along - half, along + half, float(h[r, col_])))
    open_top = max([z for near, far, z in pixels if near <= OPEN / 2 + FINGER_DEPTH and far >= OPEN / 2],
                   default=0.0)
    for near, far, z in pixels:
        if z <= fingertips:
            continue
        if near <= width / 2 and far >= width / 2 - MARGIN:
            return True
        if z > open_top and near <= width / 2 + FINGER_DEPTH and far >= width / 2:
            return True
    return False


def test_a_lone_block_gets_its_span_across_the_closing_line_and_a_margin_each_side():
    h = block(np.zeros((80, 80)), (30, 50), (32, 48))   # 32 mm along the columns, 40 mm along the rows
    across_cols = preshape_width(h, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES)
    across_rows = preshape_width(h, 39.5, 39.5, math.pi / 2, 0.004, OPEN, MARGIN, RES)
    assert 0.032 + 2 * MARGIN <= across_cols <= 0.032 + 2 * MARGIN + 2 * RES
    assert 0.040 + 2 * MARGIN <= across_rows <= 0.040 + 2 * MARGIN + 2 * RES


def test_a_neighbour_where_a_finger_would_land_opens_past_it_and_one_too_close_keeps_the_fingers_fully_open():
    lone = block(np.zeros((80, 80)), (30, 50), (32, 48))
    alone = preshape_width(lone, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES)
    # a 4 mm wide rib 4 mm beyond the block's edge: where the narrow fingers would land, inside the open ones
    ribbed = block(lone.copy(), (30, 50), (50, 52))
    past = preshape_width(ribbed, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES)
    assert alone < past < OPEN
    assert not band_blocked(ribbed, 39.5, 39.5, 0.0, 0.004, past + 1e-5)
    assert band_blocked(ribbed, 39.5, 39.5, 0.0, 0.004, alone)
    # blocks touching on both sides, wider together than the stroke: nothing narrower than fully open is free
    row = block(lone.copy(), (30, 50), (10, 70))
    assert preshape_width(row, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES) == OPEN


def test_a_finger_may_land_on_what_is_no_higher_than_what_the_open_fingers_would_come_down_on():
    h = block(np.zeros((80, 80)), (30, 50), (32, 48))   # the grasped block, 32 mm across, 30 mm tall
    tall = block(h.copy(), (30, 50), (62, 70), height=0.06)   # 45-61 mm out: under the open finger, 60 mm tall
    alone = preshape_width(h, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES)
    # a 20 mm block where the narrow finger lands: it would stop the descent sooner than the table, not sooner
    # than the tall one under the open fingers
    low = block(tall.copy(), (30, 50), (54, 58), height=0.02)
    assert preshape_width(low, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES) == alone
    # without the tall one the open fingers come down on table: the low block is in the way
    assert preshape_width(block(h.copy(), (30, 50), (54, 58), height=0.02), 39.5, 39.5, 0.0, 0.004, OPEN,
                          MARGIN, RES) > alone


def test_table_noise_up_to_the_floor_does_not_widen_a_low_objects_opening():
    h = block(np.zeros((80, 80)), (30, 50), (32, 48), height=0.02)
    alone = preshape_width(h, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES, floor=0.01)
    noisy = h.copy()
    noisy[::3, ::3] = np.where(noisy[::3, ::3] > 0, noisy[::3, ::3], 0.006)   # specks of 6 mm on the table
    assert preshape_width(noisy, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES, floor=0.01) == alone < OPEN
    assert preshape_width(noisy, 39.5, 39.5, 0.0, 0.004, OPEN, MARGIN, RES) == OPEN   # without the floor


def test_what_stands_lower_than_the_fingertips_does_not_widen_the_opening():
    h = block(np.zeros((80, 80)), (30, 50), (32, 48), height=0.05)
    low_neighbour = block(h.copy(), (30, 50), (50, 60), height=0.008)   # lower than the fingertips' 0.02 m
    assert preshape_width(low_neighbour, 39.5, 39.5, 0.0, 0.02, OPEN, MARGIN, RES) == \
        preshape_width(h, 39.5, 39.5, 0.0, 0.02, OPEN, MARGIN, RES)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(10, 60), st.integers(10, 60), st.integers(2, 12), st.integers(2, 12),
                          st.sampled_from([0.003, 0.02, 0.03, 0.06])),
                min_size=1, max_size=5),
       st.integers(0, 15))
def test_the_opening_is_the_narrowest_free_one(blocks, rotation):
    h = np.zeros((70, 70))
    for r, c, dr, dc, z in blocks:
        block(h, (r, r + dr), (c, c + dc), height=z)
    r0, c0, dr0, dc0, _ = blocks[0]
    row, col = r0 + dr0 / 2 - 0.5, c0 + dc0 / 2 - 0.5   # the middle of the first block
    angle = 2 * math.pi * rotation / 16
    width = preshape_width(h, row, col, angle, 0.004, OPEN, MARGIN, RES)
    assert 2 * MARGIN <= width <= OPEN
    if width < OPEN:
        assert not band_blocked(h, row, col, angle, 0.004, width + 1e-5)
    for narrower in np.arange(2 * MARGIN, width - 0.001, 0.0005):
        assert band_blocked(h, row, col, angle, 0.004, narrower), f"{narrower:.4f} m is free, narrower than {width}"
