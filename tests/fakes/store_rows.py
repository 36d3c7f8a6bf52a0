"""Small stand-ins for what the cycle stores: a random heightmap and an action-log row."""

from __future__ import annotations

import time

import numpy as np

from flgd.perception import Heightmaps


def random_heightmaps(seed: int, shape=(32, 40)) -> Heightmaps:
    rng = np.random.default_rng(seed)
    height = np.zeros(shape, np.float32)
    height[5:15, 8:20] = rng.uniform(0.01, 0.08, (10, 12)).astype(np.float32)
    color = rng.integers(0, 255, shape + (3,), dtype=np.uint8)
    return Heightmaps(color=color, height=height)


def action_row(step: int, **kw) -> dict:
    row = {"step": step, "time": time.time(), "backend": "test", "outcome": "executed", "primitive": "grasp",
           "kind": "grasp", "row": 1, "col": 2, "rotation": 3, "reward": 1.0, "success": 1, "duration": 0.5,
           "t_capture": 0.01, "t_execute": 0.4}
    row.update(kw)
    return row
