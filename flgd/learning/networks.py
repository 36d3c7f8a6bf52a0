"""Q-map networks (paper III-C) and the rotation pipeline that ties their outputs to actions.

A network maps one rotated colour + height heightmap to a dueling dual-channel
dense map (channel 0 grasp, 1 move) at the input's resolution.  ``q_maps``
rotates the heightmap by each theta_i = 2*pi*i/R, runs all rotations as one
batch and rotates the outputs back, so that ``q[i, ch, row, col]`` is the value
of primitive ``ch`` at heightmap pixel (row, col) with direction
u_i = (cos theta_i, sin theta_i) in (x = col, y = row).

Rotation convention (it ties Q-maps to plans): the input for rotation i is
turned so that u_i becomes the +col axis of the rotated image, so the network
always "closes the gripper / pushes along its own x axis".  The rotated image
is a square of side >= the heightmap's diagonal (rounded up to the network's
stride), sampled with zero padding outside the heightmap, so no corner of the
heightmap is ever cut off; the back-rotation samples the network output
directly at every original pixel, so no separate pad/crop step exists.  Zero
padding is applied to raw values, i.e. the padding looks like a black, empty
table (height 0), before normalisation.

Dueling: Q = V + A - mean(A), where the mean is taken per network input (one
rotation of one state) over both channels and every pixel of the rotated
square.  Taking it per rotation keeps each rotation's Q computable on its own,
which is what lets the learner forward only the executed rotation instead of
all R.  V is a scalar per input from globally pooled bottleneck features.

Variants (``VARIANTS``):

* ``densenet121`` - paper-faithful: a DenseNet-121 trunk (growth 32, blocks
  6/12/24/16, written here in plain torch because torchvision cannot be used),
  one trunk over the 4-channel RGB-height input; head: 1x1 conv + ReLU + BN,
  x4 bilinear up, concat with the stride-8 DenseNet feature (output of dense
  block 2, the skip), 3x3 conv + ReLU + BN, 1x1 conv to the two advantage maps,
  x4 bilinear up (stride 2), and a final bilinear resize to the input size
  (the paper gets the last x2 by feeding a x2-upsampled heightmap, as VPG does;
  resizing the output instead is 4x cheaper).
* ``rho-fcn`` - the VPG-style head of the paper's rho-FCN baseline: the same
  trunk, BN-ReLU-1x1 conv-BN-ReLU-1x1 conv on the stride-32 bottleneck and x16
  bilinear upsampling, no skip.  It keeps the dueling value stream so that the
  comparison isolates the head.
* ``rho-fcn-fast`` - the rho-FCN head on the ``fast`` trunk, so that the
  FLG / DPEN / rho-FCN comparison (``flgd bench learning``) runs on one CPU-
  feasible trunk and isolates the head and the masks (the DenseNet ``rho-fcn``
  costs about 4 s per decision here, far too slow to train).  It keeps what
  the paper says distinguishes rho-FCN: the Q-maps come from a coarse
  bottleneck upsampled x16 bilinearly, with no skip.  Trunk = ``fast``'s
  encoder and dilated context (stride 8) plus one more stride-2 3x3 conv
  stage (4w -> 8w, stride 16); head = BN-ReLU-1x1 conv-BN-ReLU-1x1 conv to two
  maps, x16 bilinear up; dueling value from the pooled bottleneck.
* ``fast`` (the default) - a small encoder-decoder for CPU-only cell PCs, chosen
  by measurement.  Three stride-2 3x3 convs (4->w->2w->4w channels, stride 8),
  a dilated residual context block (dilations 2 and 4; receptive field about
  111 px = 22 cm, wider than the 8.5 cm gripper), then the FLG head in
  miniature: 1x1 conv + ReLU + BN, x2 bilinear up, concat with the stride-4
  encoder feature (skip), 3x3 conv + ReLU + BN, 1x1 conv to two maps and x4
  bilinear up to the input size.

How ``fast`` was chosen (``flgd bench latency --learning --threads 1``, 2-core
CPU shared with other jobs; the fast rows from one run, densenet121 from a
second run straight after).  Learning = a synthetic
task on 64 x 64 maps (one bar per scene at a random multiple of 22.5 deg; a
grasp succeeds only on the bar's middle with the fingers closing across it),
64 training scenes x 12 labelled grasps, the real Learner (prioritized replay,
Huber, Adam, lr 5e-4, batch 4); score = greedy masked grasp success on 32
held-out scenes, mean of 2 seeds (densenet121: 1 seed).  Decision = 16
rotations x 2 maps x 224 x 224 incl. masks and argmax, one torch thread.

    network       success @100  @200  @300 updates   ms/update (64 px)   decision (224 px)
    fast w=8          0.13      0.42  0.59               19                0.116 s
    fast w=12         0.50      0.75  0.89               20                0.200 s
    fast w=16         0.42      0.72  0.84               37                0.353 s
    fast w=24         0.58      0.73  0.92               53                0.495 s
    densenet121       0.69      0.53  0.84              564                4.76 s

Width 12 learns almost as fast per update as width 24 and as the DenseNet,
at a fraction of the cost per update, and is the widest that stays inside the
0.25 s decision budget with margin on a loaded machine; width 8 learns
clearly slower.  (The machine was loaded during that run; see the latency
benchmark for quiet-machine numbers.)
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

if TYPE_CHECKING:
    from flgd.perception import Heightmaps

__all__ = [
    "VARIANTS",
    "FAST_WIDTH",
    "QMapNetwork",
    "FastQNet",
    "RhoFcnFastQNet",
    "DenseNetQNet",
    "build_network",
    "q_maps",
    "q_at_pixels",
    "rotated_inputs",
    "rotate_maps",
    "unrotate_maps",
    "normalise",
    "padded_side",
]

VARIANTS: tuple[str, ...] = ("fast", "densenet121", "rho-fcn", "rho-fcn-fast")

# Normalisation: colour to about zero mean / unit spread, heights like VPG (mean 1 cm, spread 3 cm).
COLOR_MEAN = (0.485, 0.456, 0.406)
COLOR_STD = (0.229, 0.224, 0.225)
HEIGHT_MEAN = 0.01
HEIGHT_STD = 0.03

# Channel width of the fast variant (chosen by benchmarks/latency.py --learning).
FAST_WIDTH = 12


class QMapNetwork(nn.Module):
    """Base of every variant: dueling combination and resizing to the input size.

    Subclasses implement ``advantage_and_value(x) -> (A [B,2,h,w], V [B,1])`` on
    the normalised 4-channel input x = [colour, height].
    """

    variant: str = ""
    stride: int = 1

    def __init__(self, rotations: int) -> None:
        super().__init__()
        if not (isinstance(rotations, int) and rotations > 0 and rotations % 2 == 0):
            raise ValueError(f"rotations: got {rotations!r}, expected a positive even integer "
                             "(a grasp's theta+pi twin must be a rotation index too)")
        self.rotations = rotations

    def architecture(self) -> dict[str, Any]:
        """Constructor arguments recorded in policy files so that a loader rebuilds the same net."""
        return {"variant": self.variant, "rotations": self.rotations}

    def advantage_and_value(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raise TypeError(f"{type(self).__name__} must implement advantage_and_value")

    def forward(self, color: torch.Tensor, height: torch.Tensor) -> torch.Tensor:
        """Normalised colour [B,3,H,W] and height [B,1,H,W] -> Q [B,2,H,W] (0 grasp, 1 move)."""
        if color.dim() != 4 or color.shape[1] != 3 or height.dim() != 4 or height.shape[1] != 1 \
                or color.shape[0] != height.shape[0] or color.shape[2:] != height.shape[2:]:
            raise ValueError(f"expected colour [B,3,H,W] and height [B,1,H,W], got {tuple(color.shape)} "
                             f"and {tuple(height.shape)}")
        size = color.shape[2:]
        advantage, value = self.advantage_and_value(torch.cat([color, height], dim=1))
        if advantage.shape[2:] != size:
            advantage = F.interpolate(advantage, size=size, mode="bilinear", align_corners=False)
        return value[:, :, None, None] + advantage - advantage.mean(dim=(1, 2, 3), keepdim=True)


def _conv_bn_relu(cin: int, cout: int, k: int = 3, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    pad = dilation * (k // 2)
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, pad, dilation=dilation, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def _conv_relu_bn(cin: int, cout: int, k: int) -> nn.Sequential:
    """The paper's head order: convolution, ReLU, batch normalisation."""
    return nn.Sequential(nn.Conv2d(cin, cout, k, 1, k // 2), nn.ReLU(inplace=True), nn.BatchNorm2d(cout))


class _DilatedContext(nn.Module):
    """Residual block of two dilated 3x3 convs: a wide receptive field at stride 8 for little compute."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.a = _conv_bn_relu(channels, channels, dilation=2)
        self.b = nn.Sequential(nn.Conv2d(channels, channels, 3, 1, 4, dilation=4, bias=False),
                               nn.BatchNorm2d(channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.b(self.a(x)))


class _FastTrunkNetwork(QMapNetwork):
    """The stride-8 encoder and dilated context shared by ``fast`` and ``rho-fcn-fast``, so that their comparison
    isolates the head.  Its layers are attributes of the network itself, as policy files name their parameters."""

    def __init__(self, rotations: int, width: int) -> None:
        super().__init__(rotations)
        if not (isinstance(width, int) and 2 <= width <= 256):
            raise ValueError(f"width: got {width!r}, expected an integer 2..256")
        self.width = width
        self.enc1 = _conv_bn_relu(4, width, stride=2)
        self.enc2 = _conv_bn_relu(width, 2 * width, stride=2)
        self.enc3 = _conv_bn_relu(2 * width, 4 * width, stride=2)
        self.context = _DilatedContext(4 * width)

    def architecture(self) -> dict[str, Any]:
        return {**super().architecture(), "width": self.width}


class FastQNet(_FastTrunkNetwork):
    """The CPU default: stride-8 encoder, dilated context, FLG-style skip head (see module doc)."""

    variant = "fast"
    stride = 8

    def __init__(self, rotations: int = 16, width: int = FAST_WIDTH) -> None:
        super().__init__(rotations, width)
        w = width
        self.squeeze = _conv_relu_bn(4 * w, 2 * w, 1)
        self.fuse = _conv_relu_bn(4 * w, 2 * w, 3)
        self.advantage = nn.Conv2d(2 * w, 2, 1)
        self.value = nn.Linear(4 * w, 1)

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(dense stride-4 features [B,2w,h/4,w/4], bottleneck [B,4w,h/8,w/8]): what the Q-maps are read from,
        and what perception pre-training (``flgd.learning.trunk``) trains."""
        s4 = self.enc2(self.enc1(x))
        s8 = self.context(self.enc3(s4))
        up = F.interpolate(self.squeeze(s8), size=s4.shape[2:], mode="bilinear", align_corners=False)
        return self.fuse(torch.cat([up, s4], dim=1)), s8

    def advantage_and_value(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        dense, s8 = self.features(x)
        return self.advantage(dense), self.value(s8.mean(dim=(2, 3)))


class RhoFcnFastQNet(_FastTrunkNetwork):
    """The VPG head (x16 bilinear, no skip) on the fast trunk plus one stride-2 stage (see module doc)."""

    variant = "rho-fcn-fast"
    stride = 16

    def __init__(self, rotations: int = 16, width: int = FAST_WIDTH) -> None:
        super().__init__(rotations, width)
        w = width
        self.enc4 = _conv_bn_relu(4 * w, 8 * w, stride=2)
        self.advantage = nn.Sequential(
            nn.BatchNorm2d(8 * w), nn.ReLU(inplace=True), nn.Conv2d(8 * w, 2 * w, 1, bias=False),
            nn.BatchNorm2d(2 * w), nn.ReLU(inplace=True), nn.Conv2d(2 * w, 2, 1))
        self.value = nn.Linear(8 * w, 1)

    def advantage_and_value(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        bottleneck = self.enc4(self.context(self.enc3(self.enc2(self.enc1(x)))))
        a = F.interpolate(self.advantage(bottleneck), scale_factor=16, mode="bilinear", align_corners=False)
        return a, self.value(bottleneck.mean(dim=(2, 3)))


class _DenseLayer(nn.Module):
    def __init__(self, cin: int, growth: int, bottleneck: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.BatchNorm2d(cin), nn.ReLU(inplace=True), nn.Conv2d(cin, bottleneck * growth, 1, bias=False),
            nn.BatchNorm2d(bottleneck * growth), nn.ReLU(inplace=True),
            nn.Conv2d(bottleneck * growth, growth, 3, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.body(x)
        return out


class _DenseBlock(nn.Module):
    def __init__(self, layers: int, cin: int, growth: int, bottleneck: int) -> None:
        super().__init__()
        self.layers = nn.ModuleList(_DenseLayer(cin + i * growth, growth, bottleneck) for i in range(layers))
        self.out_channels: int = cin + layers * growth

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        features = [x]
        for layer in self.layers:
            features.append(layer(torch.cat(features, dim=1)))
        return torch.cat(features, dim=1)


def _transition(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.BatchNorm2d(cin), nn.ReLU(inplace=True), nn.Conv2d(cin, cout, 1, bias=False),
                         nn.AvgPool2d(2, 2))


class DenseNet121Trunk(nn.Module):
    """DenseNet-121 (Huang et al. 2017) feature extractor; returns the stride-8 and stride-32 features."""

    def __init__(self, in_channels: int = 4, growth: int = 32, blocks: Sequence[int] = (6, 12, 24, 16),
                 init_features: int = 64, bottleneck: int = 4) -> None:
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, init_features, 7, 2, 3, bias=False), nn.BatchNorm2d(init_features),
            nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, 1))
        c = init_features
        stages = []
        skip_channels = c
        for i, n in enumerate(blocks):
            block = _DenseBlock(n, c, growth, bottleneck)
            c = block.out_channels
            if i == 1:
                skip_channels = c  # dense block 2 output, stride 8
            stage: list[nn.Module] = [block]
            if i < len(blocks) - 1:
                stage.append(_transition(c, c // 2))
                c //= 2
            stages.append(nn.ModuleList(stage))
        self.stages = nn.ModuleList(stages)
        self.norm = nn.BatchNorm2d(c)
        self.out_channels: int = c
        self.skip_channels: int = skip_channels

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.stem(x)
        skip = x
        for i, stage in enumerate(self.stages):
            parts = list(stage.children())
            x = parts[0](x)
            if i == 1:
                skip = x
            if len(parts) > 1:
                x = parts[1](x)
        return skip, F.relu(self.norm(x))


class DenseNetQNet(QMapNetwork):
    """DenseNet-121 trunk with the FLG skip head (``densenet121``) or the VPG head (``rho-fcn``)."""

    stride = 32

    def __init__(self, rotations: int = 16, head: str = "flg") -> None:
        super().__init__(rotations)
        if head not in ("flg", "vpg"):
            raise ValueError(f"head: got {head!r}, expected 'flg' or 'vpg'")
        self.head = head
        self.variant = "densenet121" if head == "flg" else "rho-fcn"
        self.trunk = DenseNet121Trunk()
        c = self.trunk.out_channels
        self.advantage: nn.Module
        if head == "flg":
            self.squeeze = _conv_relu_bn(c, 256, 1)
            self.fuse = _conv_relu_bn(256 + self.trunk.skip_channels, 128, 3)
            self.advantage = nn.Conv2d(128, 2, 1)
        else:
            self.advantage = nn.Sequential(
                nn.BatchNorm2d(c), nn.ReLU(inplace=True), nn.Conv2d(c, 64, 1, bias=False),
                nn.BatchNorm2d(64), nn.ReLU(inplace=True), nn.Conv2d(64, 2, 1))
        self.value = nn.Linear(c, 1)

    def advantage_and_value(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        skip, bottleneck = self.trunk(x)
        if self.head == "flg":
            up = F.interpolate(self.squeeze(bottleneck), scale_factor=4, mode="bilinear", align_corners=False)
            up = _match(up, skip)
            a = self.advantage(self.fuse(torch.cat([up, skip], dim=1)))
            a = F.interpolate(a, scale_factor=4, mode="bilinear", align_corners=False)
        else:
            a = F.interpolate(self.advantage(bottleneck), scale_factor=16, mode="bilinear", align_corners=False)
        return a, self.value(bottleneck.mean(dim=(2, 3)))


def _match(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Resize x to like's spatial size when odd input sizes left them one pixel apart."""
    if x.shape[2:] == like.shape[2:]:
        return x
    return F.interpolate(x, size=like.shape[2:], mode="bilinear", align_corners=False)


def build_network(variant: str, rotations: int = 16, seed: int | None = None, **architecture: int) -> QMapNetwork:
    """A freshly initialised network of ``variant``; ``seed`` makes the initial weights reproducible."""
    if variant not in VARIANTS:
        raise ValueError(f"network variant: got {variant!r}, expected one of {', '.join(VARIANTS)}")
    with torch.random.fork_rng(devices=[]):
        if seed is not None:
            torch.manual_seed(seed)
        if variant == "fast":
            net: QMapNetwork = FastQNet(rotations, **architecture)
        elif variant == "rho-fcn-fast":
            net = RhoFcnFastQNet(rotations, **architecture)
        else:
            if architecture:
                raise ValueError(f"network variant {variant!r} takes no architecture options, got {architecture}")
            net = DenseNetQNet(rotations, head="flg" if variant == "densenet121" else "vpg")
    return net


# --------------------------------------------------------------------------- rotation pipeline

def padded_side(height: int, width: int, stride: int) -> int:
    """Side of the rotated square: the heightmap's diagonal rounded up to a multiple of ``stride``."""
    diagonal = math.ceil(math.hypot(height, width))
    return int(math.ceil(diagonal / stride) * stride)


_GRID_CACHE: dict[tuple[Any, ...], tuple[torch.Tensor, torch.Tensor]] = {}


def _grids(height: int, width: int, side: int, rotations: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """grid_sample grids for all R rotations: heightmap -> rotated square, and back.

    Forward: rotated pixel q samples the heightmap at c_h + M_i (q - c_s), M_i the
    rotation by theta_i, so the image content lying along u_i appears along +col.
    Back: heightmap pixel p samples the network output at c_s + M_i^T (p - c_h).
    Coordinates are pixel centres in (x = col, y = row); grid_sample takes them
    normalised with align_corners=False.
    """
    key = (height, width, side, rotations, str(device))
    cached = _GRID_CACHE.get(key)
    if cached is not None:
        return cached
    theta = torch.arange(rotations, dtype=torch.float64) * (2.0 * math.pi / rotations)
    cos, sin = torch.cos(theta)[:, None, None], torch.sin(theta)[:, None, None]
    c_s = (side - 1) / 2.0
    c_hx, c_hy = (width - 1) / 2.0, (height - 1) / 2.0

    qy, qx = torch.meshgrid(torch.arange(side, dtype=torch.float64) - c_s,
                            torch.arange(side, dtype=torch.float64) - c_s, indexing="ij")
    sx = c_hx + cos * qx - sin * qy
    sy = c_hy + sin * qx + cos * qy
    forward = torch.stack([(2 * sx + 1) / width - 1, (2 * sy + 1) / height - 1], dim=-1)

    py, px = torch.meshgrid(torch.arange(height, dtype=torch.float64) - c_hy,
                            torch.arange(width, dtype=torch.float64) - c_hx, indexing="ij")
    bx = c_s + cos * px + sin * py
    by = c_s - sin * px + cos * py
    back = torch.stack([(2 * bx + 1) / side - 1, (2 * by + 1) / side - 1], dim=-1)
    result = (forward.to(device=device, dtype=torch.float32), back.to(device=device, dtype=torch.float32))
    if len(_GRID_CACHE) > 16:
        _GRID_CACHE.clear()
    _GRID_CACHE[key] = result
    return result


def normalise(color: torch.Tensor, height: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Raw colour in [0, 1] [B,3,H,W] and height in metres [B,1,H,W] -> network input."""
    mean = torch.tensor(COLOR_MEAN, dtype=color.dtype, device=color.device)[None, :, None, None]
    std = torch.tensor(COLOR_STD, dtype=color.dtype, device=color.device)[None, :, None, None]
    return (color - mean) / std, (height - HEIGHT_MEAN) / HEIGHT_STD


def _as_tensors(heightmaps: Heightmaps, device: torch.device) -> torch.Tensor:
    """Heightmaps -> raw [1,4,H,W] float tensor: colour in [0, 1], height in metres (NaN -> 0)."""
    color = np.asarray(heightmaps.color)
    height = np.asarray(heightmaps.height, dtype=np.float32)
    if color.ndim != 3 or color.shape[2] != 3 or height.ndim != 2 or color.shape[:2] != height.shape:
        raise ValueError(f"heightmaps: expected colour HxWx3 and height HxW of the same size, got "
                         f"{color.shape} and {height.shape}")
    c = torch.from_numpy(np.ascontiguousarray(color)).to(device=device, dtype=torch.float32)
    if color.dtype == np.uint8:
        c = c / 255.0
    h = torch.from_numpy(np.nan_to_num(height, nan=0.0, posinf=0.0, neginf=0.0)).to(device)
    return torch.cat([c.permute(2, 0, 1), h[None]], dim=0)[None]


def rotated_inputs(heightmaps: Heightmaps, rotation_indices: Sequence[int], rotations: int, stride: int,
                   device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """The normalised network inputs (colour [n,3,S,S], height [n,1,S,S]) for the given rotations."""
    device = torch.device(device)
    rotated = rotate_maps(_as_tensors(heightmaps, device), rotation_indices, rotations, stride)
    return normalise(rotated[:, :3], rotated[:, 3:])


def rotate_maps(maps: torch.Tensor, rotation_indices: Sequence[int], rotations: int, stride: int,
                mode: str = "bilinear") -> torch.Tensor:
    """Heightmap-frame maps [1,C,H,W] -> the rotated squares [n,C,S,S] the network sees (zero outside).

    ``mode="nearest"`` keeps label maps (e.g. pre-training targets) free of blended values.
    """
    h, w = maps.shape[2:]
    side = padded_side(h, w, stride)
    grid = _grids(h, w, side, rotations, maps.device)[0][list(rotation_indices)]
    return F.grid_sample(maps.expand(len(rotation_indices), -1, -1, -1), grid, mode=mode,
                         padding_mode="zeros", align_corners=False)


def unrotate_maps(maps: torch.Tensor, rotation_indices: Sequence[int], rotations: int,
                  height: int, width: int) -> torch.Tensor:
    """Network outputs in the rotated frames [n,C,S,S] -> the heightmap frame [n,C,H,W]."""
    side = maps.shape[-1]
    grid = _grids(height, width, side, rotations, maps.device)[1][list(rotation_indices)]
    return F.grid_sample(maps, grid, mode="bilinear", padding_mode="border", align_corners=False)


def q_maps(net: QMapNetwork, heightmaps: Heightmaps, rotations: int = 16,
           rotation_indices: Sequence[int] | None = None) -> torch.Tensor:
    """Q-maps [R,2,H,W] of ``heightmaps`` for all rotations (or the listed ones), in the heightmap frame.

    Runs in whatever grad mode and train/eval mode the caller set; the agent
    calls it under ``torch.inference_mode`` with the network in eval mode.
    """
    if rotations != net.rotations:
        raise ValueError(f"rotations: got {rotations}, but the network was built for {net.rotations}")
    indices = list(range(rotations)) if rotation_indices is None else [int(i) for i in rotation_indices]
    for i in indices:
        if not 0 <= i < rotations:
            raise ValueError(f"rotation index {i} is outside 0..{rotations - 1}")
    device = next(net.parameters()).device
    color, height = rotated_inputs(heightmaps, indices, rotations, net.stride, device)
    out = net(color, height)
    h, w = np.asarray(heightmaps.height).shape
    return unrotate_maps(out, indices, rotations, h, w)


_UPSAMPLE_CACHE: dict[tuple[int, int], torch.Tensor] = {}


def _upsample_matrix(source: int, size: int) -> torch.Tensor:
    """U [size, source]: ``F.interpolate(..., mode="bilinear", align_corners=False)`` along one axis as a matrix
    (bilinear resizing is separable, so a 2-D map resizes as U_y A U_x^T)."""
    key = (source, size)
    cached = _UPSAMPLE_CACHE.get(key)
    if cached is None:
        if source == size:
            cached = torch.eye(size)
        else:
            basis = torch.eye(source, dtype=torch.float64)[None]  # [1, source, source]: one channel per source pixel
            cached = F.interpolate(basis, size=size, mode="linear", align_corners=False)[0].T.float()
        if len(_UPSAMPLE_CACHE) > 16:
            _UPSAMPLE_CACHE.clear()
        _UPSAMPLE_CACHE[key] = cached
    return cached


def _sample_weights(coords: torch.Tensor, size: int) -> torch.Tensor:
    """[n, size] bilinear weights with which ``F.grid_sample(align_corners=False, padding_mode="border")`` reads
    the normalised coordinates ``coords`` [n] along one axis of length ``size``."""
    pixel = (((coords.double() + 1.0) * size - 1.0) / 2.0).clamp(0.0, size - 1.0)
    low = pixel.floor()
    upper = pixel - low
    low = low.long()
    weights = torch.zeros(len(coords), size, dtype=torch.float64)
    rows = torch.arange(len(coords))
    weights[rows, low] += 1.0 - upper
    weights[rows, (low + 1).clamp(max=size - 1)] += upper
    return weights.float()


def q_at_pixels(net: QMapNetwork, color: torch.Tensor, height: torch.Tensor, rotation_indices: Sequence[int],
                channels: Sequence[int], rows: Sequence[int], cols: Sequence[int], map_height: int,
                map_width: int) -> torch.Tensor:
    """Q [n] of input k (rotation ``rotation_indices[k]``, from ``rotated_inputs``) at channel ``channels[k]`` and
    heightmap pixel (``rows[k]``, ``cols[k]``): what ``q_maps`` gives there, read without building the full maps.

    The learner needs one value per input; resizing the advantage to the input size and rotating both channels
    back costs about a sixth of an update's forward and backward.  Everything after the network is linear in its
    advantage map A [a, a]: the resize is U A U^T, the dueling mean is a weighted sum of A, and the back-rotation
    is a bilinear read of four neighbours, so Q = V + r_y^T A r_x - mean with small weight vectors.
    """
    n = color.shape[0]
    if not (len(rotation_indices) == len(channels) == len(rows) == len(cols) == n):
        raise ValueError(f"q_at_pixels: {n} inputs but {len(rotation_indices)} rotations, {len(channels)} channels, "
                         f"{len(rows)} rows and {len(cols)} columns")
    side = color.shape[-1]
    advantage, value = net.advantage_and_value(torch.cat([color, height], dim=1))
    source = advantage.shape[-1]
    if advantage.shape[-2] != source:
        raise ValueError(f"q_at_pixels: expected a square advantage map, got {tuple(advantage.shape[2:])}")
    device, dtype = advantage.device, advantage.dtype
    upsample = _upsample_matrix(source, side).to(device=device, dtype=dtype)      # [side, source]
    column_weight = upsample.sum(dim=0)                                            # [source]
    channel_count = advantage.shape[1]
    mean = torch.einsum("i,nkij,j->n", column_weight, advantage, column_weight) / (channel_count * side * side)
    back = _grids(map_height, map_width, side, net.rotations, torch.device("cpu"))[1]
    coords = back[torch.as_tensor(list(rotation_indices)), torch.as_tensor(list(rows)), torch.as_tensor(list(cols))]
    read_x = _sample_weights(coords[:, 0], side).to(device=device, dtype=dtype) @ upsample   # [n, source]
    read_y = _sample_weights(coords[:, 1], side).to(device=device, dtype=dtype) @ upsample
    chosen = advantage[torch.arange(n, device=device), torch.as_tensor(list(channels), device=device)]
    return value[:, 0] + torch.einsum("ni,nij,nj->n", read_y, chosen, read_x) - mean


def twin_grasp_maps(q: np.ndarray) -> np.ndarray:
    """Q-maps [R,2,H,W] whose grasp channel at rotation i is the mean of rotations i and i + R/2.

    Why: a two-finger grasp at angle theta and at theta + pi is the same
    grasp (the learner trains both towards one target), but the network
    predicts them apart, and an argmax over both picks whichever twin's error
    happens to be higher.  The mean of the two is the better estimate.  Moves
    are directional and keep their values; an odd R has no twins.
    """
    q = np.asarray(q)
    rotations = q.shape[0]
    if rotations % 2:
        return q
    out = np.array(q, copy=True)
    half = rotations // 2
    mean = (q[:half, 0] + q[half:, 0]) / 2
    out[:half, 0] = mean
    out[half:, 0] = mean
    return out
