"""The cell backends by name: which ``backend:`` values exist, where each cell is built, which grippers it drives.

Why a leaf module (it imports nothing of ``flgd``): the config validates ``backend:`` and ``gripper.driver``
against these names, and the config is the bottom layer that the cell interface, the safety envelope and the
plans import; reading the names from ``flgd.cell`` would make the config import them back.  This module lists
names only; ``flgd.cell.make_cell`` imports a backend's module when one is opened, and it is there that a cell
whose libraries are missing on this machine fails to load.
"""

from __future__ import annotations

from typing import Any, Callable

__all__ = ["BACKEND_GRIPPER_DRIVERS", "backend_factory", "backend_names", "register_backend"]

# name -> "module:attribute", imported on first use so that a machine without a cell's libraries can still run
# the others, or a factory callable given to ``flgd.cell.register_cell``.
_FACTORIES: dict[str, str | Callable[[Any], Any]] = {
    "sim": "sim_cell.cell:SimCell",
    "ur5e": "flgd.hardware.ur5e_cell:UR5eCell",
}

# Gripper drivers each cell can drive.  A backend not listed here takes any driver: the simulated cell
# ignores gripper.driver (it simulates the RG2 itself), which also lets a real-cell config be swapped to
# the simulator with `flgctl backend sim`.
BACKEND_GRIPPER_DRIVERS: dict[str, tuple[str, ...]] = {
    "ur5e": ("rg2_xmlrpc", "tool_digital_output"),
}


def register_backend(name: str, factory: str | Callable[[Any], Any]) -> None:
    """Register a cell factory under ``name`` (a callable, or "module:attribute" imported lazily)."""
    _FACTORIES[name] = factory


def backend_names() -> list[str]:
    """Every registered backend name, sorted (whether its module imports on this machine is not checked)."""
    return sorted(_FACTORIES)


def backend_factory(name: str) -> str | Callable[[Any], Any] | None:
    """The factory registered under ``name``, or None."""
    return _FACTORIES.get(name)
