"""Straight TCP lines as joint trajectories: trapezoidal timing plus analytic IK per control tick.

A MoveL on the real UR runs the TCP along a straight line with a trapezoidal
speed profile; here the same line is sampled at the control rate, each sample
solved with the closed-form IK, and the joint vectors are handed to the
simulated joint position controllers.  The whole line is solved before the arm
moves, so an unreachable pose or a configuration flip on the way stops the
plan before any motion, the way the UR controller refuses a moveL it cannot do.
A line that would drive a joint faster than the UR5e's rated 180 deg/s at the
commanded speed is slowed until none does (``Trajectory.speed_scale``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flgd.geometry import matrix_to_rotvec
from sim_cell import kinematics

__all__ = ["Trajectory", "Unreachable", "trapezoid_duration", "trapezoid_fraction", "plan_line",
           "raised_joints", "tcp_to_flange", "flange_to_tcp", "line_profile", "joint_speed_scale", "JOINT_SPEED_LIMIT",
           "solve_poses"]

# Tool rotation rate used to time moves that mostly turn the wrist (UR's default tool speed is
# given per translation only; a real moveL still takes time to turn).
ANGULAR_SPEED = 1.5      # rad/s
ANGULAR_ACCELERATION = 4.0  # rad/s^2
# The UR5e's rated joint speed, every joint (datasheet: 180 deg/s); a line that would drive a joint faster is slowed.
JOINT_SPEED_LIMIT = math.pi   # rad/s
# Largest joint step allowed between two control ticks; more means a flip through a singularity.
MAX_JOINT_STEP = 0.25    # rad
# IK residual above which a pose counts as unreachable.
MAX_POSITION_ERROR = 1e-4  # m
MAX_ROTATION_ERROR = 1e-3  # rad


class Unreachable(Exception):
    """A line cannot be followed: no IK solution, a residual too large, or a flip on the way."""


@dataclass(frozen=True)
class Trajectory:
    """Joint targets (ticks x 6) at the control rate and their TCP poses (ticks x 4 x 4)."""

    joints: np.ndarray
    tcp: np.ndarray
    tick: float
    speed_scale: float = 1.0   # < 1: slowed from the commanded speed to keep every joint within JOINT_SPEED_LIMIT

    @property
    def duration(self) -> float:
        return self.tick * max(len(self.joints) - 1, 0)


def trapezoid_duration(distance: float, speed: float, acceleration: float) -> float:
    """Time of a rest-to-rest move with a trapezoidal (or triangular) speed profile."""
    if distance <= 0.0:
        return 0.0
    ramp = speed / acceleration
    if distance >= speed * ramp:
        return distance / speed + ramp
    return 2.0 * math.sqrt(distance / acceleration)


def trapezoid_fraction(t: float, distance: float, speed: float, acceleration: float) -> float:
    """Fraction of ``distance`` covered at time ``t`` of the trapezoidal profile."""
    if distance <= 0.0:
        return 1.0
    total = trapezoid_duration(distance, speed, acceleration)
    t = min(max(t, 0.0), total)
    v_peak = min(speed, math.sqrt(distance * acceleration))
    ramp = v_peak / acceleration
    if t < ramp:
        s = 0.5 * acceleration * t * t
    elif t <= total - ramp:
        s = 0.5 * acceleration * ramp * ramp + v_peak * (t - ramp)
    else:
        rest = total - t
        s = distance - 0.5 * acceleration * rest * rest
    return min(max(s / distance, 0.0), 1.0)


def tcp_to_flange(tcp: np.ndarray, tcp_offset: np.ndarray) -> np.ndarray:
    """Flange pose for a TCP pose; the TCP sits at ``tcp_offset`` in the flange frame."""
    out = tcp.copy()
    out[:3, 3] = tcp[:3, 3] - tcp[:3, :3] @ tcp_offset
    return out


def flange_to_tcp(flange: np.ndarray, tcp_offset: np.ndarray) -> np.ndarray:
    out = flange.copy()
    out[:3, 3] = flange[:3, 3] + flange[:3, :3] @ tcp_offset
    return out


def line_profile(distance: float, angle: float, speed: float, acceleration: float,
                 scale: float = 1.0) -> tuple[float, float, float]:
    """(length, top speed, acceleration) of the trapezoid that times a line: the translation's or, for a line that
    mostly turns the wrist, the rotation's.  ``scale`` (<= 1) slows the line in time: speeds times ``scale``,
    accelerations times its square, so every joint's speed along the line scales by ``scale`` (``joint_speed_scale``)."""
    t_lin = trapezoid_duration(distance, speed * scale, acceleration * scale ** 2)
    t_rot = trapezoid_duration(angle, ANGULAR_SPEED * scale, ANGULAR_ACCELERATION * scale ** 2)
    if t_lin >= t_rot:
        return distance, speed * scale, acceleration * scale ** 2
    return angle, ANGULAR_SPEED * scale, ANGULAR_ACCELERATION * scale ** 2


def joint_speed_scale(traj: Trajectory, q_start: np.ndarray) -> float:
    """The factor (<= 1) a line's speeds must be scaled by so that no joint exceeds ``JOINT_SPEED_LIMIT``."""
    path = np.vstack([np.asarray(q_start, dtype=float)[None], traj.joints])
    peak = float(np.max(np.abs(np.diff(path, axis=0)))) / traj.tick if len(path) > 1 else 0.0
    return 1.0 if peak <= JOINT_SPEED_LIMIT else JOINT_SPEED_LIMIT / peak


