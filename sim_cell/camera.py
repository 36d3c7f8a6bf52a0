"""A simulated RealSense D415: pinhole rendering from the config's intrinsics, plus a depth-noise model.

The image is rendered headless with pybullet's TinyRenderer.  The OpenGL
projection is built from fx, fy, cx, cy so that a point projects to the same
pixel as with the OpenCV pinhole model the perception code inverts (pixel
centres at integer coordinates); the view matrix is the inverse of the
camera pose turned from the OpenCV optical frame (z forward, y down) to the
OpenGL camera frame (z backward, y up).

Depth noise, D415-like (stereo depth error grows with the square of the
distance): per-pixel Gaussian with std = ``NOISE_AT_HALF_METRE`` * (z / 0.5 m)^2,
1 mm quantisation (the uint16 unit), random dropouts, and holes along depth
edges where stereo matching fails.  All draws come from the cell's seeded
generator.

The numbers it follows, so that it is no kinder than a real D415:

* RMS depth error of a stereo camera: z^2 * subpixel / (fx * baseline) (Intel,
  "Tuning depth cameras for best performance", D400 white paper).  With a
  typical subpixel of 0.08, fx 615 px and the D415's 55 mm baseline that is
  about 1.2 mm at 0.70 m; the default Gaussian here (1 mm at 0.5 m, growing
  with z^2) is 2.0 mm there.
* Occlusion shadow (``DepthNoise.stereo_shadow``; on in a cell config's defaults): depth is given in
  the left imager; a pixel the right imager, ``STEREO_BASELINE`` = 55 mm along
  +x, cannot see past a nearer surface has no reading.  It falls on the left
  (smaller column) side of nearer objects, ~fx * B * (1/z_far - 1/z_near) px wide.
* Outliers, flying pixels and speckle (``DepthNoise.outlier_rate``; 0.3 % in a cell config's defaults): a
  share of valid pixels off by up to +-``OUTLIER_SPAN``.  No datasheet gives a
  number for this; the share is a knob.

``flgd bench depth_model`` measures a cell's frames against these numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as p

from flgd.config import CameraConfig, CameraPoseErrorConfig, SimConfig
from flgd.geometry import pose_matrix, rpy_to_matrix

__all__ = ["CameraModel", "DepthNoise", "render", "render_labelled", "add_depth_noise", "stereo_shadow", "to_raw_depth"]

NEAR, FAR = 0.05, 3.0
NOISE_AT_HALF_METRE = 0.001   # m, std at 0.5 m
DROPOUT_RATE = 0.002          # share of pixels with no reading
EDGE_STEP = 0.008             # m; a larger depth step to a neighbour is an edge
EDGE_HOLE_RATE = 0.5          # chance an edge pixel has no reading
STEREO_BASELINE = 0.055       # m, D415 left-right imager baseline (along the image x axis)
OUTLIER_SPAN = 0.03           # m, outlier depth errors are uniform in +-OUTLIER_SPAN


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics, pose and the derived OpenGL matrices of one camera."""

    width: int
    height: int
    intrinsics: np.ndarray   # 3x3
    pose: np.ndarray         # 4x4 optical frame -> base
    view: tuple[float, ...]
    projection: tuple[float, ...]

    @staticmethod
    def from_config(cam: CameraConfig, pose_error: CameraPoseErrorConfig | None = None) -> "CameraModel":
        """The camera of ``cam``; with ``pose_error``, the camera where it truly is on a miscalibrated cell:
        position offset in the base frame, rotation offset about the configured optical frame's own axes."""
        ic = cam.intrinsics
        k = np.array([[ic.fx, 0.0, ic.cx], [0.0, ic.fy, ic.cy], [0.0, 0.0, 1.0]])
        pose = pose_matrix(cam.pose.position, rpy_to_matrix(*cam.pose.rpy))
        if pose_error is not None:
            pose = pose_matrix(np.asarray(cam.pose.position, float) + np.asarray(pose_error.position, float),
                               pose[:3, :3] @ rpy_to_matrix(*pose_error.rpy))
        gl_from_cv = np.diag([1.0, -1.0, -1.0, 1.0])
        view = np.linalg.inv(pose @ gl_from_cv)
        w, h = ic.width, ic.height
        proj = np.zeros((4, 4))
        proj[0, 0] = 2.0 * ic.fx / w
        proj[0, 2] = 1.0 - 2.0 * (ic.cx + 0.5) / w
        proj[1, 1] = 2.0 * ic.fy / h
        proj[1, 2] = 2.0 * (ic.cy + 0.5) / h - 1.0
        proj[2, 2] = -(FAR + NEAR) / (FAR - NEAR)
        proj[2, 3] = -2.0 * FAR * NEAR / (FAR - NEAR)
        proj[3, 2] = -1.0
        # pybullet takes column-major 4x4 matrices
        return CameraModel(width=w, height=h, intrinsics=k, pose=pose,
                           view=tuple(view.T.reshape(-1).tolist()), projection=tuple(proj.T.reshape(-1).tolist()))


def render(client: int, cam: CameraModel, light_direction=(0.3, -0.2, 1.0), shadow: bool = False,
           ambient: float = 0.6, diffuse: float = 0.4) -> tuple[np.ndarray, np.ndarray]:
    """(colour HxWx3 uint8, metric depth HxW float32 along the optical axis)."""
    color, depth, _ = _render(client, cam, light_direction, shadow, ambient, diffuse, segmentation=False)
    return color, depth


