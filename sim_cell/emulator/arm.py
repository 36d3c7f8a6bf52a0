"""The emulated UR5e controller's arm: its state as UR reports it and linear motion on the SimCell arm.

What a UR controller owns and what the emulator's servers read and command:
  * the TCP pose as UR reports it (base frame, metres, rotation vector) from the
    simulated joint angles and the active TCP offset (``set_tcp``; a fresh
    control script starts with the installation's TCP, ``config.robot.tcp_offset``),
    joint positions and speeds, and the force at the TCP from the sim's contacts;
  * robot mode, safety mode and status bits, and the runtime (program) state,
    with UR's numbers (the RTDE guide's tables);
  * moveL: a straight TCP line at the commanded speed and acceleration
    (trapezoidal, the rotation along with it), slowed where a joint would
    exceed the UR5e's rated 180 deg/s (``motion.JOINT_SPEED_LIMIT``), followed on the physics clock of
    ``EmulatorWorld`` by closed-form IK and the joint servos; ``stop_linear``
    decelerates along the line; a target out of reach is refused before
    anything moves (``pose_within_limits``); a moveL path (ur_rtde's
    ``moveL(path)``) runs its blended lines as one motion (``sim_cell.path_motion``);
  * the fault latch: a protective stop (also raised by the arm itself when the
    gripper presses on something harder than ``PROTECTIVE_STOP_FORCE``), an
    emergency stop, and the operator's actions on them.  Any fault ends a
    motion at once and stops the running program.  ``unlock_protective_stop``
    is refused within 5 s of the stop, as the controller refuses it.

Every pybullet call happens under ``world.lock``: motion runs in the world's
tick callback, and the readers take the lock for a consistent snapshot.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pybullet as p

from flgd.geometry import matrix_to_rotvec, rotvec_to_matrix
from sim_cell import kinematics, motion, path_motion
from sim_cell.path_motion import PathProfile
from sim_cell.emulator.world import EmulatorWorld

__all__ = ["EmulatedArm", "ArmSnapshot", "RobotMode", "SafetyMode", "RuntimeState", "Refused",
           "PROTECTIVE_STOP_UNLOCK_DELAY"]

log = logging.getLogger(__name__)


class RobotMode:
    """RTDE ``robot_mode`` values."""
    POWER_OFF, POWER_ON, IDLE, RUNNING = 3, 4, 5, 7
    NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
             4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}


class SafetyMode:
    """RTDE ``safety_mode`` values."""
    NORMAL, PROTECTIVE_STOP, ROBOT_EMERGENCY_STOP = 1, 3, 7
    NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
             6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT"}


class RuntimeState:
    """RTDE ``runtime_state`` values."""
    STOPPING, STOPPED, PLAYING, PAUSING, PAUSED, RESUMING = 0, 1, 2, 3, 4, 5


# safety_status_bits (RTDE guide): normal, reduced, protective stopped, recovery, safeguard stopped,
# system emergency stopped, robot emergency stopped, emergency stopped, violation, fault, stopped due to safety
_SAFETY_NORMAL, _SAFETY_PROTECTIVE, _SAFETY_ROBOT_ESTOP, _SAFETY_ESTOP, _SAFETY_STOPPED = 0, 2, 6, 7, 10
# robot_status_bits: power on, program running, teach button pressed, power button pressed
_STATUS_POWER_ON, _STATUS_PROGRAM_RUNNING = 0, 1

PROTECTIVE_STOP_UNLOCK_DELAY = 5.0   # s; the controller refuses an unlock sooner
PROTECTIVE_STOP_FORCE = 150.0        # N of push on the gripper that stops the arm (UR's default force limit)
PRESS_DEPTH = 0.006                  # m an object may be squeezed into what it rests on (sim_cell.cell)
SQUEEZE_STIFFNESS = PROTECTIVE_STOP_FORCE / PRESS_DEPTH   # N/m a squeezed block pushes back with
SETTLE_TOLERANCE = 2e-4              # rad of servo tracking error at which a finished line counts as arrived
SETTLE_TIME = 1.0                    # s a finished line waits at most for the servos (a UR reports a move done
                                     # once its servos have arrived; 0.3 s left a carried load 2 mm short)
MAX_SPEED = 3.0                      # m/s, the controller's limit for a tool speed
MAX_ACCELERATION = 150.0             # m/s^2
REACH_CHECK_TICK = 0.02              # s between the line samples checked for reach before a move


class Refused(Exception):
    """The controller refuses a command (not powered, a fault, unreachable): the text says why."""


@dataclass(frozen=True)
class ArmSnapshot:
    """The controller's state at one instant, as the RTDE outputs report it."""

    timestamp: float
    actual_q: list[float]
    actual_qd: list[float]
    target_q: list[float]
    actual_tcp_pose: list[float]
    target_tcp_pose: list[float]
    actual_tcp_speed: list[float]
    actual_tcp_force: list[float]
    robot_mode: int
    safety_mode: int
    safety_status_bits: int
    robot_status_bits: int
    runtime_state: int
    tool_digital_outputs: int


