"""FLG's clutter quantization, move and grasp rewards, and Q-map masks (paper III-B, III-D).

All functions take height heightmaps (metres above the table) and the reward
thresholds of the config, so the same numbers judge a simulated and a real cell.

Objects, not pixels: a pixel counts as part of an object only when it belongs to
a connected region (8-neighbourhood) above ``rewards.min_height`` of at least
``rewards.min_object_area``.  A depth camera lifts single pixels of empty table
above any fixed height threshold (a D415 in every frame); unfiltered, such a
speck is a grasp target in rho_g, a 21 px square of push targets in rho_m, and
121 px of "clutter change" in eta.  Every mask below goes through the one
filter, so acting, the learner's bootstrapped targets, the move reward and the
empty-table test can never disagree about what is an object.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from flgd.config import CellConfig, GripperConfig, RewardConfig
from flgd.finger_clearance import fingers_clear
from flgd.side_slope import SIDE_RISE, steep_sides
from flgd.grasp_view import grasps_in_view, moves_in_view

__all__ = [
    "DEFAULT_RESOLUTION",
    "min_region_pixels",
    "keep_regions",
    "object_mask",
    "objects",
    "clutter_map",
    "coverage_change",
    "height_rise",
    "MoveJudgement",
    "judge_move",
    "grasp_reward",
    "grasp_mask",
    "move_mask",
    "action_masks",
    "cell_action_masks",
    "reachable_objects",
]


def _kernel(size: int) -> np.ndarray:
    return np.ones((size, size), dtype=np.uint8)


# metres per heightmap pixel when a caller gives none (the config's default workspace.resolution)
DEFAULT_RESOLUTION = 0.002


def min_region_pixels(rc: RewardConfig, resolution: float = DEFAULT_RESOLUTION) -> int:
    """``rewards.min_object_area`` (mm^2) as a pixel count at ``resolution`` m/px (0 = no filter)."""
    if rc.min_object_area <= 0:
        return 0
    return max(1, int(np.ceil(rc.min_object_area * 1e-6 / (resolution * resolution) - 1e-9)))


def keep_regions(mask: np.ndarray, min_pixels: int) -> np.ndarray:
    """``mask`` (0/1 uint8) without its 8-connected regions of fewer than ``min_pixels`` pixels."""
    mask = np.ascontiguousarray(mask, dtype=np.uint8)
    if min_pixels <= 1 or not mask.any():
        return mask
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    small = stats[:, cv2.CC_STAT_AREA] < min_pixels
    small[0] = True  # label 0 is the background
    if not small[1:].any():
        return mask
    return np.where(small[labels], 0, 1).astype(np.uint8)


def object_mask(height: np.ndarray, min_height: float, min_pixels: int = 0) -> np.ndarray:
    """1 where something stands higher than ``min_height`` above the table in a connected region of at least
    ``min_pixels`` pixels, else 0 (uint8)."""
    return keep_regions((np.nan_to_num(height, nan=0.0) > min_height).astype(np.uint8), min_pixels)


def objects(height: np.ndarray, rc: RewardConfig, resolution: float = DEFAULT_RESOLUTION) -> np.ndarray:
    """The object mask of the module doc: above ``rc.min_height`` and in a region of ``rc.min_object_area``."""
    return object_mask(height, rc.min_height, min_region_pixels(rc, resolution))


def clutter_map(height: np.ndarray, rc: RewardConfig, resolution: float = DEFAULT_RESOLUTION) -> np.ndarray:
    """The clutter quantization map: the object mask, dilated (fills gaps between neighbours)."""
    return cv2.dilate(objects(height, rc, resolution), _kernel(rc.clutter_dilation))


def coverage_change(before: np.ndarray, after: np.ndarray, rc: RewardConfig,
                    resolution: float = DEFAULT_RESOLUTION) -> int:
    """eta(t): change in the number of set pixels of the clutter quantization map."""
    return (int(clutter_map(after, rc, resolution).sum(dtype=np.int64))
            - int(clutter_map(before, rc, resolution).sum(dtype=np.int64)))


def height_rise(before: np.ndarray, after: np.ndarray, delta: float, min_pixels: int = 0) -> int:
    """mu(t): the number of pixels whose height rose by more than ``delta`` (in rising regions of at least
    ``min_pixels`` pixels: a noise speck is no rise)."""
    diff = np.nan_to_num(after, nan=0.0) - np.nan_to_num(before, nan=0.0)
    return int(np.count_nonzero(keep_regions((diff > delta).astype(np.uint8), min_pixels)))


@dataclass(frozen=True)
class MoveJudgement:
    reward: float
    mu: int
    eta: int


def judge_move(before: np.ndarray, after: np.ndarray, rc: RewardConfig,
               resolution: float = DEFAULT_RESOLUTION) -> MoveJudgement:
    """r_m = move_reward (0.5) if mu > tau1 or eta > tau2, else 0."""
    mu = height_rise(before, after, rc.delta, min_region_pixels(rc, resolution))
    eta = coverage_change(before, after, rc, resolution)
    reward = rc.move_reward if (mu > rc.tau1 or eta > rc.tau2) else 0.0
    return MoveJudgement(reward=reward, mu=mu, eta=eta)


def grasp_reward(width: float, gc: GripperConfig) -> float:
    """r_g = 1 if the fingers stayed apart (an object is held) after lifting, else 0."""
    return 1.0 if np.isfinite(width) and width > gc.success_threshold else 0.0


def grasp_mask(height: np.ndarray, rc: RewardConfig, resolution: float = DEFAULT_RESOLUTION) -> np.ndarray:
    """rho_g: where an object is (the object mask)."""
    return objects(height, rc, resolution)


def move_mask(height: np.ndarray, rc: RewardConfig, resolution: float = DEFAULT_RESOLUTION) -> np.ndarray:
    """rho_m: rho_g dilated, so that pushes may start beside objects."""
    return cv2.dilate(grasp_mask(height, rc, resolution), _kernel(rc.move_mask_dilation))


def action_masks(height: np.ndarray, rc: RewardConfig, enabled: bool = True,
                 resolution: float = DEFAULT_RESOLUTION,
                 in_view: tuple[np.ndarray, np.ndarray] | None = None,
                 free: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(rho_g, rho_m) as the agent acts and the learner bootstraps; all ones when ``enabled`` is off
    (the DPEN ablation).  One function, so that the two can never mask differently.

    ``in_view`` (two uint8 [R,H,W], ``flgd.grasp_view``): the grasps and the moves whose fingers stay inside the
    heightmap; given, rho_g and rho_m are per rotation, [R,H,W] (a geometric limit, kept in the DPEN ablation too).
    ``free`` (uint8 [R,H,W], ``flgd.finger_clearance``, ``flgd.side_slope``): the grasps allowed by the grasp
    limits; given, rho_g is limited to them after the objects to push are chosen, so an object none of whose
    grasps is allowed can still be pushed or shifted apart."""
    if enabled:
        rho_g = grasp_mask(height, rc, resolution)
        rho_m = cv2.dilate(rho_g, _kernel(rc.move_mask_dilation))
    else:
        rho_g = np.ones(height.shape, dtype=np.uint8)
        rho_m = rho_g.copy()
    if in_view is not None:
        grasps, moves = in_view
        if grasps.shape[1:] != height.shape or moves.shape[1:] != height.shape:
            raise ValueError(f"in_view: {list(grasps.shape)}, {list(moves.shape)} do not match the heightmap "
                             f"{list(height.shape)}")
        if enabled:   # an object no grasp in view reaches (a sliver at the border) is not pushed at either
            rho_g = reachable_objects(rho_g, grasps)
            rho_m = cv2.dilate(rho_g, _kernel(rc.move_mask_dilation))
        rho_g, rho_m = rho_g[None] & grasps, rho_m[None] & moves
    if free is not None:
        if free.shape[1:] != height.shape:
            raise ValueError(f"free: {list(free.shape)} does not match the heightmap {list(height.shape)}")
        if rho_m.ndim == 2:
            rho_m = np.repeat(rho_m[None], free.shape[0], axis=0)
        rho_g = rho_g & free if rho_g.ndim == 3 else rho_g[None] & free
    return rho_g, rho_m


