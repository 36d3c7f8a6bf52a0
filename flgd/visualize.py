"""Pictures of what the policy sees: Q-maps over the heightmap, the masks and the chosen action.

One implementation for ``flgctl snapshot`` (the daemon) and ``flgd eval --save-qmaps``.

Layout of ``qmap_figure`` / ``qmap_picture`` (one image, drawn with OpenCV):

* left: the 16 rotations of the grasp Q-map as a 4 x 4 grid of heat maps
  blended over the colour heightmap (VPG's way of drawing them); the chosen
  rotation is framed in white and carries the action glyph;
* middle: the same for the move Q-map;
* right column: a large colour heightmap with the chosen action drawn on it,
  and below it the height map (cells without a depth reading in magenta),
  the grasp mask, the move mask (the failure memory's
  suppressed regions in red on both) and a legend (the colour scale of each
  channel with its Q range, the action and its Q).

The action glyph is drawn to scale at the action's pixel with its rotation
theta: a grasp is the gripper seen from above -- the closing line along
u = (cos theta, sin theta) as wide as the open fingers, with a finger pad at
each end; a push or shift is an arrow along u as long as its travel.

Heat maps are normalised per channel over all rotations (so rotations can be
compared) and are drawn only inside that channel's mask; outside it the colour
heightmap is shown dimmed.  Image rows follow heightmap rows (base y), columns
heightmap columns (base x).
"""

from __future__ import annotations

import math
import os
import stat
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from flgd.actions import Action, move_kind_at
from flgd.atomic_file import write_atomically

if TYPE_CHECKING:
    from flgd.config import CellConfig

__all__ = ["ActionGlyph", "QmapFigure", "qmap_figure", "qmap_picture", "encode_png", "write_png",
           "output_mode", "greedy_action", "ACTION_COLORS", "heat_color"]

ACTION_COLORS = {"grasp": (40, 255, 40), "push": (0, 160, 255), "shift": (255, 60, 255)}  # BGR
_TEXT = (255, 255, 255)
_OUTLINE = (0, 0, 0)
_FRAME = (255, 255, 255)
_UNKNOWN = (255, 0, 255)     # BGR magenta: no depth reading
_SUPPRESSED = (40, 40, 220)  # BGR red: the failure memory's regions


@dataclass(frozen=True)
class ActionGlyph:
    """Glyph sizes in heightmap pixels (defaults: the RG2 and the shipped sim config at 2 mm/px)."""

    opening_px: float = 42.5   # open finger width 0.085 m
    push_px: float = 50.0      # push travel 0.10 m
    shift_px: float = 30.0     # shift travel 0.06 m

    @classmethod
    def from_config(cls, config: CellConfig) -> "ActionGlyph":
        """Sizes of ``config`` (a CellConfig): gripper opening, push and shift travel over the resolution."""
        res = float(config.workspace.resolution)
        return cls(opening_px=config.gripper.open_width / res, push_px=config.robot.push_distance / res,
                   shift_px=config.robot.shift_distance / res)

    def length(self, primitive: str) -> float:
        return {"grasp": self.opening_px, "push": self.push_px}.get(primitive, self.shift_px)


@dataclass
class QmapFigure:
    """The picture and where its parts are (x, y, width, height in image pixels), for callers and tests."""

    image: np.ndarray
    tiles: dict[tuple[int, int], tuple[int, int, int, int]] = field(default_factory=dict)  # (channel, rot)
    scene: tuple[int, int, int, int] = (0, 0, 0, 0)
    q_range: dict[int, tuple[float, float]] = field(default_factory=dict)  # channel -> (lo, hi)

    def to_image(self, heightmap_row: float, heightmap_col: float, box: tuple[int, int, int, int],
                 shape: tuple[int, int]) -> tuple[int, int]:
        """Image (x, y) of a heightmap pixel centre inside ``box`` (a tile or the scene view)."""
        x, y, w, h = box
        return (int(round(x + (heightmap_col + 0.5) * w / shape[1])),
                int(round(y + (heightmap_row + 0.5) * h / shape[0])))


def greedy_action(q_maps: np.ndarray, grasp_mask: np.ndarray, move_mask: np.ndarray,
                  height: np.ndarray, shift_height: float) -> Action:
    """The best masked action (used to draw a picture when nothing was decided yet)."""
    q = np.asarray(q_maps, dtype=np.float32).copy()
    q[:, 0][np.broadcast_to(grasp_mask, q.shape[:1] + q.shape[2:]) == 0] = -np.inf   # [H,W] or per rotation
    q[:, 1][np.broadcast_to(move_mask, q.shape[:1] + q.shape[2:]) == 0] = -np.inf
    rot, ch, row, col = (int(v) for v in np.unravel_index(int(np.argmax(q)), q.shape))
    prim = "grasp" if ch == 0 else move_kind_at(float(height[row, col]), shift_height)
    return Action(prim, row, col, rot, q.shape[0])