class _Line:
    """One moveL in progress: a straight line run along an online trapezoidal profile (or a stop ramp)."""

    def __init__(self, start: np.ndarray, goal: np.ndarray, speed: float, acceleration: float,
                 speed_scale: float = 1.0):
        self.start, self.goal = start, goal
        self.rel = matrix_to_rotvec(start[:3, :3].T @ goal[:3, :3])
        distance = float(np.linalg.norm(goal[:3, 3] - start[:3, 3]))
        angle = float(np.linalg.norm(self.rel))
        self.length, self.vmax, self.acc = motion.line_profile(distance, angle, speed, acceleration, speed_scale)
        self.speed_scale = speed_scale   # < 1: slowed so that no joint exceeds its rated speed
        self.s = 0.0
        self.v = 0.0
        self.stop_acc: float | None = None   # set by stopL: decelerate at this rate to rest
        self.arrived = self.length <= 1e-9
        self.settle = 0.0
        # only a line that goes down can press the gripper into what lies below it; a lift or a carry that
        # drags a held block along a neighbour is friction, not a collision (pybullet's soft contacts sink)
        self.descending = bool(goal[2, 3] < start[2, 3] - 1e-4)

    def advance(self, dt: float) -> None:
        if self.arrived:
            return
        if self.stop_acc is not None:
            self.v = max(self.v - self.stop_acc * dt, 0.0)
            self.s = min(self.s + self.v * dt, self.length)
            if self.v <= 0.0 or self.s >= self.length:
                self.arrived = True
            return
        left = self.length - self.s
        self.v = min(self.vmax, self.v + self.acc * dt, math.sqrt(2.0 * self.acc * left))
        if left <= max(self.v * dt, 1e-9):
            self.s, self.arrived = self.length, True
        else:
            self.s += self.v * dt

    def pose(self) -> np.ndarray:
        frac = 1.0 if self.length <= 1e-9 else self.s / self.length
        out = np.eye(4)
        out[:3, 3] = self.start[:3, 3] + frac * (self.goal[:3, 3] - self.start[:3, 3])
        out[:3, :3] = self.start[:3, :3] @ rotvec_to_matrix(self.rel * frac)
        return out

    @property
    def progress(self) -> float:
        return 1.0 if self.length <= 1e-9 else self.s / self.length

    def direction(self) -> np.ndarray:
        """The unit direction the TCP moves in now."""
        return (self.goal[:3, 3] - self.start[:3, 3]) / max(self.length, 1e-12)


class _Path(_Line):
    """A moveL path in progress: blended lines followed along ``path_motion.PathProfile`` online (or a stop
    ramp), never faster than the profile allows where the tool is."""

    def __init__(self, start: np.ndarray, profile: PathProfile, speed_scale: float = 1.0):
        self.profile = profile
        self.start, self.goal = start, profile.pose_at(profile.length)
        self.length, self.acc = profile.length, profile.acceleration
        self.vmax = float(profile.v.max())
        self.speed_scale = speed_scale
        self.s = 0.0
        self.v = 0.0
        self.stop_acc = None
        self.arrived = self.length <= 1e-9
        self.settle = 0.0
        self.descending = bool(np.any(np.diff(profile.positions[:, 2]) < -1e-4))

    def advance(self, dt: float) -> None:
        if self.arrived:
            return
        if self.stop_acc is not None:
            super().advance(dt)
            return
        left = self.length - self.s
        want = self.v + self.acc * dt
        self.v = min(want, max(self.profile.allowed_speed(self.s + want * dt), 0.5 * self.acc * dt))
        if left <= max(self.v * dt, 1e-9):
            self.s, self.arrived = self.length, True
        else:
            self.s += self.v * dt

    def pose(self) -> np.ndarray:
        return self.profile.pose_at(self.s)

    def direction(self) -> np.ndarray:
        ahead = self.profile.pose_at(self.s + 1e-3)[:3, 3] - self.profile.pose_at(self.s)[:3, 3]
        return ahead / max(float(np.linalg.norm(ahead)), 1e-12)


