"""The cell interface: the little a robot cell must do, and the registry that finds cells by name.

A cell captures raw RGB-D frames and executes *checked* plans.  Everything
else -- heightmaps, rewards, decisions, plans, the safety envelope -- is
cell-independent and lives in ``flgd``.  Cells register a factory under a
name (``backend:`` in the config) so that a new arm or camera is a new module,
not an edit across the code base.
"""

from __future__ import annotations

import abc
import importlib
import threading
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from flgd.backends import backend_factory, backend_names, register_backend
from flgd.config import CellConfig
from flgd.geometry import ToolPose
from flgd.safety import CheckedPlan

__all__ = [
    "Frame",
    "ExecutionResult",
    "ContactStop",
    "Cell",
    "FrameOnTheWay",
    "WrappedCell",
    "CellFault",
    "StopPending",
    "STOPPED_ON_REQUEST",
    "register_cell",
    "make_cell",
    "available_cells",
]


@dataclass(frozen=True)
class Frame:
    """One raw RGB-D frame as a camera delivers it, plus what is needed to project it.

    color: HxWx3 uint8 RGB.  depth: HxW uint16 raw units (0 = no reading).
    intrinsics: 3x3 pinhole matrix.  camera_pose: 4x4 camera-to-base transform
    of the OpenCV optical frame (x right, y down, z forward).  ``tool_position``: where the
    cell read the TCP (x, y, z in the base frame) when the frame was taken, None from a cell
    that cannot tell; the cycle refuses a frame with the tool in view (``flgd.camera_view``).
    """

    color: np.ndarray
    depth: np.ndarray
    depth_scale: float
    intrinsics: np.ndarray
    camera_pose: np.ndarray
    timestamp: float = 0.0
    tool_position: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.color.ndim != 3 or self.color.shape[2] != 3 or self.color.dtype != np.uint8:
            raise ValueError(f"Frame.color: expected HxWx3 uint8, got {self.color.shape} {self.color.dtype}")
        if self.depth.shape != self.color.shape[:2]:
            raise ValueError(f"Frame.depth: shape {self.depth.shape} does not match color "
                             f"{self.color.shape[:2]}")
        if np.shape(self.intrinsics) != (3, 3) or np.shape(self.camera_pose) != (4, 4):
            raise ValueError("Frame: intrinsics must be 3x3 and camera_pose 4x4")
        if not self.depth_scale > 0:
            raise ValueError(f"Frame.depth_scale: expected > 0, got {self.depth_scale!r}")


@dataclass(frozen=True)
class ContactStop:
    """A guarded move (``MoveL.stop_on_contact``) that ended at a contact, short of its pose.

    Reported so that an engineer tuning ``robot.descent_contact_force`` can see
    how often a descent stopped and how far above its planned depth.
    """

    label: str  # the move's step label, e.g. "descend"
    short_by: float  # metres between where the TCP stopped and the move's pose


@dataclass
class ExecutionResult:
    """What happened when a cell ran a plan.

    ``completed`` is False when a motion could not be carried out (unreachable
    pose, collision stop); the cell is then left safe and the caller decides.
    ``widths`` holds the gripper widths measured at the plan's MeasureWidth steps;
    ``contact_stops`` the guarded moves that stopped at a contact.  ``duration`` is the
    time the plan took on the cell's own clock: the robot controller's on a real cell
    (an emulated one keeps its own), simulated time on a simulated one; ``gripper_time``
    the part of it spent on the gripper's commands and width readings (the rest is motion).
    """

    completed: bool
    widths: list[float] = field(default_factory=list)
    failure: str = ""
    duration: float = 0.0
    contact_stops: list[ContactStop] = field(default_factory=list)
    gripper_time: float = 0.0


# ExecutionResult.failure of a plan interrupted by Cell.stop_motion() contains this text.
STOPPED_ON_REQUEST = "stopped on request"


class CellFault(RuntimeError):
    """The cell cannot go on safely (protective stop, lost connection, camera gone ...).

    After a fault no further motion is attempted until ``Cell.recover`` succeeds.
    """


class StopPending(CellFault):
    """A stop was requested and not cleared: the cell refuses to recover or move.

    Raised by ``Cell.recover`` so that a stop arriving during a recovery is never
    erased by it; the caller should treat it as "stopping", not as a new fault.
    """


# Called with a frame taken while a plan was still running and the seconds on the cell's clock from the plan's start
# to when the frame was there (``Cell.execute_and_capture``); from any thread, at most once per plan.
FrameOnTheWay = Callable[[Frame, float], None]


