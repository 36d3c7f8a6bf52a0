"""Whether the tool stands between the camera and the workspace: a frame taken so is never used.

A heightmap of a frame with the gripper in view shows the gripper as a tall object (and hides what lies under
it).  The cycle takes its pictures with the arm at home, or on a grasp's move home once the arm has left the view
(``flgd.cell.Cell.execute_and_capture``: the cells decide when with this module); every one is checked here, on the
tool position the cell read when the frame was taken (``flgd.cell.Frame.tool_position``), not assumed from the
plan.

The tool is modelled as a vertical cylinder around the TCP: ``TOOL_RADIUS`` wide (the RG2 open, with a held
object), from ``TOOL_BELOW`` under the TCP (an object hanging from the fingers) to ``TOOL_ABOVE`` over it (gripper,
wrist and the last links).  A point of it is in view when the camera's ray through it meets the table inside the
workspace, widened by ``VIEW_MARGIN``.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from flgd.config import CellConfig

__all__ = ["tool_in_view", "in_view_on_the_way", "TOOL_RADIUS", "HELD_REACH", "TOOL_ABOVE", "TOOL_BELOW",
           "VIEW_MARGIN"]

TOOL_RADIUS = 0.07   # m: RG2 fingers open (85 mm) plus a held block's overhang
TOOL_ABOVE = 0.30    # m: gripper (0.2 m flange to fingertips) and the wrist above it
TOOL_BELOW = 0.05    # m: an object hanging under the fingertips
VIEW_MARGIN = 0.01   # m around the workspace on the table
# m: the cylinder a picture on the way home waits for (``in_view_on_the_way``): an object up to 24 cm long held across
# its middle.  At home the arm stands still where its config put it out of view; on the way, the first pose the 7 cm
# model calls clear can still show a long held object's end over the workspace.
HELD_REACH = 0.12


def _tool_points(tcp: Sequence[float], radius: float = TOOL_RADIUS) -> np.ndarray:
    """Points on the tool's cylinder: 5 heights x (centre + 8 around the rim)."""
    x, y, z = (float(v) for v in tcp)
    angles = np.linspace(0.0, 2.0 * math.pi, 8, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1) * radius
    points = []
    for dz in np.linspace(-TOOL_BELOW, TOOL_ABOVE, 5):
        points.append((x, y, z + dz))
        points.extend((x + dx, y + dy, z + dz) for dx, dy in ring)
    return np.asarray(points, dtype=float)


def in_view_on_the_way(tcp: Sequence[float], config: CellConfig) -> str:
    """``tool_in_view`` with the tool widened to ``HELD_REACH``: what a cell waits for before a picture on the way."""
    return tool_in_view(tcp, config, radius=HELD_REACH)


def tool_in_view(tcp: Sequence[float], config: CellConfig, radius: float = TOOL_RADIUS) -> str:
    """Why the tool at ``tcp`` (x, y, z in the base frame) hides part of the workspace from the camera, or ''.

    A non-finite position is in view (nothing proves the arm is out of the picture)."""
    if len(tcp) != 3 or not all(math.isfinite(float(v)) for v in tcp):
        return f"the tool position {list(tcp)!r} is not three finite numbers: nothing shows the arm is out of view"
    camera = np.asarray(config.camera.pose.position, dtype=float)
    ws = config.workspace
    table = ws.table_z
    for point in _tool_points(tcp, radius):
        if point[2] >= camera[2] or point[2] <= table:
            continue   # above the camera, or under the table: on no ray from the camera to the workspace
        t = (camera[2] - table) / (camera[2] - point[2])
        hit = camera[:2] + t * (point[:2] - camera[:2])
        if (ws.x[0] - VIEW_MARGIN <= hit[0] <= ws.x[1] + VIEW_MARGIN
                and ws.y[0] - VIEW_MARGIN <= hit[1] <= ws.y[1] + VIEW_MARGIN):
            where = ", ".join(f"{float(v):.3f}" for v in tcp)
            return (f"the tool at [{where}] m stands between the camera and the workspace (a point of it at "
                    f"z {point[2]:.3f} m is seen over the table at x {hit[0]:.3f}, y {hit[1]:.3f} m)")
    return ""
