"""Heightmaps from analytic RGB-D frames, and the pixel <-> base-frame map."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flgd.config import WorkspaceConfig
from flgd.perception import base_to_pixel, make_heightmaps, pixel_to_base
from tests.fakes.scene import Box, camera_looking_down, intrinsics_matrix, render

WS = WorkspaceConfig()  # 224 x 224 at 2 mm, x in [-0.724, -0.276], table at z = 0


def true_footprint(box: Box, ws: WorkspaceConfig = WS) -> np.ndarray:
    rows, cols = ws.shape
    r, c = np.mgrid[0:rows, 0:cols]
    x, y, _ = pixel_to_base(r, c, 0.0, ws)
    return box.contains_xy(x, y)


BOXES = [
    Box(-0.60, -0.10, 0.050, 0.030, 0.040, yaw=0.0, color=(220, 40, 40)),
    Box(-0.42, 0.08, 0.070, 0.025, 0.025, yaw=0.6, color=(40, 200, 60)),
    Box(-0.50, 0.15, 0.040, 0.040, 0.090, yaw=-0.3, color=(30, 60, 210)),
]


@pytest.mark.parametrize("tilt", [0.0, 0.12])
def test_boxes_heights_and_footprints(tilt: float) -> None:
    k = intrinsics_matrix()
    pose = camera_looking_down(-0.5, 0.02, 0.70, tilt=tilt, yaw=0.2)
    color, depth = render(BOXES, pose, k, table_z=WS.table_z)
    hm = make_heightmaps(color, depth, k, 0.001, pose, WS)
    assert hm.height.shape == (224, 224) and hm.height.dtype == np.float32
    assert hm.color.shape == (224, 224, 3) and hm.color.dtype == np.uint8

    one = np.ones((3, 3), np.uint8)
    for box in BOXES:
        truth = true_footprint(box)
        seen = hm.height > box.height / 2
        # Only this box's pixels: near its own footprint.
        near = cv2.dilate(truth.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        seen &= near
        # Footprint within one pixel: what is seen lies inside the truth grown by one pixel,
        # and the truth shrunk by one pixel is seen (the top face is fully visible).
        grown = cv2.dilate(truth.astype(np.uint8), one).astype(bool)
        shrunk = cv2.erode(truth.astype(np.uint8), one).astype(bool)
        assert not (seen & ~grown).any(), f"{box}: {int((seen & ~grown).sum())} px outside the footprint"
        assert not (shrunk & ~seen).any(), f"{box}: {int((shrunk & ~seen).sum())} px of the top missing"
        # Heights within 2 mm on the top face; colour of the top face is the box's.
        top = hm.height[shrunk]
        assert np.abs(top - box.height).max() <= 0.002
        assert (hm.color[shrunk] == np.array(box.color, np.uint8)).all()

    # Table pixels far from every box are at height ~0.
    anything = np.zeros((224, 224), bool)
    for box in BOXES:
        anything |= cv2.dilate(true_footprint(box).astype(np.uint8), np.ones((31, 31), np.uint8)).astype(bool)
    table = hm.height[~anything]
    assert np.abs(table).max() <= 0.002


def test_invalid_depth_is_ignored_and_unfilled_empty_cells_are_zero() -> None:
    k = intrinsics_matrix()
    pose = camera_looking_down(-0.5, 0.0, 0.70)
    box = Box(-0.5, 0.0, 0.06, 0.06, 0.05)
    color, depth = render([box], pose, k)
    depth_f = depth.astype(np.float32) * 0.001
    # Holes (0), NaN and readings beyond range over the box's top: those cells must stay 0.
    depth_f[200:280, 280:360] = 0.0
    depth_f[230:240, 300:340] = np.nan
    depth_f[250:255, 300:340] = 5.0
    hm = make_heightmaps(color, depth_f, k, 1.0, pose, WS, depth_range=(0.2, 1.5), fill="none")
    assert np.isfinite(hm.height).all()
    assert hm.height.max() <= box.height + 0.002
    r, c = base_to_pixel(-0.5, 0.0, WS)
    assert hm.height[r, c] == 0.0 and (hm.color[r, c] == 0).all() and hm.unknown[r, c]
    # filled, the hole (which reaches the table around the box) takes the table's height, and is marked too
    filled = make_heightmaps(color, depth_f, k, 1.0, pose, WS, depth_range=(0.2, 1.5), fill="lowest")
    assert filled.height[r, c] == 0.0 and filled.unknown[r, c]


@pytest.mark.parametrize("method", ["lowest", "inpaint"])
def test_holes_inside_a_block_get_the_blocks_height_and_are_marked(method: str) -> None:
    k = intrinsics_matrix()
    pose = camera_looking_down(-0.5, 0.0, 0.70)
    box = Box(-0.5, 0.0, 0.08, 0.08, 0.05, color=(200, 60, 30))
    color, depth = render([box], pose, k)
    holed = depth.copy()
    rng = np.random.default_rng(3)
    holes = np.zeros(depth.shape, bool)
    holes[225:255, 305:335] = rng.random((30, 30)) < 0.3   # dropouts scattered over the top face
    holes[236:244, 316:324] = True                         # and one larger hole in its middle
    holed[holes] = 0
    hm = make_heightmaps(color, holed, k, 0.001, pose, WS, fill=method)
    plain = make_heightmaps(color, holed, k, 0.001, pose, WS, fill="none")
    r, c = base_to_pixel(-0.5, 0.0, WS)
    assert plain.height[r, c] == 0.0, "the hole is there without filling"
    top = true_footprint(box)
    top = cv2.erode(top.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.abs(hm.height[top] - box.height).max() <= 0.002
    assert (hm.color[top] == np.array(box.color, np.uint8)).all()
    assert hm.unknown[r, c] and hm.unknown[top].sum() == (plain.height[top] < 0.01).sum()
    assert np.array_equal(plain.unknown, hm.unknown), "marked the same whether filled or not"


def test_highest_point_wins_each_cell() -> None:
    """Two depth pixels landing in one heightmap cell: the higher point sets height and colour."""
    k = intrinsics_matrix(fx=600, fy=600, cx=2.0, cy=0.5)
    pose = camera_looking_down(-0.4995, 0.0011, 0.70)  # over the centre of one heightmap cell
    color = np.zeros((1, 4, 3), np.uint8)
    depth = np.zeros((1, 4), np.float32)
    # Pixels 2 and 3 look almost straight down; 1/600 rad apart = 1.1 mm at 0.66 m: same 2 mm cell.
    # The higher point comes first in memory, so "last write wins" would get it wrong.
    depth[0, 2], color[0, 2] = 0.70 - 0.04, (200, 100, 50)
    depth[0, 3], color[0, 3] = 0.70 - 0.01, (10, 20, 30)
    hm = make_heightmaps(color, depth, k, 1.0, pose, WS)
    nz = np.argwhere(hm.height > 0)
    assert len(nz) == 1
    assert hm.height[tuple(nz[0])] == pytest.approx(0.04, abs=1e-5)
    assert tuple(hm.color[tuple(nz[0])]) == (200, 100, 50)


@settings(max_examples=300, deadline=None)
@given(
    px=st.floats(-0.72, -0.28), py=st.floats(-0.22, 0.22), h=st.floats(0.0, 0.25),
    cam_x=st.floats(-0.6, -0.4), cam_y=st.floats(-0.1, 0.1), cam_z=st.floats(0.45, 1.2),
    tilt=st.floats(-0.3, 0.3), yaw=st.floats(-math.pi, math.pi), f=st.floats(400.0, 900.0),
)
def test_pixel_world_round_trip(px, py, h, cam_x, cam_y, cam_z, tilt, yaw, f) -> None:
    """A point seen by any camera pose lands in the heightmap pixel whose centre is within half a pixel of it."""
    pose = camera_looking_down(cam_x, cam_y, cam_z, tilt=tilt, yaw=yaw)
    p_cam = np.linalg.inv(pose) @ np.array([px, py, WS.table_z + h, 1.0])
    if p_cam[2] <= 0.05:
        return  # behind or too close to the camera: no image of it exists
    u, v = f * p_cam[0] / p_cam[2], f * p_cam[1] / p_cam[2]
    # Put the principal point so that the point projects exactly onto pixel (10, 5).
    k = intrinsics_matrix(fx=f, fy=f, cx=10 - u, cy=5 - v)
    depth = np.zeros((12, 20), np.float64)
    depth[5, 10] = p_cam[2]
    color = np.zeros((12, 20, 3), np.uint8)
    color[5, 10] = (1, 2, 3)
    hm = make_heightmaps(color, depth, k, 1.0, pose, WS)
    hit = np.argwhere(hm.height > 0) if h > 1e-4 else np.argwhere((hm.color == (1, 2, 3)).all(-1))
    assert len(hit) == 1
    r, c = hit[0]
    x, y, z = pixel_to_base(r, c, float(hm.height[r, c]), WS)
    half = WS.resolution / 2 + 1e-6
    assert abs(x - px) <= half and abs(y - py) <= half
    assert abs(z - (WS.table_z + h)) <= 1e-4
    assert base_to_pixel(x, y, WS) == (r, c)


@given(r=st.integers(-50, 300), c=st.integers(-50, 300), h=st.floats(-1, 1))
def test_pixel_to_base_inverts_base_to_pixel(r, c, h) -> None:
    x, y, z = pixel_to_base(r, c, h, WS)
    assert base_to_pixel(x, y, WS) == (r, c)
    assert z == pytest.approx(WS.table_z + h)


# --------------------------------------------------------------------------- perception: bad input is a clear error

def _frame(h: int = 30, w: int = 30):
    k = intrinsics_matrix()
    k = k.copy()
    k[0, 2], k[1, 2] = w / 2, h / 2
    pose = camera_looking_down(-0.5, 0.0, 0.7)
    return np.zeros((h, w, 3), np.uint8), np.full((h, w), 700, np.uint16), k, pose


def test_rgba_colour_is_refused_not_scrambled():
    color, depth, k, pose = _frame()
    rgba = np.zeros((30, 30, 4), np.uint8)  # 30*30*4 bytes divide by 3: the old byte view silently misread it
    with pytest.raises(ValueError, match="color"):
        make_heightmaps(rgba, depth, k, 0.001, pose, WorkspaceConfig())
    with pytest.raises(ValueError, match="color"):
        make_heightmaps(color.astype(np.float32), depth, k, 0.001, pose, WorkspaceConfig())


@pytest.mark.parametrize("what", ["pose", "intrinsics", "depth_scale", "depth"])
def test_non_finite_camera_model_is_refused_not_an_empty_heightmap(what):
    color, depth, k, pose = _frame()
    scale = 0.001
    if what == "pose":
        pose = pose.copy()
        pose[0, 3] = np.nan
    elif what == "intrinsics":
        k[0, 0] = 0.0
    elif what == "depth_scale":
        scale = float("nan")
    else:
        depth = depth[None]
    with pytest.raises(ValueError, match=what):
        make_heightmaps(color, depth, k, scale, pose, WorkspaceConfig())


@pytest.mark.parametrize("method", ["lowest", "inpaint"])
def test_a_heightmap_with_most_readings_missing_is_not_filled_and_one_with_half_known_is(method) -> None:
    """A covered lens or a camera that lost its depth is no scene to fill in: with fewer than half the cells
    known nothing is filled (and the caller is told); with exactly half known the holes are filled."""
    from flgd.perception import FILL_MIN_VALID, fill_unknown

    assert FILL_MIN_VALID == 0.5
    n = 40
    color = np.full((n, n, 3), 120, np.uint8)
    height = np.full((n, n), 0.02, np.float32)
    for known_rows in (n // 2 - 1, n // 2):  # 47.5 % of the cells known, then 50 %
        unknown = np.zeros((n, n), bool)
        unknown[known_rows:, :] = True
        holed = np.where(unknown, 0.0, height).astype(np.float32)
        out_color, out_height, filled = fill_unknown(color, holed, unknown, method)
        if known_rows < n // 2:
            assert not filled and out_height is holed and out_color is color
            assert np.all(out_height[unknown] == 0.0)
        else:
            assert filled and np.allclose(out_height[unknown], 0.02, atol=1e-3)
