"""Q-map networks and the rotation pipeline: shapes, dueling, the rotation convention, equivariance,
and that a few updates put the argmax on the rotation that matches a known good grasp angle."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
import torch

from flgd.actions import Action
from flgd.config import CellConfig
from flgd.learning.learner import Learner
from flgd.learning.networks import (VARIANTS, build_network, padded_side, q_maps, rotated_inputs,
                                    unrotate_maps, HEIGHT_MEAN, HEIGHT_STD)
from flgd.learning.replay import PrioritizedReplay, Transition
from flgd.perception import Heightmaps


@pytest.fixture(autouse=True)
def one_thread():
    """The machine is shared: one torch thread avoids spin-wait contention and keeps results stable."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def bar_scene(n: int = 64, angle_deg: float = 45.0, length: float = 30, width: float = 8) -> Heightmaps:
    """One 3 cm high bar centred in an n x n map, its long axis at ``angle_deg`` from +col towards +row."""
    h = np.zeros((n, n), np.float32)
    c = (n - 1) / 2
    box = cv2.boxPoints(((c, c), (length, width), angle_deg))
    cv2.fillPoly(h, [np.round(box).astype(np.int32)], 0.03)
    color = np.full((n, n, 3), 100, np.uint8)
    color[h > 0] = (220, 40, 40)
    return Heightmaps(color, h)


def rot90_scene(hm: Heightmaps) -> Heightmaps:
    """The scene turned by +90 deg in (x = col, y = row): +col goes to +row."""
    return Heightmaps(np.rot90(hm.color, -1).copy(), np.rot90(hm.height, -1).copy())


def rot90_pixel(row: int, col: int, n: int) -> tuple[int, int]:
    index = np.arange(n * n).reshape(n, n)
    r, c = np.argwhere(np.rot90(index, -1) == row * n + col)[0]
    return int(r), int(c)


@pytest.mark.parametrize("variant", VARIANTS)
def test_every_variant_maps_a_batch_to_two_maps_of_the_input_size(variant):
    net = build_network(variant, 16, seed=0).eval()
    color, height = torch.randn(2, 3, 64, 64), torch.randn(2, 1, 64, 64)
    with torch.no_grad():
        q = net(color, height)
    assert q.shape == (2, 2, 64, 64)
    assert torch.isfinite(q).all()
    # Dueling: Q - V has zero mean over both channels and all pixels of each input.
    with torch.no_grad():
        advantage, value = net.advantage_and_value(torch.cat([color, height], 1))
    centred = q - value[:, :, None, None]
    assert torch.allclose(centred.mean(dim=(1, 2, 3)), torch.zeros(2), atol=1e-5)


def test_variants_differ_in_head_as_the_paper_says():
    flg, rho = build_network("densenet121"), build_network("rho-fcn")
    assert flg.variant == "densenet121" and rho.variant == "rho-fcn"
    assert hasattr(flg, "fuse") and not hasattr(rho, "fuse")  # only FLG has the skip fusion
    # Same DenseNet-121 trunk: 6/12/24/16 dense layers, 1024 bottleneck channels.
    assert [len(s[0].layers) for s in flg.trunk.stages] == [6, 12, 24, 16]
    assert flg.trunk.out_channels == 1024 and flg.trunk.skip_channels == 512
    with pytest.raises(ValueError, match="variant"):
        build_network("resnet")
    with pytest.raises(ValueError, match="even"):
        build_network("fast", rotations=15)


def test_q_maps_covers_every_rotation_of_a_non_square_map():
    rng = np.random.default_rng(1)
    hm = Heightmaps(rng.integers(0, 255, (40, 56, 3), dtype=np.uint8), rng.random((40, 56), np.float32) * 0.05)
    net = build_network("fast", 16, seed=0).eval()
    with torch.no_grad():
        q = q_maps(net, hm)
        some = q_maps(net, hm, rotation_indices=[3, 11])
    assert q.shape == (16, 2, 40, 56)
    assert torch.allclose(some, q[[3, 11]], atol=1e-5)
    with pytest.raises(ValueError, match="rotation index"):
        q_maps(net, hm, rotation_indices=[16])


@pytest.mark.parametrize("index", [0, 2, 5, 12])
def test_rotated_input_puts_direction_u_i_on_the_plus_col_axis(index):
    """A bump at centre + 12 px along u_i appears 12 px right of the rotated image's centre."""
    n, rotations = 64, 16
    theta = 2 * math.pi * index / rotations
    c = (n - 1) / 2
    height = np.zeros((n, n), np.float32)
    col, row = c + 12 * math.cos(theta), c + 12 * math.sin(theta)
    height[int(round(row)), int(round(col))] = 0.05
    hm = Heightmaps(np.zeros((n, n, 3), np.uint8), height)
    _, h = rotated_inputs(hm, [index], rotations, stride=8)
    raw = h[0, 0].numpy() * HEIGHT_STD + HEIGHT_MEAN
    side = padded_side(n, n, 8)
    r, k = np.unravel_index(np.argmax(raw), raw.shape)
    cs = (side - 1) / 2
    assert abs(r - cs) <= 1.0 and abs(k - (cs + 12)) <= 1.0


