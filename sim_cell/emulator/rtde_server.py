"""The UR controller's RTDE interface (port 30004) on the emulated arm, as UR's RTDE guide describes it.

Packets: a big-endian header (uint16 size including the header, uint8 type),
then the payload.  What a client does and what the emulator answers:
  * ``V`` protocol version request (uint16) -> uint8 1 (accepted; versions 1 and 2; ur_rtde asks for 2);
  * ``v`` controller version -> four uint32: major, minor, bugfix, build (``CONTROLLER_VERSION``);
  * ``O`` output recipe (v2: double frequency, then comma-separated names) ->
    uint8 recipe id, comma-separated types (``NOT_FOUND`` for a name the
    controller does not know: the recipe is then invalid, id 0);
  * ``I`` input recipe (comma-separated names) -> recipe id, types;
  * ``S`` start / ``P`` pause -> uint8 1; after start, the controller sends a
    data package ``U`` (uint8 recipe id, the values in recipe order) at the
    recipe's frequency (at most the controller's 500 Hz, or ``max_frequency``),
    skipping the beats on which the world has not stepped since the last package
    (the emulated state changes only with a physics step), but never silent for
    more than ``MAX_SILENCE`` (the modes a fault sets between steps go out then);
  * ``U`` from the client: an input recipe's values, written into the
    controller's input registers and IO (tool digital outputs act on the arm).

The registers (``Registers``) are the controller's: every client sees the same
ones, and the emulated control script (``control_script``) reads the inputs
and writes the outputs.
"""

from __future__ import annotations

import logging
import math
import re
import select
import socket
import struct
import threading
import time
from typing import Any, Callable

from sim_cell.emulator.arm import ArmSnapshot, EmulatedArm
from sim_cell.emulator.tcp_service import TCPService, read_exact

__all__ = ["RTDEServer", "Registers", "RTDE_PORT", "CONTROLLER_VERSION", "output_type", "input_type"]

log = logging.getLogger(__name__)

RTDE_PORT = 30004
CONTROLLER_VERSION = (5, 11, 1, 108318)   # PolyScope 5.11.1: an e-Series controller, 500 Hz
CONTROLLER_FREQUENCY = 500.0
MAX_SILENCE = 0.02   # s: a package goes out at least this often even when no physics step has happened since
HEADER = struct.Struct(">HB")
REGISTER_COUNT = 48

# RTDE data types and their wire formats
_FORMATS = {"DOUBLE": "d", "UINT64": "Q", "UINT32": "I", "INT32": "i", "VECTOR6D": "6d", "VECTOR3D": "3d",
            "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I", "BOOL": "?", "UINT8": "B"}

_OUTPUT_TYPES = {
    "timestamp": "DOUBLE", "actual_execution_time": "DOUBLE", "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE", "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE", "actual_robot_current": "DOUBLE", "io_current": "DOUBLE",
    "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE", "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
    "tool_output_current": "DOUBLE", "tool_temperature": "DOUBLE", "tcp_force_scalar": "DOUBLE",
    "euromap67_24V_voltage": "DOUBLE", "euromap67_24V_current": "DOUBLE", "payload": "DOUBLE",
    "joint_position_deviation_ratio": "DOUBLE", "collision_detection_ratio": "DOUBLE",
    "robot_mode": "INT32", "safety_mode": "INT32", "safety_status": "INT32", "tool_output_voltage": "INT32",
    "runtime_state": "UINT32", "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32", "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
    "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32", "script_control_line": "UINT32",
    "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
    "actual_configurable_digital_io_bits": "UINT64",
    "joint_mode": "VECTOR6INT32",
    "actual_tool_accelerometer": "VECTOR3D", "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
    "payload_cog": "VECTOR3D",
    "tool_output_mode": "UINT8", "tool_digital_output0_mode": "UINT8", "tool_digital_output1_mode": "UINT8",
}
for _name in ("target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q", "actual_qd",
              "actual_current", "actual_current_window", "joint_control_output", "actual_TCP_pose",
              "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed", "joint_temperatures",
              "actual_joint_voltage", "ft_raw_wrench", "payload_inertia", "actual_current_as_torque"):
    _OUTPUT_TYPES[_name] = "VECTOR6D"

_INPUT_TYPES = {
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}
_REGISTER = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")


def _register_type(name: str, direction: str) -> str | None:
    m = _REGISTER.match(name)
    if not m:
        return None
    index = int(m.group(3))
    if m.group(2) == "bit":
        return "BOOL" if 64 <= index < 128 else None
    if index >= REGISTER_COUNT:
        return None
    if m.group(1) == "output" and direction == "input":
        return None   # a client cannot write the controller's output registers
    return "INT32" if m.group(2) == "int" else "DOUBLE"


def output_type(name: str) -> str | None:
    """The RTDE type of an output field, or None when the controller has no such output."""
    return _OUTPUT_TYPES.get(name) or _register_type(name, "output")


