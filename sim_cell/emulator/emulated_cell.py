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
                 fault_socket: str | os.PathLike | None = None, marker: str | None = None,
                 marker_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        """``marker`` ("aruco" or "checkerboard") mounts a calibration marker on the gripper at ``marker_offset``
        (tool frame, m) for ``flgd calibrate`` (sim_cell/emulator/marker.py)."""
        from sim_cell.emulator.camera_feed import CameraFeed
        from sim_cell.emulator.faults import FaultInjector, FaultSocket
        from sim_cell.emulator.rg2_service import RG2Service
        from sim_cell.emulator.ur_controller import EmulatedURController
        from sim_cell.emulator.world import EmulatorWorld

        host, cam_host, cam_port = _check(config)
        self.config = config
        self.world = EmulatorWorld(config, time_scale=time_scale)
        self.controller = EmulatedURController(self.world, host)
        self.arm = self.controller.arm
        self.gripper = RG2Service(self.world, host, config.gripper.xmlrpc_port)
        self.camera = CameraFeed(self.world, cam_host, cam_port)
        self.faults = FaultInjector(arm=self.arm, rtde=self.controller.rtde, gripper=self.gripper,
                                    camera=self.camera)
        self.faults.watch(self.world)
        self.marker = None
        if marker is not None:
            from sim_cell.emulator.marker import CalibrationMarker

            self.marker = CalibrationMarker(self.world, marker, marker_offset)
        self.fault_socket = FaultSocket(self.faults, fault_socket) if fault_socket else None
        self._parts: list[Any] = [self.controller, self.gripper, self.camera]
        if self.fault_socket is not None:
            self._parts.append(self.fault_socket)

    def start(self) -> None:
        """The controller's servers and the world's clock, the RG2, the camera, the fault socket; on a failure
        (a port taken: PortTaken names it) what started is stopped and the error raised."""
        from sim_cell.emulator.tcp_service import start_all

        try:
            start_all(self._parts)
        except Exception:
            self.world.close()
            raise

    def close(self) -> None:
        """Stop the armed faults, the servers (reverse order), then the clock and the simulator."""
        self.faults.close()
        if self.marker is not None:
            self.marker.close()
        for part in reversed(self._parts):
            try:
                part.close()
            except Exception as exc:  # closing the rest matters more
                log.warning("closing %s: %s", type(part).__name__, exc)
        self.world.close()

    def describe(self) -> str:
        """One line per device and its address, for the console."""
        host = self.config.robot.host
        lines = [f"UR5e controller on {host}: dashboard 29999, scripts 30001-30003, RTDE 30004",
                 f"RG2 (URCap XML-RPC) on {host}:{self.config.gripper.xmlrpc_port}",
                 f"D415 frames on {self.config.camera.emulator} (the daemon's camera.emulator)"]
        if self.marker is not None:
            lines.append(f"calibration marker: {self.marker.kind} at {tuple(self.marker.offset.tolist())} m in the "
                         f"tool frame (flgd calibrate --marker {self.marker.kind} --marker-offset X Y Z)")
        if self.fault_socket is not None:
            lines.append(f"faults: flgd emulate --inject KIND --faults {Path(self.fault_socket.path)}")
        return "\n".join(lines)