def reachable_objects(objects_mask: np.ndarray, grasps: np.ndarray) -> np.ndarray:
    """The objects (8-connected regions of ``objects_mask``) with at least one grasp allowed by ``grasps``
    ([R,H,W]) on them: an object pushed over the heightmap's border shows as a sliver no grasp can reach, and a
    push beside it would come down on its unseen part."""
    count, labels = cv2.connectedComponents(np.ascontiguousarray(objects_mask, dtype=np.uint8), connectivity=8)
    if count <= 1:
        return objects_mask
    reached = np.unique(labels[(grasps.max(axis=0) > 0) & (objects_mask > 0)])
    return np.isin(labels, reached[reached > 0]).astype(np.uint8)


def cell_action_masks(height: np.ndarray, config: CellConfig, rotations: int) -> tuple[np.ndarray, np.ndarray]:
    """``action_masks`` with the cell's settings (``exploration.masks``, ``exploration.grasp_in_view``,
    ``exploration.finger_clearance``, ``exploration.side_taper``): what the agent and the learner both call."""
    rows, cols, res, rb = height.shape[0], height.shape[1], config.workspace.resolution, config.robot
    ex = config.exploration
    in_view = ((grasps_in_view(rows, cols, rotations, res, config.gripper.open_width),
                moves_in_view(rows, cols, rotations, res, max(rb.push_distance, rb.shift_distance)))
               if ex.grasp_in_view else None)
    limits: list[np.ndarray] = []   # the grasp limits to try, strictest first
    if ex.finger_clearance > 0.0:
        limits.append(fingers_clear(height, objects(height, config.rewards, res), rotations, res,
                                    config.gripper.open_width, ex.finger_clearance, config.rewards.min_height))
    if ex.side_taper > 0.0:
        upright = steep_sides(height, rotations, res, config.gripper.open_width, rb.grasp_depth, SIDE_RISE,
                              config.safety.min_table_clearance, ex.side_taper)
        limits.insert(0, upright if not limits else limits[0] & upright)
    for allowed in limits:
        rho_g, rho_m = action_masks(height, config.rewards, ex.masks, res, in_view, allowed)
        if _can_act(rho_g, rho_m, ex.grasp_only):
            return rho_g, rho_m
    # no allowed grasp and no move that may free one: these limits predict a poor grasp, they bound nothing, so
    # the cell grasps as it would without them (the side limit first, then the clearance) rather than stop
    rho_g, rho_m = action_masks(height, config.rewards, ex.masks, res, in_view)
    if in_view is None or not ex.last_resort_grasps or _can_act(rho_g, rho_m, ex.grasp_only):
        return rho_g, rho_m
    objects_seen = grasp_mask(height, config.rewards, res)
    if not objects_seen.any():
        return rho_g, rho_m
    # only objects at the border are left: grasp them without the in-view limit (a grasp's descent is guarded,
    # a finger meeting a hidden part stops on it); moves, whose descent is not guarded, stay limited
    return (np.repeat(objects_seen[None], rotations, axis=0),
            np.zeros((rotations,) + height.shape, dtype=np.uint8))


def _can_act(rho_g: np.ndarray, rho_m: np.ndarray, grasp_only: bool) -> bool:
    return bool(rho_g.any() or (not grasp_only and rho_m.any()))