def input_type(name: str) -> str | None:
    """The RTDE type of an input field, or None when the controller accepts no such input."""
    return _INPUT_TYPES.get(name) or _register_type(name, "input")


class Registers:
    """The controller's general purpose registers (input: written by RTDE clients; output: by the script)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.input_int = [0] * REGISTER_COUNT
        self.input_double = [0.0] * REGISTER_COUNT
        self.output_int = [0] * REGISTER_COUNT
        self.output_double = [0.0] * REGISTER_COUNT
        self.changed = threading.Condition(self.lock)   # notified when a client writes an input

    def reset_outputs(self) -> None:
        with self.lock:
            self.output_int = [0] * REGISTER_COUNT
            self.output_double = [0.0] * REGISTER_COUNT


class _Recipe:
    def __init__(self, names: list[str], types: list[str]):
        self.names = names
        self.types = types
        self.struct = struct.Struct(">" + "".join(_FORMATS[t] for t in types))


def _flatten(values: list[Any]) -> list[Any]:
    out: list[Any] = []
    for v in values:
        if isinstance(v, (list, tuple)):
            out.extend(v)
        else:
            out.append(v)
    return out


class RTDEServer:
    """Port 30004 of the emulated controller: recipes, start/pause, data packages in and out."""

    def __init__(self, arm: EmulatedArm, registers: Registers, host: str = "127.0.0.1", *,
                 port: int = RTDE_PORT, max_frequency: float = CONTROLLER_FREQUENCY):
        self.arm = arm
        self.registers = registers
        self.max_frequency = float(max_frequency)
        self.service = TCPService("RTDE", host, port, self._serve)

    def start(self) -> None:
        self.service.start()

    def close(self) -> None:
        self.service.close()

    def drop_clients(self) -> None:
        """Close every RTDE connection now (a dropped link); clients may reconnect."""
        self.service.drop_clients()

    # ------------------------------------------------------------------ one client
    def _serve(self, conn: socket.socket) -> None:
        outputs: _Recipe | None = None
        inputs: dict[int, _Recipe] = {}
        period = 1.0 / CONTROLLER_FREQUENCY
        started = False
        version = 1
        next_send = time.monotonic()
        last_steps, last_sent = -1, 0.0
        while not self.service.closing:
            wait = max(next_send - time.monotonic(), 0.0) if started else 0.5
            readable, _, _ = select.select([conn], [], [], wait)
            if readable:
                size, kind = HEADER.unpack(read_exact(conn, HEADER.size))
                if size < HEADER.size:
                    raise ValueError(f"RTDE: packet size {size} is shorter than its header")
                payload = read_exact(conn, size - HEADER.size)
                if kind == ord("U"):
                    self._apply_inputs(payload, inputs)
                elif kind == ord("V"):
                    asked = struct.unpack(">H", payload[:2])[0]
                    if asked in (1, 2):
                        version = asked
                    self._send(conn, "V", struct.pack(">B", 1 if asked in (1, 2) else 0))
                elif kind == ord("v"):
                    self._send(conn, "v", struct.pack(">IIII", *CONTROLLER_VERSION))
                elif kind == ord("O"):
                    frequency, names = ((struct.unpack(">d", payload[:8])[0], payload[8:]) if version >= 2
                                        else (CONTROLLER_FREQUENCY, payload))   # v1: no frequency field
                    outputs, reply = self._output_recipe(names.decode("ascii"))
                    period = 1.0 / min(max(frequency, 1.0), self.max_frequency, CONTROLLER_FREQUENCY)
                    self._send(conn, "O", reply)
                elif kind == ord("I"):
                    recipe_id = len(inputs) + 1
                    recipe, reply = self._input_recipe(payload.decode("ascii"), recipe_id)
                    if recipe is not None:
                        inputs[recipe_id] = recipe
                    self._send(conn, "I", reply)
                elif kind == ord("S"):
                    started = outputs is not None
                    self._send(conn, "S", struct.pack(">B", 1 if started else 0))
                    next_send = time.monotonic()
                elif kind == ord("P"):
                    started = False
                    self._send(conn, "P", struct.pack(">B", 1))
                else:
                    raise ValueError(f"RTDE: unknown packet type {kind}")
            if started and outputs is not None and time.monotonic() >= next_send:
                steps = self.arm.world.steps   # counted after a step's ticks (the script's registers too)
                if steps != last_steps or time.monotonic() - last_sent >= MAX_SILENCE:
                    self._send(conn, "U", b"\x01" + self._pack_outputs(outputs, self.arm.state()))
                    last_steps, last_sent = steps, time.monotonic()
                next_send += period
                if time.monotonic() - next_send > 0.1:   # fell behind (a busy machine): do not burst
                    next_send = time.monotonic() + period

    @staticmethod
    def _send(conn: socket.socket, kind: str, payload: bytes) -> None:
        conn.sendall(HEADER.pack(HEADER.size + len(payload), ord(kind)) + payload)

    @staticmethod
    def _names(text: str) -> list[str]:
        return [n.strip() for n in text.split(",") if n.strip()]

    def _output_recipe(self, text: str) -> tuple[_Recipe | None, bytes]:
        names = self._names(text)
        types = [output_type(n) or "NOT_FOUND" for n in names]
        missing = [n for n, t in zip(names, types) if t == "NOT_FOUND"]
        if missing or not names:
            log.warning("RTDE: output recipe refused, unknown fields %s", missing)
            return None, b"\x00" + ",".join(types).encode("ascii")
        return _Recipe(names, types), b"\x01" + ",".join(types).encode("ascii")

    def _input_recipe(self, text: str, recipe_id: int) -> tuple[_Recipe | None, bytes]:
        names = self._names(text)
        types = [input_type(n) or "NOT_FOUND" for n in names]
        if "NOT_FOUND" in types or not names:
            log.warning("RTDE: input recipe refused: %s", names)
            return None, b"\x00" + ",".join(types).encode("ascii")
        return _Recipe(names, types), struct.pack(">B", recipe_id) + ",".join(types).encode("ascii")

    # ------------------------------------------------------------------ data
    def _apply_inputs(self, payload: bytes, inputs: dict[int, _Recipe]) -> None:
        recipe = inputs.get(payload[0]) if payload else None
        if recipe is None:
            raise ValueError(f"RTDE: data package for unknown input recipe {payload[:1]!r}")
        values = recipe.struct.unpack(payload[1:1 + recipe.struct.size])
        fields: dict[str, Any] = {}
        i = 0
        for name, kind in zip(recipe.names, recipe.types):
            n = int(_FORMATS[kind][0]) if _FORMATS[kind][0].isdigit() else 1
            fields[name] = values[i] if n == 1 else list(values[i:i + n])
            i += n
        regs = self.registers
        with regs.changed:
            for name, value in fields.items():
                m = _REGISTER.match(name)
                if m and m.group(2) == "int":
                    regs.input_int[int(m.group(3))] = int(value)
                elif m and m.group(2) == "double":
                    regs.input_double[int(m.group(3))] = float(value) if math.isfinite(value) else 0.0
            regs.changed.notify_all()
        if "tool_digital_output_mask" in fields and "tool_digital_output" in fields:
            self.arm.set_tool_digital_out(int(fields["tool_digital_output_mask"]), int(fields["tool_digital_output"]))

    def _pack_outputs(self, recipe: _Recipe, state: ArmSnapshot) -> bytes:
        regs = self.registers
        with regs.lock:
            values = [self._output_value(name, state, regs) for name in recipe.names]
        return recipe.struct.pack(*_flatten(values))

    @staticmethod
    def _output_value(name: str, s: ArmSnapshot, regs: Registers) -> Any:
        direct: dict[str, Callable[[], Any]] = {
            "timestamp": lambda: s.timestamp, "actual_q": lambda: s.actual_q, "actual_qd": lambda: s.actual_qd,
            "target_q": lambda: s.target_q, "actual_TCP_pose": lambda: s.actual_tcp_pose,
            "target_TCP_pose": lambda: s.target_tcp_pose, "actual_TCP_speed": lambda: s.actual_tcp_speed,
            "target_TCP_speed": lambda: s.actual_tcp_speed, "actual_TCP_force": lambda: s.actual_tcp_force,
            "robot_mode": lambda: s.robot_mode, "safety_mode": lambda: s.safety_mode,
            "safety_status": lambda: s.safety_mode, "safety_status_bits": lambda: s.safety_status_bits,
            "robot_status_bits": lambda: s.robot_status_bits, "runtime_state": lambda: s.runtime_state,
            "speed_scaling": lambda: 1.0, "target_speed_fraction": lambda: 1.0,
            "actual_digital_output_bits": lambda: s.tool_digital_outputs << 16,
            "joint_mode": lambda: [253] * 6,    # JOINT_RUNNING_MODE
            "actual_main_voltage": lambda: 48.0, "actual_robot_voltage": lambda: 48.0,
            "joint_temperatures": lambda: [30.0] * 6,
        }
        if name in direct:
            return direct[name]()
        m = _REGISTER.match(name)
        if m and m.group(2) == "int":
            return (regs.input_int if m.group(1) == "input" else regs.output_int)[int(m.group(3))]
        if m and m.group(2) == "double":
            return (regs.input_double if m.group(1) == "input" else regs.output_double)[int(m.group(3))]
        kind = output_type(name)
        width = int(_FORMATS[kind][0]) if _FORMATS[kind][0].isdigit() else 1
        zero = 0.0 if kind in ("DOUBLE", "VECTOR6D", "VECTOR3D") else (False if kind == "BOOL" else 0)
        return zero if width == 1 else [zero] * width