def test_padding_keeps_the_corners_and_back_rotation_inverts():
    """Objects in all four corners survive every rotation (no mass lost), and rotate->unrotate is ~identity."""
    n = 48
    height = np.zeros((n, n), np.float32)
    for r, c in ((0, 0), (0, n - 4), (n - 4, 0), (n - 4, n - 4)):
        height[r:r + 4, c:c + 4] = 0.04
    hm = Heightmaps(np.zeros((n, n, 3), np.uint8), height)
    _, h = rotated_inputs(hm, range(16), 16, stride=8)
    raw = h[:, 0].numpy() * HEIGHT_STD + HEIGHT_MEAN
    mass = raw.reshape(16, -1).sum(axis=1)
    # Bilinear resampling of 4 px blocks changes their mass by a few percent; a cut-off corner would lose 25 %.
    assert np.allclose(mass, height.sum(), rtol=0.05), mass / height.sum()
    smooth = cv2.GaussianBlur(height, (0, 0), 2.0)
    _, h2 = rotated_inputs(Heightmaps(np.zeros((n, n, 3), np.uint8), smooth), range(16), 16, stride=8)
    back = unrotate_maps(h2 * HEIGHT_STD + HEIGHT_MEAN, range(16), 16, n, n)[:, 0].numpy()
    # Exact at multiples of 90 deg; elsewhere two bilinear resamplings smooth a little.  The outermost ring
    # of pixels is excluded: there bilinear sampling mixes in the zero padding.
    error = np.abs(back - smooth[None])
    assert error[::4].max() < 1e-5 * smooth.max()
    assert error[:, 1:-1, 1:-1].max() < 0.05 * smooth.max()


def test_q_maps_are_equivariant_to_a_quarter_turn_of_the_scene():
    """Turning the scene by 90 deg shifts rotation indices by R/4 and moves pixels with it, for any weights."""
    n = 64
    rng = np.random.default_rng(3)
    color = rng.integers(0, 255, (n, n, 3), dtype=np.uint8)
    height = (rng.random((n, n)) * 0.05).astype(np.float32)
    hm = Heightmaps(color, height)
    net = build_network("fast", 16, seed=2).eval()
    with torch.no_grad():
        q = q_maps(net, hm).numpy()
        q90 = q_maps(net, rot90_scene(hm)).numpy()
    expected = np.stack([np.rot90(q[(i - 4) % 16], -1, axes=(1, 2)) for i in range(16)])
    assert np.abs(q90 - expected).max() < 1e-3 * max(1.0, np.abs(q).max())


def test_a_few_updates_move_the_argmax_to_the_rotation_of_the_only_good_grasp():
    """Bar at 45 deg: only closing across it (u at 135 deg, index 6, twin 14) succeeds.

    Training must raise that rotation above the others at the bar's centre, and
    on the quarter-turned scene the argmax must follow to index 10 (twin 2),
    which only holds if the rotation used for training and the one used for
    acting agree.
    """
    scene = bar_scene(64, 45.0)
    cfg = CellConfig()
    cfg = dataclasses.replace(cfg, learning=dataclasses.replace(cfg.learning, learning_rate=1e-3))
    replay = PrioritizedReplay.from_config(cfg.learning)
    for r in range(16):
        replay.add(Transition(scene, Action("grasp", 32, 32, r), 1.0 if r % 8 == 6 else 0.0, None, True))
    net = build_network("fast", 16, seed=0)
    with torch.no_grad():
        before = q_maps(net.eval(), scene)[:, 0, 32, 32].numpy()
    learner = Learner(cfg, net, replay, device="cpu")
    for _ in range(60):
        learner.update()
    trained = learner.snapshot()
    with torch.no_grad():
        after = q_maps(trained, scene)[:, 0, 32, 32].numpy()
        r90, c90 = rot90_pixel(32, 32, 64)
        turned = q_maps(trained, rot90_scene(scene))[:, 0, r90, c90].numpy()
    assert int(np.argmax(after)) % 8 == 6, (before, after)
    others = np.delete(after, [6, 14])
    assert min(after[6], after[14]) > others.max() + 0.3
    assert int(np.argmax(turned)) % 8 == 2, turned
