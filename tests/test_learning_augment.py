"""Mirror augmentation: the reflected action is the reflected motion, and the learner trains it there."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from flgd.actions import Action
from flgd.config import CellConfig
from flgd.learning.augment import mirror_action, mirror_heightmaps
from flgd.learning.learner import Learner
from flgd.learning.networks import build_network, q_maps
from flgd.learning.replay import PrioritizedReplay, Transition
from flgd.perception import Heightmaps
from flgd.plans import plan_action


def _scene(rows: int = 224, cols: int = 224) -> Heightmaps:
    h = np.zeros((rows, cols), np.float32)
    h[100:130, 40:60] = 0.03  # a block left of centre
    h[20:30, 150:200] = 0.05
    color = np.zeros((rows, cols, 3), np.uint8)
    color[h > 0] = (200, 30, 30)
    color[:, :5] = (0, 0, 255)  # an asymmetric marker
    return Heightmaps(color, h)


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


@pytest.mark.parametrize("primitive,row,col,rotation", [("grasp", 115, 50, 3), ("push", 115, 35, 1),
                                                         ("shift", 25, 160, 12), ("grasp", 25, 190, 0)])
def test_the_mirrored_action_on_the_mirrored_scene_is_the_mirrored_motion(primitive, row, col, rotation):
    cfg = CellConfig()
    ws = cfg.workspace
    scene = _scene()
    a = Action(primitive, row, col, rotation)
    m = mirror_action(a, 224)
    plan, mplan = plan_action(a, scene.height, cfg), plan_action(m, mirror_heightmaps(scene).height, cfg)
    x, y, z = plan.target
    mx, my, mz = mplan.target
    assert mx == pytest.approx(ws.x[0] + ws.x[1] - x, abs=1e-9)
    assert (my, mz) == pytest.approx((y, z), abs=1e-9)
    if primitive == "grasp":  # fingers close along u or -u alike
        assert min(_angle_diff(mplan.angle, math.pi - plan.angle),
                   _angle_diff(mplan.angle, -plan.angle)) == pytest.approx(0.0, abs=1e-9)
    else:  # a push travels along u: its direction is mirrored exactly
        assert _angle_diff(mplan.angle, math.pi - plan.angle) == pytest.approx(0.0, abs=1e-9)
    assert mirror_action(m, 224) == a  # a reflection undone by itself


def test_mirror_heightmaps_reflects_columns_only():
    scene = _scene()
    m = mirror_heightmaps(scene)
    assert np.array_equal(m.height[:, ::-1], scene.height) and np.array_equal(m.color[:, 223], scene.color[:, 0])
    assert not np.array_equal(m.color, scene.color)


def test_an_odd_rotation_count_cannot_be_mirrored():
    with pytest.raises(ValueError, match="even"):
        mirror_action(Action("grasp", 1, 1, 2, rotations=5), 10)


@pytest.mark.parametrize("p,mirrored", [(1.0, True), (0.0, False)])
def test_the_learner_puts_the_gradient_at_the_mirrored_pixel_and_rotations(p, mirrored):
    torch.set_num_threads(1)
    cfg = CellConfig()
    cfg = dataclasses.replace(cfg, learning=dataclasses.replace(cfg.learning, mirror_probability=p, device="cpu"))
    n = 32
    h = np.zeros((n, n), np.float32)
    h[10:16, 4:10] = 0.03
    scene = Heightmaps(np.full((n, n, 3), 80, np.uint8), h)
    lrn = Learner(cfg, build_network("fast", 16, seed=0), PrioritizedReplay(4))
    t = Transition(scene, Action("grasp", 12, 6, 3), 1.0, None, True)
    terms = lrn.loss_terms([t], np.ones(1, np.float32))
    if mirrored:
        assert terms.actions == [Action("grasp", 12, n - 1 - 6, 5)] and terms.rotations == [5, 13]
        trained, pixel = mirror_heightmaps(scene), (12, n - 1 - 6)
    else:
        assert terms.actions == [t.action] and terms.rotations == [3, 11]
        trained, pixel = scene, (12, 6)
    with torch.no_grad():  # the values the loss read are the full Q-maps' at that scene, pixel and rotations
        full = q_maps(lrn.online, trained, 16, rotation_indices=terms.rotations)[:, 0, pixel[0], pixel[1]]
        other = q_maps(lrn.online, mirror_heightmaps(trained), 16, rotation_indices=terms.rotations)
    assert torch.allclose(terms.predicted.detach(), full, atol=1e-6)
    assert not torch.allclose(terms.predicted.detach(), other[:, 0, pixel[0], pixel[1]], atol=1e-4)