def render_labelled(client: int, cam: CameraModel, light_direction=(0.3, -0.2, 1.0), shadow: bool = False,
                    ambient: float = 0.6, diffuse: float = 0.4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(colour, depth, body id HxW int32; -1 = nothing): ground truth for perception pre-training."""
    return _render(client, cam, light_direction, shadow, ambient, diffuse, segmentation=True)


def _render(client: int, cam: CameraModel, light_direction, shadow: bool, ambient: float, diffuse: float,
            segmentation: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    _, _, rgba, zbuf, seg = p.getCameraImage(cam.width, cam.height, viewMatrix=cam.view,
                                             projectionMatrix=cam.projection, renderer=p.ER_TINY_RENDERER,
                                             lightDirection=list(light_direction), shadow=int(shadow),
                                             lightAmbientCoeff=ambient, lightDiffuseCoeff=diffuse,
                                             lightSpecularCoeff=0.05,
                                             flags=0 if segmentation else p.ER_NO_SEGMENTATION_MASK,
                                             physicsClientId=client)
    rgba = np.asarray(rgba, dtype=np.uint8).reshape(cam.height, cam.width, 4)
    zbuf = np.asarray(zbuf, dtype=np.float32).reshape(cam.height, cam.width)
    depth = (FAR * NEAR / (FAR - (FAR - NEAR) * zbuf)).astype(np.float32)
    depth[zbuf >= 1.0] = 0.0  # nothing hit
    labels = np.asarray(seg, dtype=np.int32).reshape(cam.height, cam.width) if segmentation else None
    return np.ascontiguousarray(rgba[:, :, :3]), depth, labels


@dataclass(frozen=True)
class DepthNoise:
    """Parameters of the depth-noise model (defaults: D415 at short range)."""

    std_at_half_metre: float = NOISE_AT_HALF_METRE
    dropout_rate: float = DROPOUT_RATE
    edge_step: float = EDGE_STEP
    edge_hole_rate: float = EDGE_HOLE_RATE
    outlier_rate: float = 0.0     # share of valid pixels with an error uniform in +-OUTLIER_SPAN
    stereo_shadow: bool = False   # no reading where the right imager's view is occluded (needs fx)

    @staticmethod
    def from_config(sim: SimConfig) -> "DepthNoise":
        """The noise of a cell's ``sim.depth_noise_std``, ``depth_dropout``, ``depth_edge_holes``,
        ``depth_outliers`` and ``stereo_shadow``."""
        return DepthNoise(std_at_half_metre=sim.depth_noise_std, dropout_rate=sim.depth_dropout,
                          edge_hole_rate=sim.depth_edge_holes, outlier_rate=sim.depth_outliers,
                          stereo_shadow=sim.stereo_shadow)


def stereo_shadow(depth: np.ndarray, fx: float, baseline: float = STEREO_BASELINE) -> np.ndarray:
    """HxW bool: pixels of the left image that the right imager (``baseline`` along +x) cannot see.

    Pixel u with disparity d(u) = fx * B / z(u) appears at u - d(u) in the right image; it is hidden when a
    pixel u' > u of the same row lands more than half a pixel to its left (u' - d(u') < u - d(u) - 0.5).
    Pixels without a reading (z == 0) neither hide nor are hidden.
    """
    z = depth.astype(np.float64)
    valid = z > 0
    u = np.arange(z.shape[1], dtype=np.float64)
    with np.errstate(divide="ignore"):
        right = np.where(valid, u - fx * baseline / np.where(valid, z, 1.0), np.inf)
    # min over u' > u: reversed cumulative minimum, shifted by one column
    after = np.full_like(right, np.inf)
    after[:, :-1] = np.minimum.accumulate(right[:, ::-1], axis=1)[:, ::-1][:, 1:]
    return valid & (after < right - 0.5)


def add_depth_noise(depth: np.ndarray, rng: np.random.Generator, noise: DepthNoise = DepthNoise(),
                    fx: float | None = None) -> np.ndarray:
    """Noisy metric depth (0 = no reading), before quantisation.

    ``fx`` (px, the camera's focal length) is needed only with ``noise.stereo_shadow``.  With the opt-in knobs
    off the draws, and so the output for a given generator state, are those of the model before they existed;
    outliers draw after all the others.
    """
    if noise.stereo_shadow and fx is None:
        raise ValueError("add_depth_noise: stereo_shadow needs the camera's fx")
    z = depth.astype(np.float64)
    valid = z > 0
    std = noise.std_at_half_metre * (z / 0.5) ** 2
    out = z + rng.standard_normal(z.shape) * std
    # holes where the depth jumps between neighbours (occlusion edges)
    step = np.zeros_like(z, dtype=bool)
    dz_x = np.abs(np.diff(z, axis=1)) > noise.edge_step
    dz_y = np.abs(np.diff(z, axis=0)) > noise.edge_step
    step[:, 1:] |= dz_x
    step[:, :-1] |= dz_x
    step[1:, :] |= dz_y
    step[:-1, :] |= dz_y
    holes = step & (rng.random(z.shape) < noise.edge_hole_rate)
    drops = rng.random(z.shape) < noise.dropout_rate
    if noise.outlier_rate > 0.0:
        at = np.flatnonzero(valid)
        hit = rng.random(at.size) < noise.outlier_rate
        err = rng.uniform(-OUTLIER_SPAN, OUTLIER_SPAN, at.size)
        out.flat[at[hit]] += err[hit]
    missing = ~valid | holes | drops
    if noise.stereo_shadow:
        missing |= stereo_shadow(z, fx)
    out[missing] = 0.0
    return out


def to_raw_depth(depth_m: np.ndarray, depth_scale: float, depth_range: tuple[float, float]) -> np.ndarray:
    """Metric depth -> uint16 raw units (rounded: 1 unit quantisation); out-of-range -> 0."""
    raw = np.rint(depth_m / depth_scale)
    ok = (depth_m >= depth_range[0]) & (depth_m <= depth_range[1])
    raw[~ok] = 0
    return np.clip(raw, 0, 65535).astype(np.uint16)
