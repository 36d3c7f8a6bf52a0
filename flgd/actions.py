"""The discrete action space of FLG (paper III-A): a primitive at a heightmap pixel and rotation."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

Primitive = Literal["grasp", "push", "shift"]
PRIMITIVES: tuple[Primitive, ...] = ("grasp", "push", "shift")

__all__ = ["Action", "Primitive", "PRIMITIVES", "rotation_angle", "move_kind_at"]


def move_kind_at(height_at_point: float, shift_height: float) -> Primitive:
    """Paper III-A: a move that starts on an object (higher than ``shift_height``) is a shift, elsewhere a push.

    The one copy of the rule: the agent labels its decisions with it, the plans execute by it and the
    pictures draw by it, so the three cannot disagree.
    """
    return "shift" if height_at_point > shift_height else "push"


def rotation_angle(index: int, rotations: int = 16) -> float:
    """theta_i = 2*pi*i / n, counter-clockwise from the base x axis."""
    return 2.0 * math.pi * index / rotations


@dataclass(frozen=True)
class Action:
    """A primitive at heightmap pixel (row, col) with rotation index ``rotation``.

    Conventions: heightmap rows follow base y, columns follow base x, both
    increasing with the coordinate.  The direction of rotation i is
    u = (cos theta_i, sin theta_i) in the base xy plane: a grasp closes its
    fingers along u, a push or shift travels along u.  The Q-network's map
    channel 0 is grasp and channel 1 is move; a move becomes a push or a shift
    from the height at its pixel (``flgd.plans.move_kind``).
    """

    primitive: Primitive
    row: int
    col: int
    rotation: int
    rotations: int = 16

    def __post_init__(self) -> None:
        if self.primitive not in PRIMITIVES:
            raise ValueError(f"Action.primitive: got {self.primitive!r}, expected one of {PRIMITIVES}")
        if not (isinstance(self.rotations, int) and self.rotations > 0):
            raise ValueError(f"Action.rotations: got {self.rotations!r}, expected a positive integer")
        if not (isinstance(self.rotation, int) and 0 <= self.rotation < self.rotations):
            raise ValueError(f"Action.rotation: got {self.rotation!r}, expected 0..{self.rotations - 1}")

    @property
    def angle(self) -> float:
        return rotation_angle(self.rotation, self.rotations)

    @property
    def is_move(self) -> bool:
        return self.primitive != "grasp"

    @property
    def channel(self) -> int:
        """Q-map channel: 0 = grasp, 1 = move."""
        return 1 if self.is_move else 0
