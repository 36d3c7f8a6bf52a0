"""A real cell behind a wrapper that forwards everything: a test overrides only the calls it watches or fails."""

from __future__ import annotations

from typing import Any

from flgd.cell import Cell, ExecutionResult, Frame
from flgd.safety import CheckedPlan


class WrappedCell(Cell):
    """Forwards every call, and any other attribute (``object_count``, ``set_object_count`` ...), to ``inner``."""

    def __init__(self, inner: Cell) -> None:
        super().__init__(inner.config)
        self.inner = inner

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def capture(self) -> Frame:
        return self.inner.capture()

    def execute(self, plan: CheckedPlan) -> ExecutionResult:
        return self.inner.execute(plan)

    def gripper_width(self) -> float:
        return self.inner.gripper_width()

    def reset_scene(self) -> None:
        self.inner.reset_scene()

    def recover(self) -> None:
        self.inner.recover()

    def workspace_empty_hint(self) -> bool | None:
        return self.inner.workspace_empty_hint()

    def close(self) -> None:
        self.inner.close()
