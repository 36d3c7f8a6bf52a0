"""The UR controller's script ports (30001, 30002, 30003): a URScript program sent there replaces the running one.

ur_rtde's ScriptClient sends its control script (``def rtde_control():`` ...
``end``) to one of these ports; the emulator recognises that program, reads
the register offset ur_rtde injected into it (``reg_offset_int``, 0 or 24) and
the blended moves of a ``moveL(path)`` (``movel(p[...], a=, v=, r=)`` lines
after ``# inject move path``), and starts ``ControlScript`` on the arm -- ``runtime_state`` then reports the
program running.  Any other complete program stops the running one and is
logged as not emulated (the emulator does not interpret URScript).  The real
ports also stream the robot state to their clients; ur_rtde never reads it,
so the emulator sends nothing.
"""

from __future__ import annotations

import logging
import re
import socket

from sim_cell.emulator.control_script import ControlScript
from sim_cell.emulator.tcp_service import TCPService, start_all

__all__ = ["ScriptServer", "SCRIPT_PORTS"]

log = logging.getLogger(__name__)

SCRIPT_PORTS = (30001, 30002, 30003)   # primary, secondary, real-time: each accepts a program
MAX_PROGRAM = 4 * 1024 * 1024          # bytes; ur_rtde's script is about 60 kB
_DEF = re.compile(rb"^def\s+(\w+)\s*\(\s*\)\s*:", re.MULTILINE)
_END = re.compile(rb"^end\b", re.MULTILINE)
_OFFSET = re.compile(rb"global\s+reg_offset_int\s*=\s*(\d+)")
_INJECTED = re.compile(rb"# inject move path\s*\n(.*?)^\s*end\b", re.MULTILINE | re.DOTALL)
_NUMBER = rb"\s*([-+0-9.eE]+)\s*"
_MOVEL = re.compile(rb"movel\(\s*p\[" + rb",".join([_NUMBER] * 6) + rb"\]\s*,\s*a=" + _NUMBER + rb",\s*v="
                    + _NUMBER + rb",\s*r=" + _NUMBER + rb"\)")
CONTROL_PROGRAM = b"rtde_control"


def injected_path(program: bytes) -> list[tuple[list[float], float, float, float]]:
    """The moves ur_rtde wrote into its control script for ``moveL(path)`` (after ``# inject move path``):
    (pose, speed, acceleration, blend radius) each, in order; empty when the script carries none."""
    block = _INJECTED.search(program)
    if block is None:
        return []
    moves = []
    for m in _MOVEL.finditer(block.group(1)):
        values = [float(v) for v in m.groups()]
        moves.append((values[:6], values[7], values[6], values[8]))
    return moves


class ScriptServer:
    """The three script ports, starting ur_rtde's control program on ``ControlScript``."""

    def __init__(self, script: ControlScript, host: str = "127.0.0.1", *, ports: tuple[int, ...] = SCRIPT_PORTS):
        self.script = script
        self.programs: list[str] = []   # names of the programs received, for tests and logs
        self.services = [TCPService(f"script port {port}", host, port, self._serve) for port in ports]

    def start(self) -> None:
        start_all(self.services)

    def close(self) -> None:
        for service in self.services:
            service.close()

    def _serve(self, conn: socket.socket) -> None:
        buffer = b""
        while True:
            data = conn.recv(65536)
            if not data:
                return
            buffer += data
            if len(buffer) > MAX_PROGRAM:
                raise ValueError("script port: a program larger than 4 MB")
            buffer = self._take_programs(buffer)

    def _take_programs(self, buffer: bytes) -> bytes:
        """Run every complete program in ``buffer``; return what is left of it."""
        while True:
            start = _DEF.search(buffer)
            if start is None:
                return buffer[-1024:]   # text outside a program (a single script line): not emulated
            end = _END.search(buffer, start.end())
            if end is None:
                return buffer[start.start():]
            program = buffer[start.start():end.end()]
            self._run(start.group(1), program)
            buffer = buffer[end.end():]

    def _run(self, name: bytes, program: bytes) -> None:
        self.programs.append(name.decode("ascii", "replace"))
        arm = self.script.arm
        if name != CONTROL_PROGRAM:
            log.warning("script port: program %r is not emulated; the running program stops", name.decode())
            arm.stop_program()
            return
        offset = _OFFSET.search(program)
        arm.stop_program()   # a new program replaces the running one
        if self.script.start(int(offset.group(1)) if offset else 0, injected_path(program)):
            log.info("script port: ur_rtde's control script runs (register offset %d)", self.script.offset)
