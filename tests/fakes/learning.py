"""A small learning config (batches of 2, CPU) and a table with a few random blocks, for learner tests."""

from __future__ import annotations

import dataclasses

import numpy as np

from flgd.config import CellConfig
from flgd.perception import Heightmaps

N = 32


def learner_config(**learning) -> CellConfig:
    """Every grasp rotation allowed: the test maps are narrower than the open gripper (exploration.grasp_in_view
    would leave no grasp; tests/test_grasp_view.py covers that rule)."""
    cfg = CellConfig()
    base = dict(batch_size=2, device="cpu")
    base.update(learning)
    return dataclasses.replace(cfg, learning=dataclasses.replace(cfg.learning, **base),
                               exploration=dataclasses.replace(cfg.exploration, grasp_in_view=False))


def block_scene(seed: int) -> Heightmaps:
    rng = np.random.default_rng(seed)
    h = np.zeros((N, N), np.float32)
    for _ in range(3):
        r, c = rng.integers(2, N - 8, 2)
        h[r:r + 6, c:c + 6] = rng.uniform(0.02, 0.05)
    color = np.full((N, N, 3), 90, np.uint8)
    color[h > 0] = rng.integers(0, 255, 3)
    return Heightmaps(color, h)
