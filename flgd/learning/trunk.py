"""Perception pre-training of the fast network's trunk: our stand-in for the paper's ImageNet weights.

The paper (and VPG) start the Q-network from a DenseNet pre-trained on
ImageNet, so the first grasps are learned on top of features that already
know edges and objects.  No weights may be downloaded here, and the fast
network has no ImageNet counterpart, so this module gives it the same kind
of head start from simulator ground truth: from a labelled heightmap (which
object each pixel shows) the network learns, per pixel, whether it is on an
object, whether it is on a boundary between objects (or object and table),
and how deep inside its object it is: the distance to the nearest pixel
outside the object (an edge pixel counts 1) over the object's largest such
distance -- 1 at its most interior pixel, 1/peak (not 0) on its edge, 0 off
objects; across a 7x7 square 0.25 0.5 0.75 1 0.75 0.5 0.25.  (Kept so: the
shipped trunk was trained on these targets.)  None of that says where or how
to grasp; it is generic instance perception, learned from objects that need
not be the ones the robot later picks (``flgd pretrain`` takes any object set).

A trunk file holds the weights of every layer except the Q-map output and the
value stream; ``load_trunk`` copies into a fresh Q-network whatever of it the
network has with the same name and shape (``fast``: all of it;
``rho-fcn-fast``: the shared encoder and context).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from flgd.learning.networks import FAST_WIDTH, FastQNet, QMapNetwork, normalise, rotate_maps

__all__ = ["TARGET_CHANNELS", "TrunkFileError", "PerceptionNet", "instance_targets", "perception_loss",
           "labelled_batch", "save_trunk", "read_trunk", "load_trunk", "HEAD_PARAMETERS", "TRUNK_FORMAT"]

TARGET_CHANNELS = ("object", "boundary", "interior")
TRUNK_FORMAT = "flgd-trunk-1"
# Q-network layers that the Q-learning task alone defines: never taken from a trunk file.
HEAD_PARAMETERS = ("advantage.", "value.")
TRUNK_VARIANTS = ("fast", "rho-fcn-fast")   # the networks built on the fast trunk
BOUNDARY_RADIUS = 1        # px: a pixel within this distance of another label is on a boundary
BOUNDARY_WEIGHT = 4.0      # boundaries are a small share of the pixels: weight them up in the loss


class TrunkFileError(ValueError):
    """A trunk file that cannot be used; the message names the file and the problem."""


def instance_targets(labels: np.ndarray) -> np.ndarray:
    """Per-pixel targets [3,H,W] float32 (object, boundary, interior) of a label heightmap (0 = no object)."""
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"labels: expected an HxW map, got shape {labels.shape}")
    labels = labels.astype(np.int32)
    k = 2 * BOUNDARY_RADIUS + 1
    kernel = np.ones((k, k), np.uint8)
    as_float = labels.astype(np.float32)
    # a pixel is on a boundary when some neighbour within the radius carries another label
    high = cv2.dilate(as_float, kernel, borderType=cv2.BORDER_REPLICATE)
    low = cv2.erode(as_float, kernel, borderType=cv2.BORDER_REPLICATE)
    boundary = (high != low) & ((high > 0) | (low > 0))
    interior = np.zeros(labels.shape, np.float32)
    for value in np.unique(labels):
        if value == 0:
            continue
        mask = (labels == value).astype(np.uint8)
        dist = cv2.distanceTransform(np.pad(mask, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
        peak = float(dist.max())
        if peak > 0:
            interior[mask > 0] = dist[mask > 0] / peak
    return np.stack([(labels > 0).astype(np.float32), boundary.astype(np.float32), interior])


class PerceptionNet(nn.Module):
    """The fast Q-network's layers with a 3-channel perception output instead of the Q-maps."""

    def __init__(self, width: int = FAST_WIDTH, seed: int | None = None) -> None:
        super().__init__()
        with torch.random.fork_rng(devices=[]):
            if seed is not None:
                torch.manual_seed(seed)
            self.body = FastQNet(rotations=2, width=width)
            self.predict = nn.Conv2d(2 * width, len(TARGET_CHANNELS), 1)

    def forward(self, color: torch.Tensor, height: torch.Tensor) -> torch.Tensor:
        """Normalised colour and height [B,*,H,W] -> logits/values [B,3,H,W] at the input's size."""
        dense, _ = self.body.features(torch.cat([color, height], dim=1))
        return F.interpolate(self.predict(dense), size=color.shape[2:], mode="bilinear", align_corners=False)

    def trunk_state(self) -> dict[str, torch.Tensor]:
        """The weights a Q-network takes over: all of ``body`` but its Q-map output and value stream."""
        return {k: v.detach().clone().contiguous() for k, v in self.body.state_dict().items()
                if not k.startswith(HEAD_PARAMETERS)}