def heat_color(fraction: float) -> tuple[int, int, int]:
    """BGR of the heat-map colour scale (JET) at ``fraction`` of the channel's Q range."""
    v = np.array([[int(np.clip(round(fraction * 255.0), 0, 255))]], dtype=np.uint8)
    return tuple(int(c) for c in cv2.applyColorMap(v, cv2.COLORMAP_JET)[0, 0])


def _bgr(color_rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(color_rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)


def _heat(values: np.ndarray, lo: float, hi: float, mask: np.ndarray, base: np.ndarray) -> np.ndarray:
    span = hi - lo if hi > lo else 1.0
    v = np.nan_to_num((values - lo) / span, nan=0.0, posinf=1.0, neginf=0.0)
    heat = cv2.applyColorMap(np.clip(v * 255.0, 0, 255).astype(np.uint8), cv2.COLORMAP_JET)
    blended = cv2.addWeighted(base, 0.25, heat, 0.75, 0.0)
    dim = (base.astype(np.float32) * 0.6).astype(np.uint8)
    return np.where(mask[..., None] > 0, blended, dim)


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.42) -> None:
    """White text with a black outline: readable on any heat map or heightmap.

    The outline is drawn glyph by glyph at the thin text's glyph positions: OpenCV widens the advance of
    thick text, so a whole outlined string drifts right of its fill and shows as a second, ghost label.
    """
    font = cv2.FONT_HERSHEY_SIMPLEX
    x, y = org
    for i, ch in enumerate(text):
        if ch.isspace():
            continue
        dx = cv2.getTextSize(text[:i], font, scale, 1)[0][0] - 1 if i else 0
        cv2.putText(img, ch, (x + dx, y), font, scale, _OUTLINE, 3, cv2.LINE_AA)
    cv2.putText(img, text, org, font, scale, _TEXT, 1, cv2.LINE_AA)


def _draw_action(img: np.ndarray, action: Action, centre: tuple[int, int], scale: float,
                 glyph: ActionGlyph) -> None:
    """The glyph described in the module doc, centred at image point ``centre``; ``scale`` = image px per
    heightmap px."""
    color = ACTION_COLORS.get(action.primitive, (0, 255, 255))
    ux, uy = math.cos(action.angle), math.sin(action.angle)
    length = glyph.length(action.primitive) * scale
    cx, cy = centre
    thick = max(2, int(round(scale)))
    if action.primitive == "grasp":
        half = length / 2.0
        a = (int(round(cx - half * ux)), int(round(cy - half * uy)))
        b = (int(round(cx + half * ux)), int(round(cy + half * uy)))
        pad = max(4.0, 0.22 * length)   # finger pads, perpendicular to the closing line
        px, py = -uy * pad / 2.0, ux * pad / 2.0
        for colour, extra in ((_OUTLINE, 2), (color, 0)):
            cv2.line(img, a, b, colour, thick + extra, cv2.LINE_AA)
            for end in (a, b):
                p0 = (int(round(end[0] - px)), int(round(end[1] - py)))
                p1 = (int(round(end[0] + px)), int(round(end[1] + py)))
                cv2.line(img, p0, p1, colour, thick + 2 + extra, cv2.LINE_AA)
    else:
        end = (int(round(cx + length * ux)), int(round(cy + length * uy)))
        for colour, extra in ((_OUTLINE, 2), (color, 0)):
            cv2.arrowedLine(img, (cx, cy), end, colour, thick + extra, cv2.LINE_AA, tipLength=0.3)
    radius = max(3, int(round(2.5 * scale)))
    cv2.circle(img, centre, radius + 1, _OUTLINE, -1, cv2.LINE_AA)
    cv2.circle(img, centre, radius, color, -1, cv2.LINE_AA)


