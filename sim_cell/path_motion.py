"""A blended run of MoveLs as one motion: straight lines joined by ``flgd.blending`` corners, timed as a whole.

The tool runs each line at its move's speed, up to the middle of a corner (its pose) at the incoming line's and
after it at the outgoing line's, never stopping between the run's first and last pose; it speeds up and slows
down at the moves' acceleration, and through a corner no faster than keeps its sideways acceleration (v^2 over the
curve's radius) within that acceleration too.  The profile is the fastest one within those limits (forward and
backward passes over the path sampled every millimetre); blends that would overlap on a line are refused.  A line that turns the wrist is slowed so that the wrist turns at most ``motion.ANGULAR_SPEED``.
The simulated cell follows the profile tick by tick (``plan_path``: one Trajectory per move, so that each move's
end is still a point in the plan); the emulated controller runs the same profile online (``PathProfile``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flgd.blending import corner_curve
from flgd.geometry import matrix_to_rotvec, pose_matrix
from flgd.plans import blended_runs
from sim_cell import motion

__all__ = ["PathProfile", "plan_path", "plan_lines", "SAMPLE_STEP"]

SAMPLE_STEP = 0.001   # m between samples of a straight line
CORNER_POINTS = 24    # samples of one blended corner


def _bend_speeds(entry: np.ndarray, corner: np.ndarray, exit_: np.ndarray, samples: int,
                 acceleration: float) -> np.ndarray:
    """The fastest speed at each of ``samples`` points of a corner (a quadratic Bezier) whose sideways
    acceleration v^2 / rho stays within ``acceleration`` (rho: the curve's radius of curvature there)."""
    t = np.linspace(0.0, 1.0, samples)[:, None]
    d1 = 2.0 * (1 - t) * (corner - entry) + 2.0 * t * (exit_ - corner)
    d2 = 2.0 * (entry - 2.0 * corner + exit_)
    speed = np.linalg.norm(d1, axis=1)
    bend = np.linalg.norm(np.cross(d1, d2), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(bend > 1e-12, speed ** 3 / bend, np.inf)
    return np.sqrt(acceleration * rho)


def _rot(rel: np.ndarray, frac: float) -> np.ndarray:
    return motion._rotations(rel, np.array([frac]))[0]


@dataclass(frozen=True)
class PathProfile:
    """Samples along the path: positions (n, 3), rotations (n, 3, 3), arc length ``s`` (n,), the fastest speed
    allowed at each sample (``v``, zero at both ends), the acceleration, and for each move the sample index where
    the tool passes its pose (the middle of its corner; the last move's is the last sample)."""

    positions: np.ndarray
    rotations: np.ndarray
    s: np.ndarray
    v: np.ndarray
    acceleration: float
    passes: tuple[int, ...]

    @property
    def length(self) -> float:
        return float(self.s[-1])

    @classmethod
    def build(cls, start: np.ndarray, goals: list[np.ndarray], speeds: list[float], accelerations: list[float],
              blends: list[float], scale: float = 1.0) -> "PathProfile":
        """From the start pose (4x4) through ``goals`` (4x4 each); ``blends[k]`` is the corner at ``goals[k]``
        (the last is ignored).  ``scale`` (<= 1) slows it in time, as ``motion.line_profile`` does."""
        poses = [start] + list(goals)
        n = len(goals)
        lengths = [float(np.linalg.norm(poses[k + 1][:3, 3] - poses[k][:3, 3])) for k in range(n)]
        if min(lengths) < 1e-6:
            raise motion.Unreachable("a blended path has a move without translation")
        rels = [matrix_to_rotvec(poses[k][:3, :3].T @ poses[k + 1][:3, :3]) for k in range(n)]
        caps = []
        for k in range(n):
            angle = float(np.linalg.norm(rels[k]))
            cap = speeds[k] if angle < 1e-9 else min(speeds[k], lengths[k] * motion.ANGULAR_SPEED / angle)
            caps.append(cap * scale)
        radius = [blends[k] if k < n - 1 else 0.0 for k in range(n)]
        pos: list[np.ndarray] = []
        rot: list[np.ndarray] = []
        vmax: list[float] = []
        passes: list[int] = []
        for k in range(n):
            a, b = poses[k][:3, 3], poses[k + 1][:3, 3]
            u = (b - a) / lengths[k]
            d0 = radius[k - 1] if k > 0 else 0.0
            d1 = lengths[k] - radius[k]
            if d1 < d0 - 1e-9:
                raise motion.Unreachable(f"the blends at both ends of move {k} overlap ({d0:.4f} + "
                                         f"{radius[k]:.4f} m on a {lengths[k]:.4f} m line)")
            count = max(int(math.ceil((d1 - d0) / SAMPLE_STEP)), 1)
            first = 0 if k == 0 else 1   # the previous corner ended on this line's first sample
            for i in range(first, count + 1):
                d = d0 + (d1 - d0) * i / count
                pos.append(a + d * u)
                rot.append(poses[k][:3, :3] @ _rot(rels[k], d / lengths[k]))
                vmax.append(caps[k])
            if k < n - 1 and radius[k] > 0.0:
                curve = corner_curve(a, b, poses[k + 2][:3, 3], radius[k], CORNER_POINTS + 1)
                bend = _bend_speeds(curve[0], b, curve[-1], len(curve), min(accelerations) * scale ** 2)
                for i in range(1, len(curve)):
                    t = i / (len(curve) - 1)
                    if t <= 0.5:
                        frac = (lengths[k] - radius[k] * (1 - 2 * t)) / lengths[k]
                        r = poses[k][:3, :3] @ _rot(rels[k], frac)
                    else:
                        frac = radius[k] * (2 * t - 1) / lengths[k + 1]
                        r = poses[k + 1][:3, :3] @ _rot(rels[k + 1], frac)
                    pos.append(curve[i])
                    rot.append(r)
                    vmax.append(min(caps[k] if t <= 0.5 else caps[k + 1], bend[i]))
                    if i == (len(curve) - 1) // 2:
                        passes.append(len(pos) - 1)
            elif k < n - 1:   # no blend: the tool stops at this pose, as the controller does
                vmax[-1] = 0.0
                passes.append(len(pos) - 1)
        passes.append(len(pos) - 1)
        positions = np.asarray(pos)
        ds = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        acc = min(accelerations) * scale ** 2
        v = np.asarray(vmax, dtype=float)
        v[0] = v[-1] = 0.0
        for i in range(len(ds)):              # forward: no faster than accelerating from rest allows
            v[i + 1] = min(v[i + 1], math.sqrt(v[i] ** 2 + 2.0 * acc * ds[i]))
        for i in range(len(ds) - 1, -1, -1):  # backward: slow enough to stop at the end
            v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2.0 * acc * ds[i]))
        return cls(positions, np.asarray(rot), np.concatenate([[0.0], np.cumsum(ds)]), v, acc, tuple(passes))

    def times(self) -> np.ndarray:
        """Time at each sample along the profile (s)."""
        ds = np.diff(self.s)
        mean_v = 0.5 * (self.v[:-1] + self.v[1:])
        dt = np.where(ds > 0.0, ds / np.maximum(mean_v, 1e-9), 0.0)
        return np.concatenate([[0.0], np.cumsum(dt)])

    def pose_at(self, s: float) -> np.ndarray:
        """The TCP pose (4x4) at arc length ``s``."""
        s = min(max(s, 0.0), self.length)
        i = int(np.searchsorted(self.s, s, side="right")) - 1
        i = min(max(i, 0), len(self.s) - 2)
        span = self.s[i + 1] - self.s[i]
        frac = 0.0 if span <= 0.0 else (s - self.s[i]) / span
        out = np.eye(4)
        out[:3, 3] = self.positions[i] + frac * (self.positions[i + 1] - self.positions[i])
        out[:3, :3] = self.rotations[i + 1] if frac > 0.5 else self.rotations[i]
        return out

    def allowed_speed(self, s: float) -> float:
        """The fastest speed at arc length ``s`` from which the rest of the path can still be followed."""
        return float(np.interp(s, self.s, self.v))


