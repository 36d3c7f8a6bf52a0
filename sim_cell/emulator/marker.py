"""A calibration marker on the emulated gripper, so ``flgd calibrate`` can run against ``flgd emulate``.

On a real cell a flat ArUco tag (or checkerboard) is fixed to the gripper, facing up, at a measured offset in
the tool frame (flgd/hardware/calibration.py).  Here the same picture, printed by OpenCV, is a thin textured
plate that follows the simulated gripper's TCP link: it is drawn by the simulated camera (so the colour and
depth frames the daemon reads through pyrealsense2 show it) and it has no collision shape (the physics never
feels it).  ``flgd emulate --marker aruco --marker-offset X Y Z`` mounts it; the offset is the plate's centre
in the tool frame (z along the tool axis, down when the tool points down), as ``flgd calibrate`` takes it.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import pybullet as p

from sim_cell.objects import quaternion_from_matrix

__all__ = ["CalibrationMarker", "MARKER_KINDS", "marker_image"]

MARKER_KINDS = ("aruco", "checkerboard")
PLATE_SIDE = 0.06      # m, the printed square including its white quiet zone
PLATE_THICKNESS = 0.002


def marker_image(kind: str, *, aruco_dict: str = "DICT_4X4_50", aruco_id: int = 0,
                 checkerboard: tuple[int, int] = (4, 3)) -> np.ndarray:
    """The square grey picture printed on the plate: the tag in a white quiet zone, or a checkerboard whose inner
    corners are (columns, rows) as ``flgd calibrate --checkerboard`` counts them."""
    if kind == "aruco":
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, aruco_dict))
        tag = cv2.aruco.generateImageMarker(dictionary, aruco_id, 240)
        return cv2.copyMakeBorder(tag, 60, 60, 60, 60, cv2.BORDER_CONSTANT, value=255)
    if kind == "checkerboard":
        cols, rows = checkerboard
        square = 40
        board = np.zeros(((rows + 1) * square, (cols + 1) * square), np.uint8)
        for r in range(rows + 1):
            for c in range(cols + 1):
                if (r + c) % 2 == 0:
                    board[r * square:(r + 1) * square, c * square:(c + 1) * square] = 255
        side = max(board.shape) + 2 * square
        top, left = (side - board.shape[0]) // 2, (side - board.shape[1]) // 2
        return cv2.copyMakeBorder(board, top, side - board.shape[0] - top, left, side - board.shape[1] - left,
                                  cv2.BORDER_CONSTANT, value=255)
    raise ValueError(f"marker: got {kind!r}, expected one of {', '.join(MARKER_KINDS)}")


# A square facing +z in its own frame, textured once on the upper face; the lower face is plain.  The plate's
# frame is the tool frame turned upside down (x kept, y and z flipped), so the upper face looks up when the tool
# points down and the picture reads unmirrored from above.
_PLATE_OBJ = """\
v {h} {h} 0.0
v {mh} {h} 0.0
v {mh} {mh} 0.0
v {h} {mh} 0.0
v {h} {h} {mt}
v {mh} {h} {mt}
v {mh} {mh} {mt}
v {h} {mh} {mt}
vt 1.0 1.0
vt 0.0 1.0
vt 0.0 0.0
vt 1.0 0.0
vn 0.0 0.0 1.0
vn 0.0 0.0 -1.0
f 1/1/1 2/2/1 3/3/1
f 1/1/1 3/3/1 4/4/1
f 5/4/2 7/4/2 6/4/2
f 5/4/2 8/4/2 7/4/2
"""
_FLIP = np.diag([1.0, -1.0, -1.0])   # tool frame -> plate frame


class CalibrationMarker:
    """The plate and the tick that keeps it on the TCP link (world: ``EmulatorWorld``; call under its lock)."""

    def __init__(self, world, kind: str, offset: Sequence[float], **picture) -> None:
        offset = [float(v) for v in offset]
        if len(offset) != 3 or not all(np.isfinite(offset)):
            raise ValueError(f"marker offset: got {offset!r}, expected three finite numbers (m, tool frame)")
        self.kind = kind
        self.offset = np.asarray(offset)
        self._world = world
        self._dir = tempfile.TemporaryDirectory(prefix="flgd-marker-")
        folder = Path(self._dir.name)
        cv2.imwrite(str(folder / "marker.png"), cv2.cvtColor(marker_image(kind, **picture), cv2.COLOR_GRAY2RGB))
        half = PLATE_SIDE / 2
        (folder / "plate.obj").write_text(_PLATE_OBJ.format(h=half, mh=-half, mt=-PLATE_THICKNESS))
        robot = world.cell._robot
        self._client, self._robot = robot.client, robot
        with world.lock:
            shape = p.createVisualShape(p.GEOM_MESH, fileName=str(folder / "plate.obj"),
                                        rgbaColor=[1, 1, 1, 1], physicsClientId=self._client)
            self.body = p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=shape,
                                          physicsClientId=self._client)
            texture = p.loadTexture(str(folder / "marker.png"), physicsClientId=self._client)
            p.changeVisualShape(self.body, -1, textureUniqueId=texture, rgbaColor=[1, 1, 1, 1],
                                physicsClientId=self._client)
            self.follow()
        world.add_tick(self._tick)

    def _tick(self, dt: float) -> None:
        self.follow()

    def pose(self) -> np.ndarray:
        """The plate's centre and axes in the world now: the TCP link's pose with the offset applied."""
        pos, quat = p.getLinkState(self._robot.body, self._robot.tcp_link, computeForwardKinematics=True,
                                   physicsClientId=self._client)[4:6]
        tool = np.eye(4)
        tool[:3, :3] = np.asarray(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
        tool[:3, 3] = pos
        plate = np.eye(4)
        plate[:3, :3] = tool[:3, :3] @ _FLIP
        plate[:3, 3] = tool[:3, :3] @ self.offset + tool[:3, 3]
        return plate

    def follow(self) -> None:
        plate = self.pose()
        p.resetBasePositionAndOrientation(self.body, plate[:3, 3].tolist(), quaternion_from_matrix(plate[:3, :3]),
                                          physicsClientId=self._client)

    def close(self) -> None:
        self._world.remove_tick(self._tick)
        self._dir.cleanup()

