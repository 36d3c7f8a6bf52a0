"""The emulated UR5e controller: the arm and its four servers (dashboard, RTDE, script ports) as one unit.

``flgd emulate`` and the tests start one of these on an ``EmulatorWorld``;
the faults a person or a test raises act on ``arm`` (protective stop,
emergency stop, stopped program) or on the connections (``drop_rtde``,
``drop_connections``).

What ur_rtde 1.6.5 does after a dropped link, seen against this emulator:
``RTDEReceiveInterface`` reports ``isConnected() == False`` and ``reconnect()``
works; ``RTDEControlInterface`` reconnects by itself from its receive thread
(dashboard, script upload, recipes) and at times loops on it or crashes the
client process at exit; ``RTDEIOInterface`` keeps reporting connected and its
``disconnect()`` raises "read: End of file".  Whether a real controller lets
these paths go better (it may stop the program on a lost link) is open; the
daemon does not depend on it: ur_rtde runs in a child process and a recovery
after a lost link opens fresh interfaces in a fresh one
(flgd/hardware/rtde_process.py).

The servers need their own process: ur_rtde's C++ calls keep Python's GIL
while they wait for the controller, so a client in the emulator's process
would wait for ever.
"""

from __future__ import annotations

from sim_cell.emulator.arm import EmulatedArm
from sim_cell.emulator.control_script import ControlScript
from sim_cell.emulator.dashboard_server import DashboardServer
from sim_cell.emulator.rtde_server import CONTROLLER_FREQUENCY, Registers, RTDEServer
from sim_cell.emulator.script_server import ScriptServer
from sim_cell.emulator.tcp_service import start_all
from sim_cell.emulator.world import EmulatorWorld

__all__ = ["EmulatedURController"]


class EmulatedURController:
    """Arm, registers, control script and the servers on ``host`` (the real ports)."""

    def __init__(self, world: EmulatorWorld, host: str = "127.0.0.1", *,
                 max_frequency: float = CONTROLLER_FREQUENCY):
        self.world = world
        self.host = host
        self.arm = EmulatedArm(world)
        self.registers = Registers()
        self.script = ControlScript(self.arm, self.registers)
        self.dashboard = DashboardServer(self.arm, host)
        self.rtde = RTDEServer(self.arm, self.registers, host, max_frequency=max_frequency)
        self.scripts = ScriptServer(self.script, host)
        self._servers = (self.dashboard, self.rtde, self.scripts)

    def start(self) -> None:
        """Listen on every port (PortTaken names the one that is busy) and start the world's clock."""
        start_all(self._servers)
        self.world.start()

    def close(self) -> None:
        for server in self._servers:
            server.close()

    def drop_rtde(self) -> None:
        """Every RTDE connection closes at once (the dashboard and script ports stay connected)."""
        self.rtde.drop_clients()

    def drop_connections(self) -> None:
        """A dropped network link: every connection to the controller closes at once."""
        self.rtde.drop_clients()
        self.dashboard.service.drop_clients()
        for service in self.scripts.services:
            service.drop_clients()
