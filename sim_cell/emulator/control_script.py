"""ur_rtde's control script as the emulated controller runs it: the command registers, interpreted on the arm.

ur_rtde uploads a URScript program (``def rtde_control():``) that loops reading
RTDE registers; the emulator does not interpret URScript, it plays that
program's register protocol (facts from ur_rtde 1.6.5's source and script):
  * ``input_int_register_0`` (+ the script's register offset, 0 or 24) holds
    the command number, the following int and double input registers its
    arguments in the order of the client's input recipe;
  * ``output_int_register_0`` is the handshake: 1 ready for a command, 2 done
    with it; the client then writes command 0 and the script is ready again;
  * ``output_int_register_1`` answers yes/no questions (isPoseWithinSafetyLimits ...),
    ``output_double_register_0..5`` return poses;
  * ``output_int_register_2`` reports the asynchronous operation: operation id
    (bits 24-30), a write counter (bits 16-22), running (bit 15), progress (bits 0-14).

The commands the emulator carries out are those flgd's URArm sends (moveL,
sync or async, a moveL path (MOVE_PATH: the moves the script server read from
the uploaded program), stopL, speedStop, setTcp, isPoseWithinSafetyLimits,
stopScript) and a few read-only queries; any other command number is
acknowledged and logged as not emulated.  A moveL the arm refuses stops the
program, as a URScript runtime error does on a robot.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from sim_cell import kinematics
from sim_cell.emulator.arm import EmulatedArm, Refused
from sim_cell.emulator.rtde_server import Registers

__all__ = ["ControlScript", "Command"]

log = logging.getLogger(__name__)

READY, DONE = 1, 2


class Command:
    """ur_rtde's command numbers (RTDE::RobotCommand::Type) that the emulator carries out."""
    NO_CMD, MOVEL, SPEED_STOP, SET_TCP, STOPL, STOPJ, MOVE_PATH = 0, 3, 15, 29, 33, 34, 45
    IS_POSE_WITHIN_SAFETY_LIMITS, IS_JOINTS_WITHIN_SAFETY_LIMITS, GET_TCP_OFFSET = 36, 37, 40
    GET_FORWARD_KINEMATICS_DEFAULT, IS_STEADY, GET_ACTUAL_TOOL_FLANGE_POSE = 43, 47, 58
    STOP_SCRIPT = 255
    DEFAULT_DECELERATION = 10.0   # m/s^2 for a speedStop without an argument


