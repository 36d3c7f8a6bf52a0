"""What a cell needs of a camera: one registered depth and colour frame per ``capture``, and ``close``.  The D415
(``flgd.hardware.d415``) implements it; a test or another camera passes its own to ``UR5eCell``."""

from __future__ import annotations

from typing import Protocol

from flgd.cell import CellFault, Frame

__all__ = ["Camera", "CameraFault"]


class CameraFault(CellFault):
    """The camera stopped delivering usable frames (timeout, disconnect, library error)."""


class Camera(Protocol):
    def capture(self) -> Frame:
        """The newest aligned depth and colour frame (CameraFault when none comes)."""
        ...

    def close(self) -> None:
        """Release the device; safe to call twice."""
        ...
