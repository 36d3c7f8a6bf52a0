"""The Q-map figure and the evaluation summary picture show what they claim (flgd.visualize, report)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from flgd.actions import Action
from flgd.evaluation.metrics import ActionEntry, RunLog
from flgd.evaluation.report import build_report, summary_picture
from flgd.evaluation.scene_sets import SceneSpec
from flgd import visualize
from flgd.visualize import ACTION_COLORS, ActionGlyph, encode_png, heat_color, qmap_figure, qmap_picture

H = W = 64
R = 16


def _scene():
    color = np.full((H, W, 3), 120, dtype=np.uint8)
    height = np.zeros((H, W), dtype=np.float32)
    height[8:56, 8:56] = 0.03
    return color, height


def _spots():
    """Rotation i is hot (1.0) at its own spot, cold (0.0) elsewhere; both channels."""
    q = np.zeros((R, 2, H, W), dtype=np.float32)
    spots = [(12 + 12 * (i // 4), 12 + 12 * (i % 4)) for i in range(R)]
    for i, (r, c) in enumerate(spots):
        q[i, :, r - 3:r + 4, c - 3:c + 4] = 1.0
    return q, spots


def _pixel(fig, box, row, col):
    x, y = fig.to_image(row, col, box, (H, W))
    return fig.image[y, x].astype(int)


def _near(a, b, tol=40):
    return int(np.abs(np.asarray(a, int) - np.asarray(b, int)).max()) <= tol


def test_grid_has_sixteen_tiles_per_channel_in_rotation_order():
    color, height = _scene()
    q, spots = _spots()
    ones = np.ones((H, W), np.uint8)
    fig = qmap_figure(color, height, q, ones, ones, tile=96)
    assert sorted(fig.tiles) == [(ch, i) for ch in (0, 1) for i in range(R)]
    boxes = list(fig.tiles.values())
    for k, (x, y, w, h) in enumerate(boxes):   # inside the image, no two tiles overlap
        assert x >= 0 and y >= 0 and x + w <= fig.image.shape[1] and y + h <= fig.image.shape[0]
        for x2, y2, w2, h2 in boxes[k + 1:]:
            assert x + w <= x2 or x2 + w2 <= x or y + h <= y2 or y2 + h2 <= y
    hot, cold = heat_color(1.0), heat_color(0.0)
    for ch in (0, 1):
        for i, (r, c) in enumerate(spots):
            own = _pixel(fig, fig.tiles[(ch, i)], r, c)
            other = _pixel(fig, fig.tiles[(ch, (i + 5) % R)], r, c)
            # the heat map blends 75 % heat over the grey heightmap: hot at its own spot, cold elsewhere
            assert _near(own, 0.25 * 120 + 0.75 * np.array(hot), 8), (ch, i, own)
            assert _near(other, 0.25 * 120 + 0.75 * np.array(cold), 8), (ch, i, other)


def test_outside_the_mask_the_heightmap_is_dimmed_not_heat():
    color, height = _scene()
    q, spots = _spots()
    mask = np.zeros((H, W), np.uint8)
    mask[:, : W // 2] = 1
    fig = qmap_figure(color, height, q, mask, mask, tile=96)
    r, c = spots[3]                       # column 48: outside the mask
    assert c >= W // 2
    px = _pixel(fig, fig.tiles[(0, 3)], r, c)
    assert _near(px, (72, 72, 72), 6)     # 0.6 x grey 120, no heat colour
    r, c = spots[0]                       # column 12: inside
    assert _near(_pixel(fig, fig.tiles[(0, 0)], r, c), 0.25 * 120 + 0.75 * np.array(heat_color(1.0)), 8)


def test_a_grasp_mask_per_rotation_masks_each_rotation_tile_and_the_greedy_grasp():
    color, height = _scene()
    q, spots = _spots()
    grasp = np.ones((R, H, W), np.uint8)
    grasp[3] = 0                           # rotation 3 allowed nowhere (its fingers would leave the heightmap)
    move = np.ones((H, W), np.uint8)
    fig = qmap_figure(color, height, q, grasp, move, tile=96)
    r, c = spots[3]
    assert _near(_pixel(fig, fig.tiles[(0, 3)], r, c), (72, 72, 72), 6)   # dimmed, no heat
    assert _near(_pixel(fig, fig.tiles[(1, 3)], r, c), 0.25 * 120 + 0.75 * np.array(heat_color(1.0)), 8)
    q[3, 0, r, c] = 5.0                    # the best grasp, at the masked rotation
    q[:, 1] = -1.0
    action = visualize.greedy_action(q, grasp, move, height, 0.01)
    assert action.primitive == "grasp" and action.rotation != 3


@pytest.mark.parametrize("primitive, rotation", [("grasp", 4), ("push", 0), ("shift", 8)])
def test_action_glyph_is_drawn_at_the_pixel_with_the_rotation(primitive, rotation):
    color, height = _scene()
    q = np.zeros((R, 2, H, W), np.float32)
    ones = np.ones((H, W), np.uint8)
    action = Action(primitive, 30, 34, rotation, R)
    glyph = ActionGlyph(opening_px=20.0, push_px=20.0, shift_px=20.0)
    fig = qmap_figure(color, height, q, ones, ones, action=action, tile=96, glyph=glyph)
    plain = qmap_figure(color, height, q, ones, ones, action=None, tile=96, glyph=glyph)
    want = ACTION_COLORS[primitive]
    ux, uy = math.cos(action.angle), math.sin(action.angle)
    for box in (fig.scene, fig.tiles[(action.channel, rotation)]):
        scale = box[2] / W
        centre = fig.to_image(action.row, action.col, box, (H, W))
        assert _near(fig.image[centre[1], centre[0]], want, 10)
        assert not _near(plain.image[centre[1], centre[0]], want, 60)
        # along u: glyph colour 0.4 of the glyph length away from the centre; not across u
        along = (int(round(centre[0] + 0.4 * 20 * scale * ux)), int(round(centre[1] + 0.4 * 20 * scale * uy)))
        across = (int(round(centre[0] - 0.4 * 20 * scale * uy)), int(round(centre[1] + 0.4 * 20 * scale * ux)))
        assert _near(fig.image[along[1], along[0]], want, 40), (box, along)
        assert not _near(fig.image[across[1], across[0]], want, 60), (box, across)
        if primitive == "grasp":   # the closing line runs both ways; a move's arrow only forwards
            back = (int(round(centre[0] - 0.4 * 20 * scale * ux)), int(round(centre[1] - 0.4 * 20 * scale * uy)))
            assert _near(fig.image[back[1], back[0]], want, 40)
        else:
            back = (int(round(centre[0] - 0.6 * 20 * scale * ux)), int(round(centre[1] - 0.6 * 20 * scale * uy)))
            assert not _near(fig.image[back[1], back[0]], want, 60)
    # the chosen tile is framed in white, the others are not
    x, y, w, h = fig.tiles[(action.channel, rotation)]
    assert (fig.image[y + 2, x + w // 2] == 255).all()
    x, y, w, h = fig.tiles[(action.channel, (rotation + 1) % R)]
    assert not (fig.image[y + 2, x + w // 2] == 255).all()


def test_picture_is_the_figure_image_and_encodes_as_png():
    color, height = _scene()
    q, _ = _spots()
    ones = np.ones((H, W), np.uint8)
    a = Action("grasp", 10, 10, 2, R)
    img = qmap_picture(color, height, q, ones, ones, a, caption="hello")
    fig = qmap_figure(color, height, q, ones, ones, a, caption="hello")
    assert np.array_equal(img, fig.image)
    assert fig.tiles[(0, 0)][1] == 22                 # the caption bar shifts every box down
    decoded = cv2.imdecode(np.frombuffer(encode_png(img), np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(decoded, img)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 200


def test_wrong_q_shape_is_a_clear_error():
    color, height = _scene()
    ones = np.ones((H, W), np.uint8)
    with pytest.raises(ValueError, match=r"expected \[R,2,64,64\]"):
        qmap_picture(color, height, np.zeros((R, 2, 32, 32), np.float32), ones, ones)


def _report(completion_runs: int, total: int) -> dict:
    logs = []
    for i in range(total):
        ok = i < completion_runs
        logs.append(RunLog(scene="s", run=i, objects=2, actions=(ActionEntry("grasp", True),
                                                                   ActionEntry("grasp", ok)),
                           objects_left=0 if ok else 1, objects_grasped=2 if ok else 1,
                           end="cleared" if ok else "action-limit"))
    return build_report([(SceneSpec(name="s", objects="blocks", count=2), logs)], policy={"path": "p"},
                        config="c", options={"runs": total}, seconds=1.0)


def test_summary_bars_are_proportional_to_the_rates():
    green = np.array((80, 175, 76))

    def green_pixels(report) -> int:
        img = summary_picture(report)
        return int(np.count_nonzero(np.all(img == green, axis=-1)))

    full, half = green_pixels(_report(4, 4)), green_pixels(_report(2, 4))
    legend = green_pixels(_report(0, 4))   # completion 0: only the legend swatch is green
    assert full > legend > 0
    assert (full - legend) == pytest.approx(2 * (half - legend), rel=0.03)


def test_label_outline_stays_under_its_text():
    """The black outline must sit under the white letters: drawn as one thick string it ran ~10 px past a
    32-character label's end (OpenCV widens thick text), a ghost copy of the label beside it."""
    label = "colour heightmap + chosen action"
    img = np.full((24, 320, 3), 128, dtype=np.uint8)
    visualize._text(img, label, (4, 14))
    width = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.42, 1)[0][0]
    touched = np.nonzero((img != 128).any(axis=(0, 2)))[0]
    assert touched.min() >= 2 and touched.max() <= 4 + width + 2, (touched.min(), touched.max(), width)
    white = (img > 200).all(axis=2)
    dark = (img < 100).all(axis=2)
    assert white.sum() > 100 and dark.sum() > 100  # both the letters and their outline are there