def perception_loss(out: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> dict[str, torch.Tensor]:
    """Loss terms over the pixels that show the workspace (``valid``): object and boundary as logistic
    losses, interior depth as an L1 loss on object pixels."""
    v = valid.float()
    n = v.sum().clamp(min=1.0)
    obj = (F.binary_cross_entropy_with_logits(out[:, 0], target[:, 0], reduction="none") * v).sum() / n
    weight = 1.0 + (BOUNDARY_WEIGHT - 1.0) * target[:, 1]
    bnd = (F.binary_cross_entropy_with_logits(out[:, 1], target[:, 1], weight=weight, reduction="none") * v).sum() / n
    on = v * target[:, 0]
    inner = ((torch.sigmoid(out[:, 2]) - target[:, 2]).abs() * on).sum() / on.sum().clamp(min=1.0)
    return {"object": obj, "boundary": bnd, "interior": inner, "total": obj + bnd + inner}


def labelled_batch(samples: list[tuple[np.ndarray, np.ndarray, np.ndarray]], rotations: list[int],
                   total_rotations: int, stride: int, crop: int | None, rng: np.random.Generator
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(colour, height, targets, valid) for the network: each (colour HxWx3 uint8, height HxW, labels HxW)
    sample turned by its rotation exactly as the Q-network's inputs are, then cropped at random."""
    colors, heights, targets, valids = [], [], [], []
    for (color, height, labels), r in zip(samples, rotations):
        raw = torch.cat([torch.from_numpy(np.ascontiguousarray(color)).float().permute(2, 0, 1) / 255.0,
                         torch.from_numpy(np.nan_to_num(np.asarray(height, np.float32)))[None],
                         torch.from_numpy(instance_targets(labels)),
                         torch.ones(1, *labels.shape)], dim=0)[None]
        turned = rotate_maps(raw, [r], total_rotations, stride, mode="nearest")[0]
        if crop is not None and crop < turned.shape[-1]:
            side = turned.shape[-1]
            top, left = (int(v) for v in rng.integers(0, side - crop + 1, size=2))
            turned = turned[:, top:top + crop, left:left + crop]
        c, h = normalise(turned[None, :3], turned[None, 3:4])
        colors.append(c[0])
        heights.append(h[0])
        targets.append(turned[4:7])
        valids.append(turned[7] > 0.5)
    return torch.stack(colors), torch.stack(heights), torch.stack(targets), torch.stack(valids)


@dataclass(frozen=True)
class TrunkFile:
    tensors: dict[str, torch.Tensor]
    metadata: dict[str, Any]


def save_trunk(path: str | Path, net: PerceptionNet, metadata: dict[str, Any]) -> None:
    """Write a trunk file atomically (safetensors; metadata as JSON strings)."""
    from safetensors.torch import save

    from flgd.atomic_file import write_atomically

    meta = {"format": TRUNK_FORMAT, "width": str(net.body.width), "info": json.dumps(metadata)}
    write_atomically(path, save(net.trunk_state(), metadata=meta), mode=0o644)


def read_trunk(path: str | Path) -> TrunkFile:
    """A trunk file's tensors and metadata; ``TrunkFileError`` naming the file when it is not one."""
    from safetensors import SafetensorError, safe_open

    p = Path(path)
    if not p.is_file():
        raise TrunkFileError(f"trunk file {p}: not found")
    try:
        with safe_open(str(p), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError, ValueError) as exc:
        raise TrunkFileError(f"trunk file {p}: not a readable safetensors file ({exc})") from None
    from flgd.learning.policy_file import first_non_finite

    bad = first_non_finite(tensors, sorted(tensors))
    if bad is not None:  # a trunk that diverged in pretraining would start every fresh network from garbage
        raise TrunkFileError(f"trunk file {p}: {bad}")
    if meta.get("format") != TRUNK_FORMAT:
        raise TrunkFileError(f"trunk file {p}: format {meta.get('format')!r}, expected {TRUNK_FORMAT!r} "
                             "(written by `flgd pretrain`)")
    try:
        info = json.loads(meta.get("info", "{}"))
        width = int(meta["width"])
        if not 2 <= width <= 256:
            raise ValueError(f"width {width}, expected 2..256")
        if not isinstance(info, dict):
            raise ValueError(f"info is a {type(info).__name__}, expected an object")
    except (KeyError, ValueError) as exc:
        raise TrunkFileError(f"trunk file {p}: unreadable metadata ({exc})") from None
    return TrunkFile(tensors=tensors, metadata={**info, "width": width})


def load_trunk(network: QMapNetwork, path: str | Path) -> list[str]:
    """Copy a trunk file's weights into ``network``; returns the names copied.

    Refuses (``TrunkFileError``, network untouched) a file whose tensors do not fit: any name the network
    has with another shape, or a network that shares none of the file's layers.
    """
    trunk = read_trunk(path)
    if network.variant not in TRUNK_VARIANTS:
        raise TrunkFileError(f"trunk file {path}: fits the {' and '.join(TRUNK_VARIANTS)} networks, not "
                             f"{network.variant} (learning.network)")
    own = network.state_dict()
    taken: dict[str, torch.Tensor] = {}
    for name, tensor in trunk.tensors.items():
        if name.startswith(HEAD_PARAMETERS) or name not in own:
            continue
        if own[name].shape != tensor.shape:
            raise TrunkFileError(f"trunk file {path}: {name} has shape {tuple(tensor.shape)}, the "
                                 f"{network.variant} network's has {tuple(own[name].shape)} (trunk width "
                                 f"{trunk.metadata['width']}, network width {getattr(network, 'width', '?')})")
        taken[name] = tensor
    # every layer of a whole trunk of this width that the network has must be in the file: a partial file
    # would leave some perception layers random without anyone knowing
    whole = set(PerceptionNet(width=trunk.metadata["width"]).trunk_state())
    missing = sorted((whole & set(own)) - set(taken))
    if missing:
        raise TrunkFileError(f"trunk file {path}: lacks {len(missing)} tensor(s) of the trunk, e.g. {missing[0]}")
    network.load_state_dict(taken, strict=False)
    return sorted(taken)
