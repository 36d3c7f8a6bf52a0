"""What the cell needs of any gripper: open or close to a width with a force limit, read the width, and the faults
a gripper raises.  The RG2's drivers (``flgd.hardware.rg2``) implement it; another gripper would too."""

from __future__ import annotations

import abc

from flgd.cell import CellFault

__all__ = ["GripperDriver", "GripperFault", "GripperWidthUnavailable"]


class GripperFault(CellFault):
    """The gripper did not do what it was told, or could not be reached."""


class GripperWidthUnavailable(GripperFault):
    """This driver has no way to measure the finger width."""


class GripperDriver(abc.ABC):
    """Open/close to a width with a force limit, and read the width."""

    measures_width: bool = True

    @abc.abstractmethod
    def move(self, width: float, force: float, proceed_after: float = 0.0) -> None:
        """Move the fingers towards ``width`` (m) with at most ``force`` (N); return when they stopped, or once
        they travelled ``proceed_after`` (m, > 0) towards it, leaving them to finish: the next move waits for
        them.  A driver that cannot see the fingers travel waits for the whole move."""

    @abc.abstractmethod
    def width(self) -> float:
        """Current finger opening in metres."""

    def stop(self) -> None:
        """Halt the fingers (best effort, any thread)."""

    def close(self) -> None:
        """Release connections; safe to call twice."""
