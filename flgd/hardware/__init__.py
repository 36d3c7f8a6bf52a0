"""The real cell: UR5e through ur_rtde, OnRobot RG2, RealSense D415 through pyrealsense2.

Nothing here imports a hardware library at module import time: ``ur_rtde``
and ``pyrealsense2`` are loaded by :func:`hardware_library` when a real device
is opened, so ``flgd`` and the simulated cell run on a machine without them.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from flgd.cell import CellFault

__all__ = ["hardware_library", "HardwareUnavailable"]


class HardwareUnavailable(CellFault):
    """A hardware library cannot be imported on this machine."""


_INSTALL_HINTS = {
    "pyrealsense2": "pip install pyrealsense2 (it needs the system's libusb-1.0; see .ci/install.sh)",
    "rtde_control": "pip install ur-rtde",
    "rtde_receive": "pip install ur-rtde",
    "rtde_io": "pip install ur-rtde",
    "dashboard_client": "pip install ur-rtde",
}


def hardware_library(name: str) -> ModuleType:
    """Import a hardware library on first use; a missing one is a clear CellFault, not a traceback."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        hint = _INSTALL_HINTS.get(name, f"install the package providing {name}")
        raise HardwareUnavailable(f"the real cell needs the Python module {name!r}, which cannot be "
                                  f"imported here ({exc}); {hint}") from exc