def plan_line(q_start: np.ndarray, start: np.ndarray, goal: np.ndarray, speed: float, acceleration: float,
              tick: float, tcp_offset: np.ndarray) -> Trajectory:
    """Joint trajectory moving the TCP from pose ``start`` to ``goal`` (4x4) along a straight line, slowed where
    a joint would exceed ``JOINT_SPEED_LIMIT`` at the commanded speed.

    Raises Unreachable with the reason when some sample has no exact IK solution
    or the arm would have to flip configuration between two ticks.
    """
    traj = _solve_line(q_start, start, goal, speed, acceleration, tick, tcp_offset, 1.0)
    slower = joint_speed_scale(traj, q_start)
    if slower >= 0.999:
        return traj
    # the same path, stretched in time: every joint speed scales with it (up to the ticks' sampling)
    return _solve_line(q_start, start, goal, speed, acceleration, tick, tcp_offset, slower * 0.98)


def _solve_line(q_start: np.ndarray, start: np.ndarray, goal: np.ndarray, speed: float, acceleration: float,
                tick: float, tcp_offset: np.ndarray, scale: float) -> Trajectory:
    p0, p1 = start[:3, 3], goal[:3, 3]
    r0, r1 = start[:3, :3], goal[:3, :3]
    rel = matrix_to_rotvec(r0.T @ r1)
    distance = float(np.linalg.norm(p1 - p0))
    angle = float(np.linalg.norm(rel))
    prof = line_profile(distance, angle, speed, acceleration, scale)
    total = trapezoid_duration(*prof)
    ticks = max(int(math.ceil(total / tick)), 1)
    frac = np.array([trapezoid_fraction(i * tick, *prof) for i in range(ticks)] + [1.0])
    poses = np.zeros((ticks + 1, 4, 4))
    poses[:, 3, 3] = 1.0
    poses[:, :3, 3] = p0 + frac[:, None] * (p1 - p0)
    poses[:, :3, :3] = r0 @ _rotations(rel, frac)
    return solve_poses(q_start, poses, tick, tcp_offset, scale)


def solve_poses(q_start: np.ndarray, poses: np.ndarray, tick: float, tcp_offset: np.ndarray,
                scale: float = 1.0) -> Trajectory:
    """Joints for TCP ``poses`` (n, 4, 4) one control tick apart, each tick's IK branch the one nearest the
    previous tick's joints; raises Unreachable naming the first pose without an exact solution or past a flip."""
    ticks = len(poses) - 1
    flanges = poses.copy()
    flanges[:, :3, 3] = poses[:, :3, 3] - np.einsum("nij,j->ni", poses[:, :3, :3], np.asarray(tcp_offset, dtype=float))
    # every tick's solutions at once; the branch nearest the previous tick's joints is picked in order
    branches = kinematics.inverse_many(flanges)
    joints = np.empty((ticks + 1, 6))
    q_prev = np.asarray(q_start, dtype=float)
    solved = ticks + 1
    for i in range(ticks + 1):
        valid = branches[i][~np.isnan(branches[i, :, 0])]
        q = kinematics.nearest_solution(list(valid), q_prev)
        if q is None:
            solved = i
            break
        joints[i] = q
        q_prev = q
    reached = kinematics.forward_many(joints[:solved])
    dp = np.linalg.norm(reached[:, :3, 3] - flanges[:solved, :3, 3], axis=1)
    cos_a = (np.einsum("nji,nji->n", reached[:, :3, :3], flanges[:solved, :3, :3]) - 1.0) / 2.0
    dr = np.arccos(np.clip(cos_a, -1.0, 1.0))
    steps = np.max(np.abs(np.diff(np.vstack([np.asarray(q_start, dtype=float)[None], joints[:solved]]), axis=0)),
                   axis=1)
    for i in range(ticks + 1):
        pose = poses[i]
        where = f"TCP ({pose[0, 3]:.3f}, {pose[1, 3]:.3f}, {pose[2, 3]:.3f}) m"
        if i == solved:
            raise Unreachable(f"no inverse-kinematics solution at {where}")
        if dp[i] > MAX_POSITION_ERROR or dr[i] > MAX_ROTATION_ERROR:
            raise Unreachable(f"inverse-kinematics residual {dp[i] * 1000:.2f} mm / {dr[i]:.4f} rad at {where}")
        if steps[i] > MAX_JOINT_STEP:
            raise Unreachable(f"the straight line passes a singularity near {where} "
                              f"(joint jump {steps[i]:.2f} rad in one tick)")
    return Trajectory(joints=joints, tcp=poses, tick=tick, speed_scale=scale)


def raised_joints(traj: Trajectory, i: int, rise: float, tcp_offset: np.ndarray) -> np.ndarray:
    """Joints of tick ``i`` with the TCP ``rise`` m higher (tick ``i``'s own where that has no IK solution)."""
    if rise <= 0.0:
        return traj.joints[i]
    pose = traj.tcp[i].copy()
    pose[2, 3] += rise
    q = kinematics.nearest_solution(kinematics.inverse(tcp_to_flange(pose, tcp_offset)), traj.joints[i])
    return traj.joints[i] if q is None else q


def _rotations(rel: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """The rotation by ``rel * s`` (axis-angle) for every fraction s: (n, 3, 3), Rodrigues' formula."""
    angle = float(np.linalg.norm(rel))
    out = np.broadcast_to(np.eye(3), (len(frac), 3, 3)).copy()
    if angle < 1e-12:
        return out
    k = rel / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = angle * frac
    out += np.sin(a)[:, None, None] * kx + (1 - np.cos(a))[:, None, None] * (kx @ kx)
    return out
