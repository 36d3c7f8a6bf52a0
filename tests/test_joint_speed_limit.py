"""Lines that would drive a joint past the UR5e's rated 180 deg/s are slowed, in the simulator and the emulator."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from flgd.config import load_config
from flgd.geometry import ToolPose, pose_matrix
from sim_cell import kinematics, motion
from sim_cell.emulator.arm import EmulatedArm
from sim_cell.emulator.world import EmulatorWorld
from sim_cell.robot import READY_JOINTS
from tests.fakes.realsense import SIM_CONFIG

CFG = load_config(SIM_CONFIG)
# from home to the workspace's far corner, turning the wrist a quarter: at 1 m/s a joint would turn at ~3.6 rad/s
FAR = ToolPose.top_down(-0.724, -0.224, CFG.workspace.table_z + 0.12, -math.pi / 2)


def _matrix(pose: ToolPose) -> np.ndarray:
    return pose_matrix(pose.position, pose.matrix)


def _home() -> tuple[np.ndarray, np.ndarray]:
    home = _matrix(ToolPose.top_down(*CFG.robot.home.position, CFG.robot.home.yaw))
    offset = np.asarray(CFG.robot.tcp_offset)
    return home, kinematics.nearest_solution(kinematics.inverse(motion.tcp_to_flange(home, offset)), READY_JOINTS)


def _peak_joint_speed(traj: motion.Trajectory, q_start: np.ndarray) -> float:
    return float(np.max(np.abs(np.diff(np.vstack([q_start[None], traj.joints]), axis=0)))) / traj.tick


def test_a_simulated_line_too_fast_for_a_joint_is_slowed_to_the_rated_joint_speed():
    home, q = _home()
    offset = np.asarray(CFG.robot.tcp_offset)
    fast = motion.plan_line(q, home, _matrix(FAR), 1.0, 1.2, 0.02, offset)
    assert fast.speed_scale < 0.95
    assert _peak_joint_speed(fast, q) <= motion.JOINT_SPEED_LIMIT * 1.001
    shipped = motion.plan_line(q, home, _matrix(FAR), CFG.robot.speed, 1.2, 0.02, offset)
    assert shipped.speed_scale == 1.0   # the shipped speed stays within the joints' rated speed


def _extent(line) -> tuple[float, float]:
    return float(np.linalg.norm(line.goal[:3, 3] - line.start[:3, 3])), float(np.linalg.norm(line.rel))


@pytest.fixture
def arm():
    cfg = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, objects=0))
    with EmulatorWorld(cfg) as world:
        yield EmulatedArm(world)


def test_the_emulated_controller_slows_a_moveL_that_would_exceed_a_joints_rated_speed(arm):
    arm.move_linear(FAR.as_ur_pose(), 1.0, 1.2)
    fast = arm.line
    assert 0.5 < fast.speed_scale < 0.95   # the commanded speeds scaled down, as the controller's speed scaling
    as_commanded = motion.trapezoid_duration(*motion.line_profile(*_extent(fast), 1.0, 1.2))
    assert motion.trapezoid_duration(fast.length, fast.vmax, fast.acc) > as_commanded * 1.05
    arm.hold()
    arm.move_linear(FAR.as_ur_pose(), CFG.robot.speed, 1.2)
    assert arm.line.speed_scale == 1.0   # within the joints' speed: as commanded