class ControlScript:
    """The running control program's register loop, one step per physics tick of the world."""

    def __init__(self, arm: EmulatedArm, registers: Registers):
        self.arm = arm
        self.regs = registers
        self.offset = 0
        self._waiting_for_motion = False   # a synchronous move/stop: DONE when the arm is still
        self._stale_stop = False           # the register still holds the stop that ended the previous program
        self._async_running = False
        self._op_id = 0
        self._writes = 0
        self.commands: list[int] = []       # every command carried out, for tests and logs
        self.path: list[tuple[list[float], float, float, float]] = []   # the running program's injected moves
        arm.world.add_tick(self._tick)

    # ------------------------------------------------------------------ program
    def start(self, register_offset: int = 0,
              path: list[tuple[list[float], float, float, float]] | None = None) -> bool:
        """The script was uploaded: the program runs if the arm lets it (False: it did not start).  ``path``: the
        blended moves written into it (pose, speed, acceleration, radius), run by a MOVE_PATH command."""
        self.path = list(path or [])
        try:
            self.arm.start_program()
        except Refused as exc:
            log.warning("control script not started: %s", exc)
            return False
        self.offset = int(register_offset)
        self._waiting_for_motion = False
        self._async_running = False
        # ur_rtde's stopScript leaves STOP_SCRIPT in the command register and its clear reaches RTDE on another
        # connection than the new program's upload: the new program must not take that stale stop for its own
        with self.regs.lock:
            self._stale_stop = self.regs.input_int[self.offset] == Command.STOP_SCRIPT
        self.regs.reset_outputs()
        self._write_progress(running=False)
        self._set_status(READY)
        return True

    # ------------------------------------------------------------------ registers
    def _in_int(self, i: int) -> int:
        return self.regs.input_int[self.offset + i]

    def _in_doubles(self, n: int) -> list[float]:
        return list(self.regs.input_double[self.offset:self.offset + n])

    def _set_status(self, value: int) -> None:
        with self.regs.lock:
            self.regs.output_int[self.offset] = value

    def _set_answer(self, value: int) -> None:
        with self.regs.lock:
            self.regs.output_int[self.offset + 1] = value

    def _set_pose(self, pose) -> None:
        with self.regs.lock:
            for i, v in enumerate(pose[:6]):
                self.regs.output_double[self.offset + i] = float(v)

    def _write_progress(self, running: bool, progress: int = 0) -> None:
        self._writes = (self._writes + 1) % 128
        if running and progress == 0:
            self._op_id = (self._op_id + 1) % 128
        value = (self._op_id << 24) | (self._writes << 16)
        if running:
            value |= 0x8000 | (progress & 0x7FFF)
        with self.regs.lock:
            self.regs.output_int[self.offset + 2] = value

    # ------------------------------------------------------------------ loop (physics tick, world lock held)
    def _tick(self, dt: float) -> None:
        arm = self.arm
        if not arm.program_running:
            if self._async_running:
                self._async_running = False
                self._write_progress(running=False)
            return
        if self._async_running and not arm.moving:
            self._async_running = False
            self._write_progress(running=False)
        with self.regs.lock:
            status = self.regs.output_int[self.offset]
            cmd = self.regs.input_int[self.offset]
        if self._waiting_for_motion:
            if not arm.moving:
                self._waiting_for_motion = False
                self._set_status(DONE)
            return
        if cmd != Command.STOP_SCRIPT:
            self._stale_stop = False
        if status == DONE and cmd == Command.NO_CMD:
            self._set_status(READY)
        elif status == READY and cmd != Command.NO_CMD and not (cmd == Command.STOP_SCRIPT and self._stale_stop):
            self._set_status(0)
            self.commands.append(cmd)
            if self._execute(cmd) and arm.program_running and not self._waiting_for_motion:
                self._set_status(DONE)

    @staticmethod
    def _no_path() -> None:
        raise Refused("move_path: the running script carries no path")

    def _start_motion(self, start: Callable[[], None]) -> bool:
        """Start a move (``start`` raises Refused when the arm refuses it: the program stops, as on a robot);
        asynchronous (the command's flag) it reports progress, else the command is done when the arm is still."""
        try:
            start()
        except Refused as exc:
            log.warning("control script: %s; the program stops", exc)
            self.arm.stop_program()
            return False
        if self._in_int(1) == 1:
            self._async_running = True
            self._write_progress(running=True)
        else:
            self._waiting_for_motion = True
        return True

    def _execute(self, cmd: int) -> bool:
        """Carry out one command; False when it ended the program (nothing more to signal)."""
        arm = self.arm
        if cmd == Command.MOVEL:
            values = self._in_doubles(8)
            return self._start_motion(lambda: arm.move_linear(values[:6], values[6], values[7]))
        if cmd == Command.MOVE_PATH:
            return self._start_motion(lambda: arm.move_path(self.path) if self.path else self._no_path())
        if cmd in (Command.STOPL, Command.STOPJ, Command.SPEED_STOP):
            deceleration = self._in_doubles(1)[0] or Command.DEFAULT_DECELERATION
            arm.stop_linear(deceleration)
            self._waiting_for_motion = not (cmd in (Command.STOPL, Command.STOPJ) and self._in_int(1) == 1)
        elif cmd == Command.SET_TCP:
            try:
                arm.set_tcp(self._in_doubles(6))
            except Refused as exc:
                log.warning("control script: %s; the program stops", exc)
                arm.stop_program()
                return False
        elif cmd == Command.IS_POSE_WITHIN_SAFETY_LIMITS:
            self._set_answer(1 if arm.pose_within_limits(self._in_doubles(6)) else 0)
        elif cmd == Command.IS_JOINTS_WITHIN_SAFETY_LIMITS:
            q = np.asarray(self._in_doubles(6))
            self._set_answer(1 if bool(np.all(np.abs(q) <= kinematics.JOINT_LIMITS)) else 0)
        elif cmd == Command.GET_TCP_OFFSET:
            self._set_pose(arm.tcp)
        elif cmd in (Command.GET_FORWARD_KINEMATICS_DEFAULT, ):
            self._set_pose(arm.tcp_pose())
        elif cmd == Command.GET_ACTUAL_TOOL_FLANGE_POSE:
            self._set_pose(arm.flange_pose())
        elif cmd == Command.IS_STEADY:
            self._set_answer(0 if arm.moving else 1)
        elif cmd == Command.STOP_SCRIPT:
            arm.stop_program()
            return False
        else:
            log.warning("control script: command %d is not emulated (acknowledged, nothing done)", cmd)
        return True
