"""The safety envelope: every pose of a plan, and every blended corner between two, is checked before any cell
sees it.

A plan with one bad step is refused as a whole, with the reason, and nothing of
it is sent.  Cells accept only ``CheckedPlan`` objects and re-verify them
against their own config, so a plan built by hand cannot bypass the check.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flgd.blending import corner_curve, corner_problem
from flgd.config import CellConfig
from flgd.plans import GripperCommand, MeasureWidth, MoveL, Plan, abort_steps

__all__ = ["PlanRefused", "CheckedPlan", "check_plan"]

_ORTHO_TOL = 1e-6
GRIPPER_STROKE = 0.110  # RG2: 0-110 mm


class PlanRefused(ValueError):
    """A plan left the safety envelope; ``reason`` says which step and why."""

    def __init__(self, reason: str, step: int | None = None):
        self.reason = reason
        self.step = step
        super().__init__(reason if step is None else f"step {step}: {reason}")


@dataclass(frozen=True)
class CheckedPlan:
    """A plan that passed the envelope of a given config."""

    plan: Plan
    _config_id: int

    def verify(self, config: CellConfig) -> Plan:
        """Re-check against ``config`` (the cell's own); raise PlanRefused if it does not pass."""
        check_plan(self.plan, config)
        return self.plan


def _finite(values) -> bool:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        return False
    return bool(np.all(np.isfinite(arr)))


def _check_position(pos, cfg: CellConfig) -> str | None:
    sf = cfg.safety
    for axis, v, (lo, hi) in zip("xyz", pos, (sf.envelope_x, sf.envelope_y, sf.envelope_z)):
        if not lo <= v <= hi:
            return f"{axis} = {v:.4f} m is outside the envelope [{lo}, {hi}] m"
    floor = cfg.workspace.table_z + sf.min_table_clearance
    if pos[2] < floor:
        return f"z = {pos[2]:.4f} m is below the table clearance floor {floor:.4f} m"
    return None


def _check_move(step: MoveL, cfg: CellConfig) -> str | None:
    sf = cfg.safety
    pos, rot = step.pose.position, step.pose.rotation
    if len(pos) != 3 or not _finite(pos):
        return f"position {pos!r} is not three finite numbers"
    r = np.asarray(rot, dtype=float) if _finite(rot) else None
    if r is None or r.shape != (3, 3):
        return "orientation is not a finite 3x3 rotation"
    if np.abs(r.T @ r - np.eye(3)).max() > _ORTHO_TOL or abs(np.linalg.det(r) - 1.0) > _ORTHO_TOL:
        return "orientation is not a proper rotation matrix"
    where = _check_position(pos, cfg)
    if where:
        return where
    tool_axis = r[:, 2]
    tilt = math.acos(max(-1.0, min(1.0, -float(tool_axis[2]))))
    if tilt > sf.max_tilt:
        return f"tool tilted {tilt:.3f} rad from straight down (max {sf.max_tilt} rad)"
    if not (_finite([step.speed]) and 0 < step.speed <= sf.max_speed):
        return f"speed {step.speed!r} m/s is outside (0, {sf.max_speed}] m/s"
    if not (_finite([step.acceleration]) and 0 < step.acceleration <= sf.max_acceleration):
        return f"acceleration {step.acceleration!r} m/s^2 is outside (0, {sf.max_acceleration}] m/s^2"
    if not (_finite([step.stop_on_contact]) and step.stop_on_contact >= 0.0):
        return f"stop_on_contact {step.stop_on_contact!r} N is not a finite force >= 0 N"
    if not (_finite([step.blend]) and 0.0 <= step.blend <= sf.max_blend_radius):
        return f"blend radius {step.blend!r} m is outside [0, {sf.max_blend_radius}] m (safety.max_blend_radius)"
    return None


def _check_corner(steps, i: int, cfg: CellConfig) -> str | None:
    """A move that blends into the next: both unguarded, the next a MoveL, a known incoming line (not the plan's
    first move, which starts wherever the arm is), the radius within half of each line, and every point of the
    blended corner inside the envelope."""
    step = steps[i]
    nxt = steps[i + 1] if i + 1 < len(steps) else None
    if not isinstance(nxt, MoveL):
        return "a move blends into a step that is not a move (it must stop there)"
    if step.stop_on_contact > 0.0 or nxt.stop_on_contact > 0.0:
        return "a guarded move (stop_on_contact) cannot blend, nor be blended into"
    before = next((s for s in reversed(steps[:i]) if isinstance(s, MoveL)), None)
    if before is None:
        return "the plan's first move cannot blend: its incoming line starts wherever the arm stands"
    why = corner_problem(before.pose.position, step.pose.position, nxt.pose.position, step.blend)
    if why:
        return why
    for point in corner_curve(before.pose.position, step.pose.position, nxt.pose.position, step.blend):
        where = _check_position(point, cfg)
        if where:
            return f"the blended corner passes {np.round(point, 4).tolist()}: {where}"
    return None


def _check_gripper(step: GripperCommand, cfg: CellConfig) -> str | None:
    if not (_finite([step.width]) and 0.0 <= step.width <= GRIPPER_STROKE):
        return f"gripper width {step.width!r} m is outside [0, {GRIPPER_STROKE}] m"
    if not (_finite([step.force]) and 0.0 < step.force <= cfg.gripper.force):
        return f"gripper force {step.force!r} N is outside (0, {cfg.gripper.force}] N"
    if not (_finite([step.proceed_after]) and 0.0 <= step.proceed_after <= GRIPPER_STROKE):
        return f"gripper proceed_after {step.proceed_after!r} m is outside [0, {GRIPPER_STROKE}] m"
    return None


def _check_proceeding(plan: Plan, i: int, cfg: CellConfig) -> str | None:
    """A gripper move the plan goes on from before the fingers stop (``proceed_after``): an opening to
    ``gripper.open_width`` (a release), or a grasp's pre-shape -- its first step (a grasp starts with nothing held:
    after a release), whose width the plan's next gripper step repeats after one move at most (the travel to the
    approach pose), so that the fingers have stopped at that width before anything comes down."""
    step = plan.steps[i]
    if step.width >= cfg.gripper.open_width:
        return None
    refused = (f"gripper proceed_after {step.proceed_after!r} m on a move to {step.width!r} m: only an opening to "
               f"gripper.open_width ({cfg.gripper.open_width} m) or a grasp's pre-shape (its first step, repeated "
               "by its next gripper step after one move at most) may go on before the fingers stop")
    if plan.primitive != "grasp" or i != 0:
        return refused
    moves = 0
    for later in plan.steps[i + 1:]:
        if isinstance(later, GripperCommand):
            return None if abs(later.width - step.width) <= 1e-9 and later.proceed_after == 0.0 else refused
        if isinstance(later, MoveL):
            moves += 1
            if moves > 1:
                return refused
    return refused


def check_plan(plan: Plan, config: CellConfig) -> CheckedPlan:
    """Check every step of ``plan``; return it wrapped as checked or raise PlanRefused."""
    if not isinstance(plan, Plan):
        raise PlanRefused(f"not a Plan: {type(plan).__name__}")
    if plan.refusal:
        raise PlanRefused(plan.refusal)
    if not plan.steps:
        raise PlanRefused("the plan has no steps")
    for i, step in enumerate(plan.steps):
        if isinstance(step, MoveL):
            why = _check_move(step, config)
            if why is None and step.blend > 0.0:
                why = _check_corner(plan.steps, i, config)
            if why is None and step.abort_on_contact:
                why = ("abort_on_contact on a move that is not guarded (stop_on_contact)" if step.stop_on_contact <= 0
                       else next(filter(None, (_check_move(m, config) for m in abort_steps(plan.steps, i))), None))
        elif isinstance(step, GripperCommand):
            why = _check_gripper(step, config)
            if why is None and step.proceed_after > 0.0:
                why = _check_proceeding(plan, i, config)
        elif isinstance(step, MeasureWidth):
            why = None
        else:
            why = f"unknown step type {type(step).__name__}"
        if why:
            raise PlanRefused(why, step=i)
    return CheckedPlan(plan, id(config))
