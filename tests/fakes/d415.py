"""A fake D415 camera: frames of an empty table as the configured camera sees it, and a camera that is gone."""

from __future__ import annotations

import numpy as np

from flgd.cell import Frame
from flgd.config import CellConfig
from flgd.geometry import pose_matrix, rpy_to_matrix
from flgd.hardware.camera import CameraFault


class FakeD415:
    """A fake of ``D415Camera``: frames of an empty table as the configured camera sees it.

    ``factory.unplugged`` models a camera that is gone: capture raises the
    CameraFault the real class raises on a frame timeout.
    """

    def __init__(self, config: CellConfig, factory: "FakeD415Factory"):
        self.config, self.factory = config, factory
        self.closed = False
        self.captures = 0

    def capture(self) -> Frame:
        if self.factory.unplugged or self.closed:
            raise CameraFault("RealSense 000000000000 was disconnected (no frame within 2.0 s)")
        self.captures += 1
        cam = self.config.camera
        it = cam.intrinsics
        pose = pose_matrix(cam.pose.position, rpy_to_matrix(*cam.pose.rpy))
        # looking straight down: every pixel sees the table at the camera's height above it
        distance = pose[2, 3] - self.config.workspace.table_z
        depth = np.full((it.height, it.width), round(distance / cam.depth_scale), dtype=np.uint16)
        color = np.full((it.height, it.width, 3), 90, dtype=np.uint8)
        k = np.array([[it.fx, 0.0, it.cx], [0.0, it.fy, it.cy], [0.0, 0.0, 1.0]])
        return Frame(color=color, depth=depth, depth_scale=cam.depth_scale, intrinsics=k, camera_pose=pose)

    def close(self) -> None:
        self.closed = True


class FakeD415Factory:
    """Opens ``FakeD415`` cameras like ``D415Camera.open``; refuses (CameraFault) while ``unplugged``."""

    def __init__(self):
        self.unplugged = False
        self.opened: list[FakeD415] = []

    def __call__(self, config: CellConfig) -> FakeD415:
        if self.unplugged:
            raise CameraFault("RealSense 000000000000 (camera.serial) is not connected; connected: none")
        cam = FakeD415(config, self)
        self.opened.append(cam)
        return cam