class Cell(abc.ABC):
    """A robot cell: camera + arm + gripper behind one small interface."""

    name: str = "cell"

    def __init__(self, config: CellConfig):
        self.config = config
        self._lock = threading.RLock()

    # -- sensing
    @abc.abstractmethod
    def capture(self) -> Frame:
        """A fresh RGB-D frame, taken with the arm out of view."""

    # -- acting
    @abc.abstractmethod
    def execute(self, plan: CheckedPlan) -> ExecutionResult:
        """Run a plan that passed the safety envelope.

        Implementations must call ``plan.verify(self.config)`` first, so an
        unchecked or tampered plan never moves the arm.
        """

    def execute_and_capture(self, plan: CheckedPlan, on_frame: FrameOnTheWay) -> ExecutionResult:
        """Run ``plan`` as ``execute`` does and, during its last move, take a frame as soon as the tool has left the
        camera's view (``flgd.camera_view``) and hand it to ``on_frame`` while the arm moves on.

        Why: the next picture, and the decision on it, then overlap the end of the carry instead of following it.
        The frame's ``tool_position`` is where the tool was when it was taken; the caller checks it as for any
        frame.  This default (a cell that cannot take a picture while its arm moves, or a wrapper that changes
        ``execute``) runs the plan and takes none: the caller captures after it, as without."""
        return self.execute(plan)

    def stop_motion(self) -> None:
        """Halt the motion in flight now; callable from a signal handler or another thread.

        The interrupted ``execute`` returns ``completed=False`` with a failure
        containing ``STOPPED_ON_REQUEST``; the caller must then send nothing
        more.  The base implementation does nothing: it suits cells whose
        plans take a fraction of a second of wall time (the simulation), which
        simply finish the plan in flight.  A real arm overrides it (stopL).

        The request is latched: ``execute`` and ``recover`` refuse to move until
        ``clear_stop`` is called deliberately by the owner of the cell.
        """

    def clear_stop(self) -> None:
        """Forget a latched stop request; call only when no stop is pending (an operator's start or reset).

        Why a separate call: neither a new plan nor a recovery may clear a stop, or a
        stop that lands just before them would be lost and the arm would move after it.
        """

    @abc.abstractmethod
    def gripper_width(self) -> float:
        """Current finger opening in metres."""

    # -- life cycle
    def reset_scene(self) -> None:
        """Prepare a new episode (new clutter in simulation; nothing on a real cell)."""

    def can_reset_scene(self) -> bool:
        """True when ``reset_scene`` lays out a new scene by itself (a cell that overrides it, the simulation).

        Why it matters: a real cell cannot refill its own table, so on an empty
        workspace the daemon must wait for a person instead of cycling forever.
        """
        return type(self).reset_scene is not Cell.reset_scene

    def recover(self) -> None:
        """Clear a fault and bring the arm home; raise CellFault if that is not possible."""

    def workspace_empty_hint(self) -> bool | None:
        """A cell that *knows* the workspace is empty (simulation) says so; others return None."""
        return None

    def home_pose(self) -> ToolPose:
        h = self.config.robot.home
        return ToolPose.top_down(*h.position, h.yaw)

    def close(self) -> None:
        """Release hardware or the physics client.  Safe to call twice."""

    def __enter__(self) -> "Cell":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class WrappedCell(Cell):
    """A cell around another one that forwards every call to it, so that a wrapper states only what it changes
    (the curriculum's new scenes, an evaluation run's end, a test's injected fault)."""

    def __init__(self, inner: Cell, config: CellConfig | None = None) -> None:
        super().__init__(inner.config if config is None else config)
        self.inner = inner

    def capture(self) -> Frame:
        return self.inner.capture()

    def execute(self, plan: CheckedPlan) -> ExecutionResult:
        return self.inner.execute(plan)

    def stop_motion(self) -> None:
        self.inner.stop_motion()

    def clear_stop(self) -> None:
        self.inner.clear_stop()

    def gripper_width(self) -> float:
        return self.inner.gripper_width()

    def reset_scene(self) -> None:
        self.inner.reset_scene()

    def can_reset_scene(self) -> bool:
        return self.inner.can_reset_scene()

    def recover(self) -> None:
        self.inner.recover()

    def workspace_empty_hint(self) -> bool | None:
        return self.inner.workspace_empty_hint()

    def close(self) -> None:
        self.inner.close()


CellFactory = Callable[[CellConfig], Cell]


def register_cell(name: str, factory: str | CellFactory) -> None:
    """Register a cell factory (a callable, or "module:attribute" imported lazily) in ``flgd.backends``."""
    register_backend(name, factory)


def available_cells() -> list[str]:
    """The registered backend names (``flgd.backends``); whether one loads here is found by ``make_cell``."""
    return backend_names()


def make_cell(config: CellConfig, backend: str | None = None) -> Cell:
    """Create the cell named by ``backend`` (default: the config's backend)."""
    name = backend or config.backend
    factory = backend_factory(name)
    if factory is None:
        raise ValueError(f"unknown cell backend {name!r}; available: {', '.join(available_cells())}")
    if isinstance(factory, str):
        module_name, _, attr = factory.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise ValueError(f"cell backend {name!r} cannot load ({module_name}): {exc}") from exc
        factory = getattr(module, attr)
    return factory(config)
