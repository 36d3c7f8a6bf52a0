"""The whole emulated cell: one world, the UR5e controller's servers, the RG2's service, the D415's feed, faults.

Addresses come from the cell config the daemon uses, so that one file describes both sides: the controller's
ports (29999 dashboard, 30001-30003 scripts, 30004 RTDE) on ``robot.host``, the RG2's XML-RPC service on
``robot.host:gripper.xmlrpc_port`` (the URCap runs on the controller), the camera feed on ``camera.emulator``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from flgd.config import CellConfig, parse_metrics_address

__all__ = ["EmulatedCell", "EmulatorConfigError"]

log = logging.getLogger(__name__)


class EmulatorConfigError(ValueError):
    """A cell config the emulator cannot play (names the key)."""


def _check(config: CellConfig) -> tuple[str, str, int]:
    """(controller host, camera feed host, camera feed port) from ``config``, or EmulatorConfigError."""
    where = config.source or "the config"
    if config.backend != "ur5e":
        raise EmulatorConfigError(f"{where}: backend is {config.backend!r}; flgd emulate plays the ur5e backend's "
                                  f"devices (set backend: ur5e)")
    host = config.robot.host
    if not host:
        raise EmulatorConfigError(f"{where}: robot.host is empty; give the loopback address to serve on "
                                  f"(e.g. 127.0.0.1)")
    if config.gripper.driver != "rg2_xmlrpc":
        raise EmulatorConfigError(f"{where}: gripper.driver is {config.gripper.driver!r}; the emulator plays "
                                  f"the RG2's XML-RPC service (rg2_xmlrpc)")
    if not config.camera.emulator:
        raise EmulatorConfigError(f"{where}: camera.emulator is empty; give the HOST:PORT the camera feed "
                                  f"serves on (e.g. 127.0.0.1:50010)")
    cam_host, cam_port = parse_metrics_address(config.camera.emulator)
    return host, cam_host, cam_port


class EmulatedCell:
    """Everything ``flgd emulate`` runs; ``start`` then ``close`` (which stops all of it)."""

    def __init__(self, config: CellConfig, *, time_scale: float = 1.0,
                 fault_socket: str | os.PathLike | None = None) -> None:
        from sim_cell.emulator.arm import EmulatedArm
        from sim_cell.emulator.camera_feed import CameraFeed
        from sim_cell.emulator.control_script import ControlScript
        from sim_cell.emulator.dashboard_server import DashboardServer
        from sim_cell.emulator.faults import FaultInjector, FaultSocket
        from sim_cell.emulator.rg2_service import RG2Service
        from sim_cell.emulator.rtde_server import Registers, RTDEServer
        from sim_cell.emulator.script_server import ScriptServer
        from sim_cell.emulator.world import EmulatorWorld

        host, cam_host, cam_port = _check(config)
        self.config = config
        self.world = EmulatorWorld(config, time_scale=time_scale)
        self.arm = EmulatedArm(self.world)
        self.registers = Registers()
        self.script = ControlScript(self.arm, self.registers)
        self.rtde = RTDEServer(self.arm, self.registers, host)
        self.dashboard = DashboardServer(self.arm, host)
        self.scripts = ScriptServer(self.script, host)
        self.gripper = RG2Service(self.world, host, config.gripper.xmlrpc_port)
        self.camera = CameraFeed(self.world, cam_host, cam_port)
        self.faults = FaultInjector(arm=self.arm, rtde=self.rtde, gripper=self.gripper, camera=self.camera)
        self.faults.watch(self.world)
        self.fault_socket = FaultSocket(self.faults, fault_socket) if fault_socket else None
        self._started: list[Any] = []

    def start(self) -> None:
        """Start the clock and every server; on a failure (a port taken) stop what started and raise."""
        try:
            for part in (self.world, self.dashboard, self.rtde, self.scripts, self.gripper, self.camera,
                         self.fault_socket):
                if part is None:
                    continue
                part.start()
                self._started.append(part)
        except Exception:
            self.close()
            raise

    def close(self) -> None:
        """Stop the fault socket, the servers and the clock (reverse order), then the simulator."""
        self.faults.close()
        for part in reversed(self._started):
            if part is self.world:
                continue  # closed last, with its simulator
            try:
                part.close()
            except Exception as exc:  # closing the rest matters more
                log.warning("closing %s: %s", type(part).__name__, exc)
        self._started.clear()
        self.world.close()

    def describe(self) -> str:
        """One line per device and its address, for the console."""
        host = self.config.robot.host
        lines = [f"UR5e controller on {host}: dashboard 29999, scripts 30001-30003, RTDE 30004",
                 f"RG2 (URCap XML-RPC) on {host}:{self.config.gripper.xmlrpc_port}",
                 f"D415 frames on {self.config.camera.emulator} (the daemon's camera.emulator)"]
        if self.fault_socket is not None:
            lines.append(f"faults: flgd emulate --inject KIND --faults {Path(self.fault_socket.path)}")
        return "\n".join(lines)
