"""A blended run of moves in the simulator: one motion through its corners, cut at each move's pose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flgd.config import load_config
from flgd.geometry import pose_matrix
from flgd.plans import MoveL, plan_grasp
from sim_cell import kinematics, motion
from sim_cell.path_motion import PathProfile, plan_lines
from sim_cell.robot import READY_JOINTS
from tests.fakes.realsense import SIM_CONFIG

CFG = load_config(SIM_CONFIG)
TICK = 8 / 240
OFFSET = np.asarray(CFG.robot.tcp_offset)


def _grasp(blend: float):
    cfg = dataclasses.replace(CFG, robot=dataclasses.replace(CFG.robot, raise_speed=0.4, blend_radius=blend))
    return plan_grasp(-0.5, 0.05, 0.05, 0.6, cfg).steps


def _lines(steps) -> dict[int, motion.Trajectory]:
    """The plan's moves from the end of its descent (where the lift starts)."""
    d = [s.label for s in steps].index("descend")
    start = pose_matrix(steps[d].pose.position, steps[d].pose.matrix)
    q = kinematics.nearest_solution(kinematics.inverse(motion.tcp_to_flange(start, OFFSET)), READY_JOINTS)
    return plan_lines(steps, q, start, TICK, OFFSET, first=d + 1)


def _tcp_speeds(parts: list[motion.Trajectory]) -> np.ndarray:
    path = np.concatenate([parts[0].tcp[:, :3, 3]] + [p.tcp[1:, :3, 3] for p in parts[1:]])
    return np.linalg.norm(np.diff(path, axis=0), axis=1) / TICK


def test_a_blended_raise_and_home_never_stop_between_and_end_where_the_plan_ends():
    steps = _grasp(0.03)
    lines = _lines(steps)
    labels = [s.label for s in steps]
    parts = [lines[labels.index(k)] for k in ("raise", "home")]
    a, b = parts   # one motion: home starts on the tick the raise ended
    assert np.allclose(a.joints[-1], b.joints[0]) and np.allclose(a.tcp[-1], b.tcp[0])
    home = steps[labels.index("home")].pose
    assert np.allclose(b.tcp[-1][:3, 3], home.position, atol=1e-6)
    speeds = _tcp_speeds(parts)
    corner = len(a.joints) - 1
    assert speeds[corner - 2:corner + 2].min() > 0.05, "the tool kept moving through the raise's pose"
    # the corner's sideways acceleration stays within the moves' acceleration (v^2 / rho, from the ticks)
    path = np.concatenate([a.tcp[:, :3, 3], b.tcp[1:, :3, 3]])
    accel = np.linalg.norm(np.diff(path, n=2, axis=0), axis=1) / TICK ** 2
    assert accel[corner - 3:corner + 3].max() <= CFG.robot.acceleration * 1.5
    # stopping at the raise's pose (no blend) takes longer
    plain = _lines(_grasp(0.0))
    blended_time = sum(p.duration for p in parts)
    plain_time = sum(plain[labels.index(k)].duration for k in ("raise", "home"))
    assert blended_time < plain_time - 0.1


def test_blends_that_overlap_on_a_line_are_refused():
    start = pose_matrix((-0.5, 0.0, 0.05), np.diag([1.0, -1.0, -1.0]))
    mid, end, last = start.copy(), start.copy(), start.copy()
    mid[2, 3] += 0.1
    end[2, 3] += 0.1
    end[1, 3] += 0.03
    last[1, 3] += 0.03
    with pytest.raises(motion.Unreachable, match="overlap"):
        PathProfile.build(start, [mid, end, last], [0.2] * 3, [1.0] * 3, [0.02, 0.02, 0.0])


def test_a_path_without_a_blend_stops_at_its_middle_pose():
    start = pose_matrix((-0.5, 0.0, 0.05), np.diag([1.0, -1.0, -1.0]))
    mid = start.copy()
    mid[2, 3] += 0.1
    end = mid.copy()
    end[1, 3] += 0.1
    for blend, stops in ((0.0, True), (0.02, False)):
        profile = PathProfile.build(start, [mid, end], [0.25, 0.25], [1.0, 1.0], [blend, 0.0])
        at_mid = profile.v[profile.passes[0]]
        assert bool(at_mid == 0.0) is stops
        assert float(profile.s[-1]) < 0.2 or blend == 0.0   # a corner cuts the path short


def test_every_move_of_a_blended_plan_is_a_trajectory_and_unblended_moves_stay_lines():
    steps = _grasp(0.03)
    lines = _lines(steps)
    d = [s.label for s in steps].index("descend")
    assert sorted(lines) == [i for i, s in enumerate(steps) if isinstance(s, MoveL) and i > d]