def plan_path(q_start: np.ndarray, start: np.ndarray, goals: list[np.ndarray], speeds: list[float],
              accelerations: list[float], blends: list[float], tick: float,
              tcp_offset: np.ndarray) -> list[motion.Trajectory]:
    """One Trajectory per move of a blended run, cut where the tool passes each move's pose; the last tick of one
    is the first of the next.  Slowed as a whole where a joint would exceed ``motion.JOINT_SPEED_LIMIT``.
    Raises motion.Unreachable like ``motion.plan_line``."""
    profile = PathProfile.build(start, goals, speeds, accelerations, blends)
    traj, cuts = _solve(q_start, profile, tick, tcp_offset, 1.0)
    slower = motion.joint_speed_scale(traj, q_start)
    if slower < 0.999:
        profile = PathProfile.build(start, goals, speeds, accelerations, blends, slower * 0.98)
        traj, cuts = _solve(q_start, profile, tick, tcp_offset, slower * 0.98)
    out = []
    begin = 0
    for end in cuts:
        end = max(end, begin + 1) if len(traj.joints) > begin + 1 else begin
        out.append(motion.Trajectory(joints=traj.joints[begin:end + 1], tcp=traj.tcp[begin:end + 1], tick=tick,
                                     speed_scale=traj.speed_scale))
        begin = end
    return out


