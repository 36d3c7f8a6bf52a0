"""The arm's reach: a workspace, envelope, home or place the arm cannot get to is a config error.

Why here and not at the first plan: a workspace typed in the wrong unit or with a flipped sign (metres off, or
on the other side of the base) passes every box check of ``flgd.config.rules`` -- workspace inside the
envelope, home beside the workspace -- and fails only when the arm is asked to move, as a refused plan or a
fault.  ``flgd check-config`` names it instead.

The model: the UR5e's published reach, 0.85 m, is a sphere around the shoulder joint, 0.1625 m above the base
origin on its axis (the first DH offset); with the tool pointing down, the flange sits ``robot.tcp_offset``'s z
above the fingertips, and it is the flange that must lie inside.  The simulated cell's arm is a UR5e with the
published DH parameters (``sim_cell/kinematics.py``), so its reach is the same.  A point the model accepts may
still need a wrist pose the planner refuses near the edge; the model only catches what no pose can reach.
"""

from __future__ import annotations

import itertools
import math

from flgd.config.schema import CellConfig

__all__ = ["ARM_REACH", "SHOULDER_HEIGHT", "check_reach"]

# backend -> (arm, reach in metres from the shoulder to the flange)
ARM_REACH: dict[str, tuple[str, float]] = {"ur5e": ("UR5e", 0.85), "sim": ("UR5e (simulated)", 0.85)}
SHOULDER_HEIGHT = 0.1625  # m above the base origin: the UR5e's first DH offset d1


def _flange_distance(x: float, y: float, z: float, tcp_z: float) -> float:
    """Shoulder to flange, for fingertips at (x, y, z) with the tool pointing straight down."""
    return math.sqrt(x * x + y * y + (z + tcp_z - SHOULDER_HEIGHT) ** 2)


def check_reach(cfg: CellConfig, problems: list[str]) -> None:
    """Every workspace corner at the table, some part of the envelope, home and place within the arm's reach
    (backends without a known arm are not checked)."""
    if cfg.backend not in ARM_REACH:
        return
    arm, reach = ARM_REACH[cfg.backend]
    tcp_z = cfg.robot.tcp_offset[2]
    why = f"expected within the {arm}'s reach of {reach:g} m (shoulder to flange, the tool pointing down)"
    ws = cfg.workspace
    for x, y in itertools.product(ws.x, ws.y):
        d = _flange_distance(x, y, ws.table_z, tcp_z)
        if d > reach:
            problems.append(f"workspace: corner (x {x!r}, y {y!r}) at the table (z {ws.table_z!r}) is {d:.2f} m "
                            f"away, {why}; workspace.x {list(ws.x)!r}, workspace.y {list(ws.y)!r}")
            break
    sf = cfg.safety
    nearest = [min(max(0.0, lo), hi) for lo, hi in (sf.envelope_x, sf.envelope_y)]
    z_lo, z_hi = sf.envelope_z
    nearest_z = min(max(SHOULDER_HEIGHT - tcp_z, z_lo), z_hi)
    d = _flange_distance(nearest[0], nearest[1], nearest_z, tcp_z)
    if d > reach:
        problems.append(f"safety.envelope: no point of the envelope (x {list(sf.envelope_x)!r}, y "
                        f"{list(sf.envelope_y)!r}, z {list(sf.envelope_z)!r}) is within reach: its nearest is "
                        f"{d:.2f} m away, {why}")
    for key in ("home", "place"):
        x, y, z = getattr(cfg.robot, key).position
        d = _flange_distance(x, y, z, tcp_z)
        if d > reach:
            problems.append(f"robot.{key}.position: {[x, y, z]!r} is {d:.2f} m away, {why}")
