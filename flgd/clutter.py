"""FLG's clutter quantization, move and grasp rewards, and Q-map masks (paper III-B, III-D).

All functions take height heightmaps (metres above the table) and the reward
thresholds of the config, so the same numbers judge a simulated and a real cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from flgd.config import GripperConfig, RewardConfig

__all__ = [
    "object_mask",
    "clutter_map",
    "coverage_change",
    "height_rise",
    "MoveJudgement",
    "judge_move",
    "grasp_reward",
    "grasp_mask",
    "move_mask",
    "action_masks",
]


def _kernel(size: int) -> np.ndarray:
    return np.ones((size, size), dtype=np.uint8)


def object_mask(height: np.ndarray, min_height: float) -> np.ndarray:
    """1 where something stands higher than ``min_height`` above the table, else 0 (uint8)."""
    return (np.nan_to_num(height, nan=0.0) > min_height).astype(np.uint8)


def clutter_map(height: np.ndarray, rc: RewardConfig) -> np.ndarray:
    """The clutter quantization map: binarised heightmap, dilated (fills gaps between neighbours)."""
    return cv2.dilate(object_mask(height, rc.min_height), _kernel(rc.clutter_dilation))


def coverage_change(before: np.ndarray, after: np.ndarray, rc: RewardConfig) -> int:
    """eta(t): change in the number of set pixels of the clutter quantization map."""
    return int(clutter_map(after, rc).sum(dtype=np.int64)) - int(clutter_map(before, rc).sum(dtype=np.int64))


def height_rise(before: np.ndarray, after: np.ndarray, delta: float) -> int:
    """mu(t): the number of pixels whose height rose by more than ``delta``."""
    diff = np.nan_to_num(after, nan=0.0) - np.nan_to_num(before, nan=0.0)
    return int(np.count_nonzero(diff > delta))


@dataclass(frozen=True)
class MoveJudgement:
    reward: float
    mu: int
    eta: int


def judge_move(before: np.ndarray, after: np.ndarray, rc: RewardConfig) -> MoveJudgement:
    """r_m = move_reward (0.5) if mu > tau1 or eta > tau2, else 0."""
    mu = height_rise(before, after, rc.delta)
    eta = coverage_change(before, after, rc)
    reward = rc.move_reward if (mu > rc.tau1 or eta > rc.tau2) else 0.0
    return MoveJudgement(reward=reward, mu=mu, eta=eta)


def grasp_reward(width: float, gc: GripperConfig) -> float:
    """r_g = 1 if the fingers stayed apart (an object is held) after lifting, else 0."""
    return 1.0 if np.isfinite(width) and width > gc.success_threshold else 0.0


def grasp_mask(height: np.ndarray, rc: RewardConfig) -> np.ndarray:
    """rho_g: where an object is (height above the workspace minimum)."""
    return object_mask(height, rc.min_height)


def move_mask(height: np.ndarray, rc: RewardConfig) -> np.ndarray:
    """rho_m: rho_g dilated, so that pushes may start beside objects."""
    return cv2.dilate(grasp_mask(height, rc), _kernel(rc.move_mask_dilation))


def action_masks(height: np.ndarray, rc: RewardConfig, enabled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(rho_g, rho_m) as the agent acts and the learner bootstraps; all ones when ``enabled`` is off
    (the DPEN ablation).  One function, so that the two can never mask differently."""
    if enabled:
        return grasp_mask(height, rc), move_mask(height, rc)
    ones = np.ones(height.shape, dtype=np.uint8)
    return ones, ones.copy()
