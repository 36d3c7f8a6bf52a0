"""A D415 played by librealsense's own software_device: frames rendered by the simulated cell or by the
analytic box renderer reach pyrealsense2 as a camera's would (import only where pyrealsense2 loads)."""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from pathlib import Path

import numpy as np
import pyrealsense2  # noqa: F401 (import only where librealsense loads, as the docstring says)

from flgd.cell import Frame
from flgd.config import CellConfig, load_config
from flgd.geometry import pose_matrix, rpy_to_matrix
from flgd.hardware import software_d415
from tests.fakes.scene import Box, render

ROOT = Path(__file__).resolve().parents[2]
SIM_CONFIG = ROOT / "cell_config" / "sim.yaml"
SERIAL = software_d415.EMULATED_SERIAL
BOXES = [Box(-0.55, -0.03, 0.05, 0.07, 0.04, 0.3, (200, 40, 40)),
         Box(-0.40, 0.10, 0.03, 0.06, 0.08, -0.6, (40, 200, 40)),
         Box(-0.47, 0.15, 0.04, 0.04, 0.025, 1.1, (40, 40, 200))]


def sim_config(**camera_changes) -> CellConfig:
    cfg = load_config(SIM_CONFIG)
    return dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, **camera_changes))


def scene_frame(cfg: CellConfig) -> Frame:
    """A frame of clutter rendered by the simulated cell (D415-like noise and holes included)."""
    from sim_cell.cell import SimCell

    with SimCell(cfg) as cell:
        return cell.capture()


def synthetic_frame(cfg: CellConfig, camera_pose: np.ndarray | None = None, intrinsics: np.ndarray | None = None,
                    width: int = 640, height: int = 480) -> Frame:
    it = cfg.camera.intrinsics
    k = intrinsics if intrinsics is not None else np.array([[it.fx, 0, it.cx], [0, it.fy, it.cy], [0, 0, 1.0]])
    pose = camera_pose if camera_pose is not None else \
        pose_matrix(cfg.camera.pose.position, rpy_to_matrix(*cfg.camera.pose.rpy))
    color, depth = render(BOXES, pose, k, table_z=cfg.workspace.table_z, width=width, height=height,
                          depth_scale=cfg.camera.depth_scale)
    return Frame(color=color, depth=depth, depth_scale=cfg.camera.depth_scale, intrinsics=k, camera_pose=pose)


class SoftwareD415(software_d415.SoftwareD415):
    """flgd's software D415, plus feeding the same pair at the camera's rate from a thread."""

    @contextlib.contextmanager
    def streaming(self, depth: np.ndarray, color: np.ndarray):
        """Feed the same pair at the camera's rate from a thread, like a live camera, until the block ends."""
        stop = threading.Event()

        def run() -> None:
            while not stop.is_set():
                self.feed(depth, color)
                stop.wait(1.0 / self.fps)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        try:
            yield self
        finally:
            stop.set()
            thread.join(timeout=5)


def registered_camera(frame: Frame, **kw) -> SoftwareD415:
    h, w = frame.depth.shape
    return SoftwareD415(frame.intrinsics, frame.intrinsics, (w, h), frame.depth_scale, **kw)