def pose_to_matrix(pose: Sequence[float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = np.asarray(pose[:3], float)
    out[:3, :3] = rotvec_to_matrix(np.asarray(pose[3:6], float))
    return out


def matrix_to_pose(m: np.ndarray) -> list[float]:
    return [float(v) for v in m[:3, 3]] + [float(v) for v in matrix_to_rotvec(m[:3, :3])]


class EmulatedArm:
    """The UR5e controller's arm state and motion on the SimCell arm (module docstring)."""

    def __init__(self, world: EmulatorWorld, *, clock=time.monotonic):
        self.world = world
        self._clock = clock
        self._robot = world.cell._robot
        self.installation_tcp = [float(v) for v in world.config.robot.tcp_offset] + [0.0, 0.0, 0.0]
        self.tcp = list(self.installation_tcp)
        self.robot_mode = RobotMode.RUNNING
        self.safety_mode = SafetyMode.NORMAL
        self.runtime_state = RuntimeState.STOPPED
        self.fault_reason: str | None = None
        self.protective_stop_at: float | None = None
        self._touch_depth: dict[int, float] = {}  # object -> its penetration when the gripper began touching it
        self._press_force = 0.0                     # N, vertical, on the gripper (last tick)
        self._squeeze = 0.0                         # m pressed into what it rests on since the touch (last tick)
        self.estop_engaged = False
        self.tool_digital_outputs = 0
        self.line: _Line | None = None
        self._target_q = self._robot.joints()
        self._last_q = self._target_q.copy()
        self._qd = np.zeros(6)
        self.faults: list[str] = []          # every fault raised, for tests and logs
        self._latest: ArmSnapshot | None = None   # the state at the last physics tick (state())
        world.add_tick(self._tick)

    # ------------------------------------------------------------------ frames
    def _tcp_matrix(self, q: np.ndarray, tcp: Sequence[float] | None = None) -> np.ndarray:
        tcp = self.tcp if tcp is None else tcp
        flange = kinematics.forward(q)
        return flange @ pose_to_matrix(tcp)

    def _flange_for(self, tcp_pose: np.ndarray) -> np.ndarray:
        return tcp_pose @ np.linalg.inv(pose_to_matrix(self.tcp))

    # ------------------------------------------------------------------ reading
    def state(self) -> ArmSnapshot:
        """The latest state without waiting for the world: kinematics of the last physics tick, modes now."""
        kin = self._latest
        if kin is None:
            return self.snapshot()
        return dataclasses.replace(kin, robot_mode=self.robot_mode, safety_mode=self.safety_mode,
                                   safety_status_bits=self._safety_bits(), robot_status_bits=self._status_bits(),
                                   runtime_state=self.runtime_state, tool_digital_outputs=self.tool_digital_outputs)

    def snapshot(self) -> ArmSnapshot:
        """The state now (takes the world's lock)."""
        with self.world.lock:
            q = self._robot.joints()
            actual = self._tcp_matrix(q)
            target = self.line.pose() if self.line is not None else self._tcp_matrix(self._target_q)
            speed = [0.0] * 6
            if self.line is not None and not self.line.arrived and self.line.length > 0:
                speed = [float(v) for v in self.line.direction() * self.line.v] + [0.0, 0.0, 0.0]
            return ArmSnapshot(
                timestamp=float(self.world.sim_time), actual_q=[float(v) for v in q],
                actual_qd=[float(v) for v in self._qd], target_q=[float(v) for v in self._target_q],
                actual_tcp_pose=matrix_to_pose(actual), target_tcp_pose=matrix_to_pose(target),
                actual_tcp_speed=speed, actual_tcp_force=self._tcp_force(),
                robot_mode=self.robot_mode, safety_mode=self.safety_mode,
                safety_status_bits=self._safety_bits(), robot_status_bits=self._status_bits(),
                runtime_state=self.runtime_state, tool_digital_outputs=self.tool_digital_outputs)

    def tcp_pose(self) -> list[float]:
        """The actual TCP pose [x, y, z, rx, ry, rz] with the active TCP."""
        with self.world.lock:
            return matrix_to_pose(self._tcp_matrix(self._robot.joints()))

    def flange_pose(self) -> list[float]:
        """The tool flange's pose (no TCP offset)."""
        with self.world.lock:
            return matrix_to_pose(kinematics.forward(self._robot.joints()))

    def _tcp_force(self) -> list[float]:
        """Contact force on the gripper (N, base frame), as the controller's TCP force estimate."""
        force = np.zeros(3)
        robot = self._robot
        for cp in p.getContactPoints(bodyA=robot.body, physicsClientId=robot.client):
            if cp[3] in robot.gripper_links:
                force += np.asarray(cp[7]) * cp[9]
        # pybullet's soft contacts let a squeezed block sink with little force, where a rigid one pushes back at
        # once: the push grows with the squeeze as it would (150 N at PRESS_DEPTH), so a guarded descent feels
        # its contact long before the protective stop
        force[2] += SQUEEZE_STIFFNESS * self._squeeze
        return [float(v) for v in force] + [0.0, 0.0, 0.0]

    def _safety_bits(self) -> int:
        bits = 0
        if self.safety_mode == SafetyMode.NORMAL:
            bits |= 1 << _SAFETY_NORMAL
        if self.safety_mode == SafetyMode.PROTECTIVE_STOP:
            bits |= (1 << _SAFETY_PROTECTIVE) | (1 << _SAFETY_STOPPED)
        if self.estop_engaged:
            bits |= (1 << _SAFETY_ROBOT_ESTOP) | (1 << _SAFETY_ESTOP) | (1 << _SAFETY_STOPPED)
        return bits

    def _status_bits(self) -> int:
        bits = 0
        if self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING):
            bits |= 1 << _STATUS_POWER_ON
        if self.program_running:
            bits |= 1 << _STATUS_PROGRAM_RUNNING
        return bits

    @property
    def program_running(self) -> bool:
        return self.runtime_state == RuntimeState.PLAYING

    @property
    def moving(self) -> bool:
        return self.line is not None

    def can_move(self) -> str | None:
        """Why the controller refuses motion now, or None."""
        if self.estop_engaged or self.safety_mode != SafetyMode.NORMAL:
            return f"safety mode {SafetyMode.NAMES.get(self.safety_mode, self.safety_mode)}"
        if self.robot_mode != RobotMode.RUNNING:
            return f"robot mode {RobotMode.NAMES.get(self.robot_mode, self.robot_mode)}"
        return None

    # ------------------------------------------------------------------ commands
    def set_tcp(self, tcp: Sequence[float]) -> None:
        values = [float(v) for v in tcp]
        if len(values) != 6 or not all(map(math.isfinite, values)):
            raise Refused(f"setTcp: {tcp!r} is not six finite numbers")
        with self.world.lock:
            self.tcp = values

    def pose_within_limits(self, pose: Sequence[float]) -> bool:
        """Whether the straight line from here to ``pose`` can be followed (the sim's IK, every sample)."""
        values = [float(v) for v in pose]
        if len(values) != 6 or not all(map(math.isfinite, values)):
            return False
        goal = pose_to_matrix(values)
        with self.world.lock:
            q = self._robot.joints()
            if float(np.linalg.norm(self.tcp[3:])) > 1e-9:   # a rotated TCP: the goal's IK only
                return kinematics.nearest_solution(kinematics.inverse(self._flange_for(goal)), q) is not None
            try:
                motion.plan_line(q, self._tcp_matrix(q), goal, 0.25, 1.2, REACH_CHECK_TICK,
                                 np.asarray(self.tcp[:3]))
            except motion.Unreachable:
                return False
            return True

    def move_linear(self, pose: Sequence[float], speed: float, acceleration: float) -> None:
        """Start a moveL to ``pose``; Refused when the arm cannot move or the line leaves the reach."""
        values = [float(v) for v in pose]
        if not (0.0 < speed <= MAX_SPEED and 0.0 < acceleration <= MAX_ACCELERATION):
            raise Refused(f"moveL: speed {speed} / acceleration {acceleration} outside the controller's limits")
        with self.world.lock:
            why = self.can_move()
            if why:
                raise Refused(f"moveL refused: {why}")
            if not self.pose_within_limits(values):
                raise Refused(f"moveL refused: {np.round(values, 4).tolist()} is out of reach")
            start = self._tcp_matrix(self._target_q)
            goal = pose_to_matrix(values)
            self.line = _Line(start, goal, float(speed), float(acceleration),
                              self._joint_speed_scale(start, goal, float(speed), float(acceleration)))
            if self.line.speed_scale < 1.0:
                log.info("moveL slowed to %.0f %% of its speed: a joint would exceed %.0f deg/s",
                         100.0 * self.line.speed_scale, math.degrees(motion.JOINT_SPEED_LIMIT))

    def move_path(self, moves: Sequence[tuple[Sequence[float], float, float, float]]) -> None:
        """Start a moveL path: (pose, speed, acceleration, blend radius) each, blended into one motion
        (``sim_cell.path_motion``); Refused when the arm cannot move or a part of the path leaves the reach."""
        if not moves:
            raise Refused("move_path: no moves")
        for pose, speed, acceleration, radius in moves:
            if not (0.0 < speed <= MAX_SPEED and 0.0 < acceleration <= MAX_ACCELERATION and radius >= 0.0):
                raise Refused(f"move_path: speed {speed} / acceleration {acceleration} / blend {radius} outside "
                              f"the controller's limits")
        with self.world.lock:
            why = self.can_move()
            if why:
                raise Refused(f"move_path refused: {why}")
            start = self._tcp_matrix(self._target_q)
            goals = [pose_to_matrix([float(v) for v in pose]) for pose, _, _, _ in moves]
            speeds = [float(m[1]) for m in moves]
            accelerations = [float(m[2]) for m in moves]
            blends = [float(m[3]) for m in moves]
            try:
                parts = path_motion.plan_path(self._target_q, start, goals, speeds, accelerations, blends,
                                              REACH_CHECK_TICK, np.asarray(self.tcp[:3]))
            except motion.Unreachable as exc:
                raise Refused(f"move_path refused: {exc}") from None
            scale = parts[0].speed_scale
            self.line = _Path(start, path_motion.PathProfile.build(start, goals, speeds, accelerations, blends,
                                                                   scale), scale)
            if scale < 1.0:
                log.info("moveL path slowed to %.0f %% of its speed: a joint would exceed %.0f deg/s",
                         100.0 * scale, math.degrees(motion.JOINT_SPEED_LIMIT))

    def _joint_speed_scale(self, start: np.ndarray, goal: np.ndarray, speed: float, acceleration: float) -> float:
        """How much a line must be slowed so that no joint exceeds the UR5e's rated speed (the controller's
        speed scaling); 1 for a rotated TCP, whose lines only the goal's reach is checked for."""
        if float(np.linalg.norm(self.tcp[3:])) > 1e-9:
            return 1.0
        try:
            return motion.plan_line(self._target_q, start, goal, speed, acceleration, REACH_CHECK_TICK,
                                    np.asarray(self.tcp[:3])).speed_scale
        except motion.Unreachable:
            return 1.0

    def stop_linear(self, deceleration: float) -> None:
        """stopL: decelerate the running line to rest at ``deceleration`` m/s^2 (nothing when still)."""
        with self.world.lock:
            if self.line is not None and not self.line.arrived:
                self.line.stop_acc = max(float(deceleration), 0.1)

    def hold(self) -> None:
        """End any motion now, the arm holding where it stands (a fault, a killed program)."""
        with self.world.lock:
            self.line = None
            self._target_q = self._robot.joints()
            self._robot.command_arm(self._target_q)

    # ------------------------------------------------------------------ motion (physics tick, lock held)
    def _tick(self, dt: float) -> None:
        self._measure_squeeze()
        q = self._robot.joints()
        self._qd = (q - self._last_q) / dt
        self._last_q = q
        self._move(dt, q)
        self._latest = self.snapshot()

    def _move(self, dt: float, q: np.ndarray) -> None:
        line = self.line
        if line is None:
            return
        if not line.arrived:
            line.advance(dt)
            flange = self._flange_for(line.pose())
            q_next = kinematics.nearest_solution(kinematics.inverse(flange), self._target_q)
            if q_next is None:
                self.protective_stop("the line left the arm's reach")
                return
            qd = (q_next - self._target_q) / dt
            self._target_q = q_next
            self._robot.command_arm(q_next, qd)
            if line.descending:
                self._check_press()
            return
        self._robot.command_arm(self._target_q)
        line.settle += dt
        if np.max(np.abs(q - self._target_q)) < SETTLE_TOLERANCE or line.settle > SETTLE_TIME:
            self.line = None

    def _measure_squeeze(self) -> None:
        """How far the gripper has pressed what it touches into what that rests on, since it touched it.

        Objects in a pile can rest a few mm into each other in pybullet; counting that as the gripper's press
        would stop the arm the instant it touches such an object, before any force builds up."""
        force, depths = self.world.cell._arm.contacts.pressing_by_object()
        self._touch_depth = {body: self._touch_depth.get(body, depth) for body, depth in depths.items()}
        self._press_force = force
        self._squeeze = max([depth - self._touch_depth[body] for body, depth in depths.items()] or [0.0])

    def _check_press(self) -> None:
        force, depth = self._press_force, self._squeeze
        if force > PROTECTIVE_STOP_FORCE or depth > PRESS_DEPTH:
            self.protective_stop(f"collision: the gripper pressed with {force:.0f} N "
                                 f"({depth * 1000:.0f} mm into an object)")

    # ------------------------------------------------------------------ faults and the operator
    def protective_stop(self, reason: str = "protective stop") -> None:
        """A protective stop: motion ends at once, the program stops, the stop waits for an unlock."""
        with self.world.lock:
            if self.estop_engaged:
                return
            self.faults.append(f"protective stop: {reason}")
            log.warning("emulated UR5e: protective stop: %s", reason)
            self.safety_mode = SafetyMode.PROTECTIVE_STOP
            self.protective_stop_at = self._clock()
            self.fault_reason = reason
            self._halt_program()

    def emergency_stop(self) -> None:
        """An emergency stop: motion ends, the program stops, the arm is powered off until released."""
        with self.world.lock:
            self.faults.append("emergency stop")
            log.warning("emulated UR5e: emergency stop")
            self.estop_engaged = True
            self.safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
            self.robot_mode = RobotMode.POWER_OFF
            self.fault_reason = "emergency stop"
            self._halt_program()

    def release_emergency_stop(self) -> None:
        """The button is pulled out: safety NORMAL, the arm stays powered off (power on, brake release)."""
        with self.world.lock:
            if self.estop_engaged:
                self.estop_engaged = False
                self.safety_mode = SafetyMode.NORMAL
                self.fault_reason = None

    def unlock_protective_stop(self) -> None:
        """Raise Refused within 5 s of the stop (the controller's rule) or when no protective stop is active."""
        with self.world.lock:
            if self.safety_mode != SafetyMode.PROTECTIVE_STOP:
                raise Refused("no protective stop to unlock")
            if self._clock() - (self.protective_stop_at or 0.0) < PROTECTIVE_STOP_UNLOCK_DELAY:
                raise Refused("Cannot unlock protective stop until 5s after occurrence. "
                              "Always inspect cause of protective stop before unlocking")
            self.safety_mode = SafetyMode.NORMAL
            self.protective_stop_at = None
            self.fault_reason = None

    def close_safety_popup(self) -> None:
        """Nothing to do: the emulator has no pendant screen."""

    def power_on(self) -> None:
        with self.world.lock:
            if self.estop_engaged:
                raise Refused("the emergency stop is engaged")
            if self.robot_mode == RobotMode.POWER_OFF:
                self.robot_mode = RobotMode.IDLE

    def power_off(self) -> None:
        with self.world.lock:
            self.robot_mode = RobotMode.POWER_OFF
            self._halt_program()

    def brake_release(self) -> None:
        with self.world.lock:
            if self.robot_mode == RobotMode.POWER_OFF:
                raise Refused("the arm is powered off")
            self.robot_mode = RobotMode.RUNNING

    def start_program(self) -> None:
        """A program starts (a control script arrived, or ``play``)."""
        with self.world.lock:
            if self.can_move():
                raise Refused(f"cannot start a program: {self.can_move()}")
            self.runtime_state = RuntimeState.PLAYING
            self.tcp = list(self.installation_tcp)   # a fresh program starts with the installation's TCP

    def play(self) -> None:
        self.start_program()

    def stop_program(self) -> None:
        """The running program stops (dashboard ``stop``, a fault injected): motion ends."""
        with self.world.lock:
            self._halt_program()

    def _halt_program(self) -> None:
        self.runtime_state = RuntimeState.STOPPED
        self.hold()

    def set_tool_digital_out(self, mask: int, levels: int) -> None:
        with self.world.lock:
            self.tool_digital_outputs = (self.tool_digital_outputs & ~mask) | (levels & mask)