def _q_range(q: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    r = q.shape[0]
    if mask.ndim == 3:   # per rotation
        values = q[mask > 0] if mask.any() else q.reshape(r, -1)
    else:
        values = q[:, mask > 0] if mask.any() else q.reshape(r, -1)
    values = values[np.isfinite(values)]
    return (float(values.min()), float(values.max())) if values.size else (0.0, 1.0)


def _grid(q: np.ndarray, mask: np.ndarray, base: np.ndarray, q_range: tuple[float, float], title: str,
          tile: int) -> np.ndarray:
    r = q.shape[0]
    side = int(math.ceil(math.sqrt(r)))
    lo, hi = q_range
    small_base = cv2.resize(base, (tile, tile), interpolation=cv2.INTER_AREA)
    masks = mask if mask.ndim == 3 else np.broadcast_to(mask, q.shape)   # [H,W] or per rotation
    out = np.zeros((side * tile, side * tile, 3), dtype=np.uint8)
    for i in range(r):
        qi = cv2.resize(q[i].astype(np.float32), (tile, tile), interpolation=cv2.INTER_AREA)
        small_mask = cv2.resize(masks[i].astype(np.uint8), (tile, tile), interpolation=cv2.INTER_NEAREST)
        cell = _heat(qi, lo, hi, small_mask, small_base)
        cell[:19] = (cell[:19].astype(np.uint16) * 2 // 5).astype(np.uint8)  # dark strip under the label
        _text(cell, f"{title} {i}  {360.0 * i / r:.1f} deg", (4, 14))
        cv2.rectangle(cell, (0, 0), (tile - 1, tile - 1), (40, 40, 40), 1)
        y, x = divmod(i, side)
        out[y * tile:(y + 1) * tile, x * tile:(x + 1) * tile] = cell
    return out


def _legend(width: int, height: int, q_range: dict[int, tuple[float, float]], action: Action | None,
            q_value: float | None) -> np.ndarray:
    panel = np.full((height, width, 3), 24, dtype=np.uint8)
    bar = cv2.applyColorMap(np.tile(np.linspace(0, 255, width - 16).astype(np.uint8), (12, 1)),
                            cv2.COLORMAP_JET)
    y = 18
    for channel, name in ((0, "grasp Q"), (1, "move Q")):
        lo, hi = q_range[channel]
        _text(panel, name, (6, y), 0.4)
        panel[y + 5:y + 17, 8:width - 8] = bar
        _text(panel, f"{lo:.3g}", (6, y + 32), 0.38)
        label = f"{hi:.3g}"
        (tw, _), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.38, 1)
        _text(panel, label, (width - 8 - tw, y + 32), 0.38)
        y += 48
    if action is not None:
        _text(panel, f"{action.primitive} at r{action.row} c{action.col}", (6, y + 4), 0.4)
        q_text = "" if q_value is None or not math.isfinite(q_value) else f"  Q {q_value:.3g}"
        _text(panel, f"rot {action.rotation} ({math.degrees(action.angle):.1f} deg){q_text}", (6, y + 22), 0.4)
    else:
        _text(panel, "no action", (6, y + 4), 0.4)
    return panel


def qmap_figure(color: np.ndarray, height: np.ndarray, q_maps: np.ndarray, grasp_mask: np.ndarray,
                move_mask: np.ndarray, action: Action | None = None, caption: str = "", tile: int = 160,
                glyph: ActionGlyph | None = None, unknown: np.ndarray | None = None,
                suppressed: np.ndarray | None = None) -> QmapFigure:
    """The picture described in the module doc (BGR uint8) and the boxes of its tiles and scene view.

    ``unknown`` (bool [H,W]): cells without a depth reading (filled or not), drawn magenta on the height panel; ``suppressed`` (uint8 [H,W]): the failure memory's regions, drawn red on both masks."""
    q = np.asarray(q_maps, dtype=np.float32)
    height = np.asarray(height, dtype=np.float32)
    h, w = height.shape
    if q.ndim != 4 or q.shape[1] != 2 or q.shape[2:] != (h, w):
        raise ValueError(f"q_maps: expected [R,2,{h},{w}], got {list(q.shape)}")
    if action is not None and action.rotation >= q.shape[0]:
        raise ValueError(f"action rotation {action.rotation} outside the {q.shape[0]} rotations of q_maps")
    glyph = glyph or ActionGlyph()
    base = _bgr(color)
    masks = (np.asarray(grasp_mask), np.asarray(move_mask))
    q_range = {ch: _q_range(q[:, ch], masks[ch]) for ch in (0, 1)}
    grids = [_grid(q[:, ch], masks[ch], base, q_range[ch], ("grasp", "move")[ch], tile) for ch in (0, 1)]
    grid_h = grids[0].shape[0]
    side = grid_h // tile
    sep = 4
    top = 22 if caption else 0

    # right column: the scene view (two tiles square) over a 2 x 2 block of small panels
    view = 2 * tile
    scene = cv2.resize(base, (view, view), interpolation=cv2.INTER_AREA)
    scene[:19] = (scene[:19].astype(np.uint16) * 2 // 5).astype(np.uint8)
    _text(scene, "colour heightmap + chosen action", (4, 14))
    hmax = float(np.nanmax(height)) if np.isfinite(height).any() else 0.0
    hnorm = np.clip(np.nan_to_num(height) / (hmax if hmax > 0 else 1.0) * 255.0, 0, 255).astype(np.uint8)
    hcolor = cv2.applyColorMap(hnorm, cv2.COLORMAP_VIRIDIS)
    n_unknown = 0
    if unknown is not None and np.shape(unknown) == (h, w):
        hcolor[np.asarray(unknown, dtype=bool)] = _UNKNOWN
        n_unknown = int(np.count_nonzero(unknown))
    hpic = cv2.resize(hcolor, (tile, tile), interpolation=cv2.INTER_NEAREST)
    _text(hpic, f"height (max {1000 * hmax:.0f} mm)", (4, 14))
    if n_unknown:
        _text(hpic, f"no reading: {n_unknown} px", (4, tile - 6))
    held = None if suppressed is None or np.shape(suppressed) != (h, w) else np.asarray(suppressed) > 0
    mask_pics = []
    for name, m in (("grasp mask", masks[0].max(axis=0) if masks[0].ndim == 3 else masks[0]),
                    ("move mask", masks[1].max(axis=0) if masks[1].ndim == 3 else masks[1])):
        grey = np.where(np.asarray(m) > 0, np.uint8(200), np.uint8(30)).astype(np.uint8)
        small = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
        if held is not None and held.any():
            small[held] = _SUPPRESSED
        pic = cv2.resize(small, (tile, tile), interpolation=cv2.INTER_NEAREST)
        _text(pic, name, (4, 14))
        if held is not None and held.any():
            _text(pic, "red: failed here", (4, tile - 6))
        mask_pics.append(pic)
    q_value = None
    if action is not None:
        q_value = float(q[action.rotation, action.channel, action.row, action.col])
    legend = _legend(tile, tile, q_range, action, q_value)
    column = np.vstack([scene, np.hstack([hpic, mask_pics[0]]), np.hstack([mask_pics[1], legend])])
    full_h = max(grid_h, column.shape[0])
    column = np.pad(column, ((0, full_h - column.shape[0]), (0, 0), (0, 0)))
    grids = [np.pad(g, ((0, full_h - grid_h), (0, 0), (0, 0))) for g in grids]
    white = np.full((full_h, sep, 3), 255, dtype=np.uint8)
    image = np.ascontiguousarray(np.hstack([grids[0], white, grids[1], white, column]))
    col_x = 2 * (grid_h + sep)
    figure = QmapFigure(image=image, scene=(col_x, top, view, view), q_range=q_range)
    for ch in (0, 1):
        x0 = ch * (grid_h + sep)
        for i in range(q.shape[0]):
            y, x = divmod(i, side)
            figure.tiles[(ch, i)] = (x0 + x * tile, top + y * tile, tile, tile)

    if caption:
        bar = np.zeros((top, image.shape[1], 3), dtype=np.uint8)
        cv2.putText(bar, caption, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, _TEXT, 1, cv2.LINE_AA)
        image = np.vstack([bar, image])
        figure.image = image
    if action is not None:
        tx, ty, tw, th = figure.tiles[(action.channel, action.rotation)]
        cv2.rectangle(image, (tx + 1, ty + 1), (tx + tw - 2, ty + th - 2), _FRAME, 3)
        _draw_action(image, action, figure.to_image(action.row, action.col, figure.tiles[(action.channel,
                     action.rotation)], (h, w)), tw / w, glyph)
        _draw_action(image, action, figure.to_image(action.row, action.col, figure.scene, (h, w)), view / w,
                     glyph)
    return figure


def qmap_picture(color: np.ndarray, height: np.ndarray, q_maps: np.ndarray, grasp_mask: np.ndarray,
                 move_mask: np.ndarray, action: Action | None = None, caption: str = "",
                 tile: int = 160, glyph: ActionGlyph | None = None, unknown: np.ndarray | None = None,
                 suppressed: np.ndarray | None = None) -> np.ndarray:
    """The picture of ``qmap_figure`` alone, as a BGR uint8 image."""
    return qmap_figure(color, height, q_maps, grasp_mask, move_mask, action, caption, tile, glyph, unknown,
                       suppressed).image


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of a BGR (or grey) uint8 image; ValueError if OpenCV cannot encode it."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def output_mode(path: str | os.PathLike) -> int:
    """Permission bits for an output file about to be replaced atomically: the existing file's, else
    rw-r--r-- (what open() gives under the usual umask), not the temp file's 0600, so that a report
    stays readable by whoever could read it before."""
    try:
        return stat.S_IMODE(os.stat(path).st_mode)
    except FileNotFoundError:
        return 0o644


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write ``image`` as PNG atomically: an interrupted write leaves the old file (or none), never half
    a picture."""
    write_atomically(path, encode_png(image), mode=output_mode(path))
