"""The UR controller's dashboard server (port 29999) on the emulated arm.

A line protocol: on connect the server sends its welcome line; each command
line gets one reply line.  The replies are PolyScope 5's texts for the
commands ur_rtde's DashboardClient and flgd's recovery send (power on, brake
release, unlock protective stop -- refused within 5 s of the stop --, close
safety popup, play/stop/pause/load, robotmode, safetymode/safetystatus,
PolyscopeVersion, serial number, remote control ...).  Anything else gets
"could not understand", as on a robot.
"""

from __future__ import annotations

import logging
import socket

from sim_cell.emulator.arm import EmulatedArm, Refused, RobotMode, SafetyMode
from sim_cell.emulator.rtde_server import CONTROLLER_VERSION
from sim_cell.emulator.tcp_service import TCPService

__all__ = ["DashboardServer", "DASHBOARD_PORT", "WELCOME"]

log = logging.getLogger(__name__)

DASHBOARD_PORT = 29999
WELCOME = "Connected: Universal Robots Dashboard Server"
POLYSCOPE_VERSION = "URSoftware {}.{}.{}.{} (Mar 22 2021)".format(*CONTROLLER_VERSION)
SERIAL_NUMBER = "20205500001"
MAX_LINE = 4096


class DashboardServer:
    """Port 29999 of the emulated controller."""

    def __init__(self, arm: EmulatedArm, host: str = "127.0.0.1", *, port: int = DASHBOARD_PORT):
        self.arm = arm
        self.loaded_program = ""
        self.service = TCPService("dashboard", host, port, self._serve)

    def start(self) -> None:
        self.service.start()

    def close(self) -> None:
        self.service.close()

    def _serve(self, conn: socket.socket) -> None:
        conn.sendall((WELCOME + "\n").encode())
        buffer = b""
        while not self.service.closing:
            data = conn.recv(1024)
            if not data:
                return
            buffer += data
            if len(buffer) > MAX_LINE and b"\n" not in buffer:
                raise ValueError("dashboard: a command line longer than 4 kB")
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                command = line.decode("utf-8", "replace").strip()
                reply = self.reply(command)
                conn.sendall((reply + "\n").encode())
                if command == "quit":
                    return

    def reply(self, command: str) -> str:
        """The controller's answer to one command line (and its effect on the arm)."""
        arm = self.arm
        word = command.split(" ", 1)
        head, arg = word[0], (word[1] if len(word) > 1 else "")
        simple = {
            "PolyscopeVersion": lambda: POLYSCOPE_VERSION,
            "get serial number": lambda: SERIAL_NUMBER,
            "get robot model": lambda: "UR5",
            "is in remote control": lambda: "true",
            "robotmode": lambda: f"Robotmode: {RobotMode.NAMES.get(arm.robot_mode, arm.robot_mode)}",
            "safetymode": lambda: f"Safetymode: {self._safety_name()}",
            "safetystatus": lambda: f"Safetystatus: {self._safety_name()}",
            "running": lambda: f"Program running: {'true' if arm.program_running else 'false'}",
            "programState": lambda: f"{'PLAYING' if arm.program_running else 'STOPPED'} "
                                    f"{self.loaded_program or '<unnamed>'}",
            "get loaded program": lambda: (f"Loaded program: {self.loaded_program}" if self.loaded_program
                                           else "No program loaded"),
            "isProgramSaved": lambda: f"true {self.loaded_program or '<unnamed>'}",
            "close popup": lambda: "closing popup",
            "close safety popup": self._close_safety_popup,
            "unlock protective stop": self._unlock,
            "power on": lambda: self._act(arm.power_on, "Powering on"),
            "power off": lambda: self._act(arm.power_off, "Powering off"),
            "brake release": lambda: self._act(arm.brake_release, "Brake releasing"),
            "play": lambda: self._act(arm.play, "Starting program", "Failed to execute: play"),
            "stop": lambda: self._act(arm.stop_program, "Stopped", "Failed to execute: stop"),
            "pause": lambda: self._act(arm.stop_program, "Pausing program", "Failed to execute: pause"),
            "restart safety": lambda: "Restarting safety",
            "quit": lambda: "Disconnected",
            "shutdown": lambda: "Shutting down",
        }
        if command in simple:
            return simple[command]()
        if head == "load" and arg:
            self.loaded_program = arg
            return f"Loading program: {arg}"
        if head == "popup":
            return "showing popup"
        if head == "addToLog":
            return "Added log message"
        return f"could not understand: '{command}'"

    def _safety_name(self) -> str:
        return SafetyMode.NAMES.get(self.arm.safety_mode, str(self.arm.safety_mode))

    @staticmethod
    def _act(action, done: str, failed: str | None = None) -> str:
        try:
            action()
        except Refused as exc:
            return failed or f"{done} failed: {exc}"
        return done

    def _unlock(self) -> str:
        try:
            self.arm.unlock_protective_stop()
        except Refused as exc:
            return str(exc)
        return "Protective stop releasing"

    def _close_safety_popup(self) -> str:
        self.arm.close_safety_popup()
        return "closing safety popup"