def _solve(q_start: np.ndarray, profile: PathProfile, tick: float, tcp_offset: np.ndarray,
           scale: float) -> tuple[motion.Trajectory, list[int]]:
    times = profile.times()
    total = float(times[-1])
    ticks = max(int(math.ceil(total / tick)), 1)
    at = np.minimum(np.arange(ticks + 1) * tick, total)
    s = np.interp(at, times, profile.s)
    s[-1] = profile.length
    poses = np.stack([profile.pose_at(float(v)) for v in s])
    cuts = [int(np.searchsorted(at, times[i] - 1e-9)) for i in profile.passes]
    cuts[-1] = ticks
    return motion.solve_poses(q_start, poses, tick, tcp_offset, scale), cuts


def plan_lines(steps, q: np.ndarray, pose: np.ndarray, tick: float, tcp_offset: np.ndarray,
               first: int = 0) -> dict[int, motion.Trajectory]:
    """Every MoveL of a plan (from step ``first``) as a line, starting at joints ``q`` and TCP ``pose``,
    keyed by step index; a blended run (``flgd.plans.blended_runs``) as one path cut at its moves' poses
    (``plan_path``).  Raises motion.Unreachable naming the step."""
    out = {}
    for a, b in blended_runs(tuple(steps)):
        if b < first:
            continue
        a = max(a, first)
        moves = steps[a:b + 1]
        goals = [pose_matrix(m.pose.position, m.pose.matrix) for m in moves]
        try:
            if b == a:
                parts = [motion.plan_line(q, pose, goals[0], moves[0].speed, moves[0].acceleration, tick, tcp_offset)]
            else:
                parts = plan_path(q, pose, goals, [m.speed for m in moves], [m.acceleration for m in moves],
                                  [m.blend for m in moves], tick, tcp_offset)
        except motion.Unreachable as exc:
            what = " to ".join(dict.fromkeys(m.label or "move" for m in moves))
            raise motion.Unreachable(f"step {a} ({what}): {exc}") from None
        for i, traj in zip(range(a, b + 1), parts):
            out[i] = traj
        q, pose = parts[-1].joints[-1], goals[-1]
    return out
