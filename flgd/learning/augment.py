"""Mirror-image augmentation of replayed transitions.

Why: the physics of picking is symmetric under a mirror of the table, but the
network's rotation pipeline is not a source of mirror images (rotating a
scene never produces its reflection), so a reflected transition is new
evidence at no cost to the cell.  A reflection across the heightmap's middle
column maps base x to its mirror about the workspace centre and keeps y, so a
direction u = (cos t, sin t) becomes (-cos t, sin t), the angle pi - t:
rotation index i becomes (R/2 - i) mod R, which needs an even R.  Values do
not change under the mirror, so the target y of a transition is kept.
"""

from __future__ import annotations

import numpy as np

from flgd.actions import Action
from flgd.perception import Heightmaps

__all__ = ["mirror_heightmaps", "mirror_action"]


def mirror_heightmaps(hm: Heightmaps) -> Heightmaps:
    """The scene reflected across the middle column (left-right)."""
    return Heightmaps(color=np.ascontiguousarray(np.asarray(hm.color)[:, ::-1]),
                      height=np.ascontiguousarray(np.asarray(hm.height)[:, ::-1]))


def mirror_action(action: Action, width: int) -> Action:
    """``action`` in the reflected scene of a heightmap ``width`` columns wide."""
    if action.rotations % 2:
        raise ValueError(f"mirror_action: {action.rotations} rotations; a mirror needs an even number")
    rotation = (action.rotations // 2 - action.rotation) % action.rotations
    return Action(action.primitive, action.row, width - 1 - action.col, rotation, action.rotations)
