"""Pictures of what the policy sees: Q-maps over the heightmap, the masks and the chosen action.

Layout of ``qmap_picture`` (one image, drawn with OpenCV):

* left: the 16 rotations of the grasp Q-map as a 4 x 4 grid of heat maps
  blended over the colour heightmap (VPG's way of drawing them); the chosen
  rotation is framed;
* middle: the same for the move Q-map;
* right column: the colour heightmap with the chosen action drawn on it (a
  circle at the pixel, an arrow along u = (cos theta, sin theta): the closing
  direction of a grasp, the travel of a push/shift), the height map, the grasp
  mask and the move mask.

Heat maps are normalised per channel over all rotations (so rotations can be
compared) and are drawn only inside that channel's mask; outside it the colour
heightmap is shown dimmed.  Image rows follow heightmap rows (base y), columns
heightmap columns (base x).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from flgd.actions import Action

__all__ = ["qmap_picture", "encode_png", "write_png", "greedy_action"]

_ACTION_COLOR = {"grasp": (0, 255, 0), "push": (255, 128, 0), "shift": (255, 0, 255)}  # BGR
_TEXT = (255, 255, 255)


def greedy_action(q_maps: np.ndarray, grasp_mask: np.ndarray, move_mask: np.ndarray,
                  height: np.ndarray, shift_height: float) -> Action:
    """The best masked action (used to draw a picture when nothing was decided yet)."""
    q = np.asarray(q_maps, dtype=np.float32).copy()
    q[:, 0][:, grasp_mask == 0] = -np.inf
    q[:, 1][:, move_mask == 0] = -np.inf
    rot, ch, row, col = (int(v) for v in np.unravel_index(int(np.argmax(q)), q.shape))
    prim = "grasp" if ch == 0 else ("shift" if float(height[row, col]) > shift_height else "push")
    return Action(prim, row, col, rot, q.shape[0])


def _bgr(color_rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(color_rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)


def _heat(values: np.ndarray, lo: float, hi: float, mask: np.ndarray, base: np.ndarray) -> np.ndarray:
    span = hi - lo if hi > lo else 1.0
    v = np.nan_to_num((values - lo) / span, nan=0.0, posinf=1.0, neginf=0.0)
    heat = cv2.applyColorMap(np.clip(v * 255.0, 0, 255).astype(np.uint8), cv2.COLORMAP_JET)
    blended = cv2.addWeighted(base, 0.4, heat, 0.6, 0.0)
    dim = (base.astype(np.float32) * 0.6).astype(np.uint8)
    return np.where(mask[..., None] > 0, blended, dim)


def _label(img: np.ndarray, text: str) -> None:
    cv2.putText(img, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, _TEXT, 1, cv2.LINE_AA)


def _draw_action(img: np.ndarray, action: Action, scale: float) -> None:
    color = _ACTION_COLOR.get(action.primitive, (0, 255, 255))
    c = (int(round((action.col + 0.5) * scale)), int(round((action.row + 0.5) * scale)))
    length = 18.0 * scale
    end = (int(round(c[0] + length * math.cos(action.angle))), int(round(c[1] + length * math.sin(action.angle))))
    cv2.circle(img, c, max(3, int(4 * scale)), color, 2, cv2.LINE_AA)
    if action.primitive == "grasp":  # fingers close along u: draw both jaws' approach
        back = (2 * c[0] - end[0], 2 * c[1] - end[1])
        cv2.line(img, back, end, color, 2, cv2.LINE_AA)
    else:
        cv2.arrowedLine(img, c, end, color, 2, cv2.LINE_AA, tipLength=0.3)


def _grid(q: np.ndarray, mask: np.ndarray, base: np.ndarray, chosen: int | None, title: str,
          tile: int) -> np.ndarray:
    r = q.shape[0]
    side = int(math.ceil(math.sqrt(r)))
    finite = q[:, mask > 0] if mask.any() else q.reshape(r, -1)
    finite = finite[np.isfinite(finite)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    small_base = cv2.resize(base, (tile, tile), interpolation=cv2.INTER_AREA)
    small_mask = cv2.resize(mask.astype(np.uint8), (tile, tile), interpolation=cv2.INTER_NEAREST)
    out = np.zeros((side * tile, side * tile, 3), dtype=np.uint8)
    for i in range(r):
        qi = cv2.resize(q[i].astype(np.float32), (tile, tile), interpolation=cv2.INTER_AREA)
        cell = _heat(qi, lo, hi, small_mask, small_base)
        _label(cell, f"{title} {i} ({360.0 * i / r:.1f} deg)")
        if chosen == i:
            cv2.rectangle(cell, (0, 0), (tile - 1, tile - 1), (255, 255, 255), 3)
        y, x = divmod(i, side)
        out[y * tile:(y + 1) * tile, x * tile:(x + 1) * tile] = cell
    return out


def qmap_picture(color: np.ndarray, height: np.ndarray, q_maps: np.ndarray, grasp_mask: np.ndarray,
                 move_mask: np.ndarray, action: Action | None = None, caption: str = "",
                 tile: int = 160) -> np.ndarray:
    """The picture described in the module doc, as a BGR uint8 image."""
    q = np.asarray(q_maps, dtype=np.float32)
    h, w = np.asarray(height).shape
    if q.ndim != 4 or q.shape[1] != 2 or q.shape[2:] != (h, w):
        raise ValueError(f"q_maps: expected [R,2,{h},{w}], got {list(q.shape)}")
    base = _bgr(color)
    chosen_g = action.rotation if action is not None and action.primitive == "grasp" else None
    chosen_m = action.rotation if action is not None and action.primitive != "grasp" else None
    grasp_grid = _grid(q[:, 0], np.asarray(grasp_mask), base, chosen_g, "grasp", tile)
    move_grid = _grid(q[:, 1], np.asarray(move_mask), base, chosen_m, "move", tile)
    grid_h = grasp_grid.shape[0]
    panel = grid_h // 4
    scale = panel / max(h, w)

    scene = cv2.resize(base, (panel, panel), interpolation=cv2.INTER_AREA)
    if action is not None:
        _draw_action(scene, action, scale)
        _label(scene, f"{action.primitive} r{action.row} c{action.col} rot{action.rotation}")
    else:
        _label(scene, "no action")
    hmax = float(np.nanmax(height)) if np.isfinite(height).any() else 0.0
    hnorm = np.clip(np.nan_to_num(height) / (hmax if hmax > 0 else 1.0) * 255.0, 0, 255).astype(np.uint8)
    hpic = cv2.resize(cv2.applyColorMap(hnorm, cv2.COLORMAP_VIRIDIS), (panel, panel),
                      interpolation=cv2.INTER_NEAREST)
    _label(hpic, f"height (max {1000 * hmax:.0f} mm)")
    masks = []
    for name, m in (("grasp mask", grasp_mask), ("move mask", move_mask)):
        pic = cv2.resize(cv2.cvtColor((np.asarray(m) > 0).astype(np.uint8) * 255, cv2.COLOR_GRAY2BGR),
                         (panel, panel), interpolation=cv2.INTER_NEAREST)
        _label(pic, name)
        masks.append(pic)
    column = np.vstack([scene, hpic, *masks])
    column = np.pad(column, ((0, grid_h - column.shape[0]), (0, 0), (0, 0)))
    sep = np.full((grid_h, 4, 3), 255, dtype=np.uint8)
    image = np.hstack([grasp_grid, sep, move_grid, sep, column])
    if caption:
        bar = np.zeros((22, image.shape[1], 3), dtype=np.uint8)
        cv2.putText(bar, caption, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, _TEXT, 1, cv2.LINE_AA)
        image = np.vstack([bar, image])
    return image


def encode_png(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def write_png(path: Any, image: np.ndarray) -> None:
    with open(path, "wb") as f:
        f.write(encode_png(image))
