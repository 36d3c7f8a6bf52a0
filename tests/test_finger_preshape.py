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
    """A restatement for one opening: anything higher than ``fingertips`` whose pixel's extent along and across
    the closing line reaches into either finger's band, from ``MARGIN`` inside the pad face to the finger's outer
    face, ``FINGER_HALF_WIDTH`` across."""
    c, s = math.cos(angle), math.sin(angle)
    half = RES / 2 * (abs(c) + abs(s))
    for r, col_ in zip(*np.nonzero(h > fingertips)):
        dx, dy = (col_ - col) * RES, (r - row) * RES
        along, across = dx * c + dy * s, -dx * s + dy * c
        if abs(across) - half > FINGER_HALF_WIDTH:
            continue
        near, far = max(abs(along) - half, 0.0), abs(along) + half
        if near <= width / 2 + FINGER_DEPTH and far >= width / 2 - MARGIN:
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


def test_what_stands_lower_than_the_fingertips_does_not_widen_the_opening():
    h = block(np.zeros((80, 80)), (30, 50), (32, 48), height=0.05)
    low_neighbour = block(h.copy(), (30, 50), (50, 60), height=0.008)   # lower than the fingertips' 0.02 m
    assert preshape_width(low_neighbour, 39.5, 39.5, 0.0, 0.02, OPEN, MARGIN, RES) == \
        preshape_width(h, 39.5, 39.5, 0.0, 0.02, OPEN, MARGIN, RES)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(10, 60), st.integers(10, 60), st.integers(2, 12), st.integers(2, 12)),
                min_size=1, max_size=4),
       st.integers(0, 15))
def test_the_opening_is_the_narrowest_free_one(blocks, rotation):
    h = np.zeros((70, 70))
    for r, c, dr, dc in blocks:
        block(h, (r, r + dr), (c, c + dc))
    r0, c0, dr0, dc0 = blocks[0]
    row, col = r0 + dr0 / 2 - 0.5, c0 + dc0 / 2 - 0.5   # the middle of the first block
    angle = 2 * math.pi * rotation / 16
    width = preshape_width(h, row, col, angle, 0.004, OPEN, MARGIN, RES)
    assert 2 * MARGIN <= width <= OPEN
    if width < OPEN:
        assert not band_blocked(h, row, col, angle, 0.004, width + 1e-5)
    for narrower in np.arange(2 * MARGIN, width - 0.001, 0.0005):
        assert band_blocked(h, row, col, angle, 0.004, narrower), f"{narrower:.4f} m is free, narrower than {width}"
