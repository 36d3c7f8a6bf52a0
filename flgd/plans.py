"""Primitive plans: a grasp, push or shift at (x, y, z, theta) becomes tool poses and gripper commands.

One implementation, used by every cell, so that the simulated and the real arm
execute the same motions.  Plans are pure data; ``flgd.safety.check_plan``
must pass before a cell runs one.

Distances (defaults in ``RobotConfig``, all configurable):
  * grasp: approach ``approach_height`` above the grasp point, open there (with ``gripper.preshape_margin``
    only as wide as the fingers need, set on the way: ``flgd.finger_preshape``), descend to
    ``grasp_depth`` below the surface (never below the table clearance; the
    descent stops early where the fingers meet ``descent_contact_force``; with
    ``contact_clearance`` and ``raise_speed`` it is slow only from that clearance
    above what surrounds the grasp down), close,
    lift to ``lift_height`` (slowly up to the approach height, or with
    ``contact_clearance`` until the object clears what surrounds it, then at
    ``raise_speed``), go home (the raise blended into it with ``blend_radius``),
    measure the width (the paper's success test).
  * place (after a grasp measured as held): carry to ``robot.place``, measure the
    width again, open (the arm goes on once ``gripper.release_gap`` is open), go
    home.  Only an object still between the fingers at the place pose was picked:
    one that slipped out on the way is a failed grasp.  With home at the place
    (``place_is_home``) the width read at home is the width at the place: the
    place is only the release.
  * push (the point is background): close, descend beside the objects to
    ``push_height`` above the table (guarded: a contact on the way down means the
    heightmap missed something there, and the push backs out and goes home),
    travel ``push_distance`` (10 cm) along theta, rise, go home.  The end point is
    clamped to the workspace.
  * shift (the point is on an object): close, press ``shift_press`` below the
    object's top surface, drag ``shift_distance`` (6 cm) along theta, rise, go
    home.  Friction between the closed fingers and the top of the object drags it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Union

import numpy as np

from flgd.actions import Action, move_kind_at
from flgd.config import CellConfig
from flgd.finger_preshape import preshape_width
from flgd.geometry import WRIST_YAW_LIMIT, ToolPose, nearest_symmetric_yaw, top_down_yaw
from flgd.grasp_view import FINGER_DEPTH, FINGER_HALF_WIDTH
from flgd.perception import pixel_to_base

__all__ = [
    "MoveL",
    "GripperCommand",
    "MeasureWidth",
    "RAISE_LABEL",
    "LOWER_LABEL",
    "PRESHAPE_LABEL",
    "PRESHAPE_PROCEED",
    "release_opening",
    "Step",
    "Plan",
    "move_kind",
    "blended_runs",
    "plan_action",
    "plan_grasp",
    "slow_lift_top",
    "slow_descent_top",
    "contact_zone_radius",
    "highest_around",
    "LIFT_LABEL",
    "PLACE_CHECK_LABEL",
    "plan_push",
    "plan_shift",
    "plan_release",
    "place_is_home",
    "plan_home",
    "abort_steps",
    "ABORT_LABEL",
    "WRIST_YAW_LIMIT",
    "tool_yaw",
    "end_yaw",
]


@dataclass(frozen=True)
class MoveL:
    """Linear tool move to ``pose`` at ``speed`` (m/s) and ``acceleration`` (m/s^2).

    ``stop_on_contact`` (N, 0 = off) makes it a guarded move: it ends early, where
    the tool first meets that much resistance, and the plan goes on from there.  A
    grasp descent is guarded so that a finger landing on a neighbouring object
    closes above it instead of pressing it into the table (a protective stop).
    The guarded move ends somewhere on the checked segment, so the envelope holds.

    ``blend`` (m, 0 = off) lets the move run into the next MoveL without stopping at ``pose``: the tool leaves the
    straight line ``blend`` before the pose and rejoins the next line ``blend`` after it (``flgd.blending``).
    Consecutive blended moves form one path (``blended_runs``), sent to a cell as one motion.

    ``abort_on_contact`` (a guarded move only): a contact ends the plan instead -- the rest of it becomes
    ``abort_steps``, straight back up to the previous pose and on to the plan's last.  A push comes down beside
    objects to near the table: meeting something there means the heightmap missed it, and pushing on would press
    it into the table (a protective stop).
    """

    pose: ToolPose
    speed: float
    acceleration: float
    label: str = ""
    stop_on_contact: float = 0.0
    blend: float = 0.0
    abort_on_contact: bool = False


@dataclass(frozen=True)
class GripperCommand:
    """Move the fingers to ``width`` (m) with at most ``force`` (N).

    ``proceed_after`` (m, 0 = off): the plan goes on once the fingers have travelled this far and they finish the
    move while the arm moves on; the cell's next gripper step waits for them.  A release needs the pads only off
    the object (``gripper.release_gap``), not the whole opening."""

    width: float
    force: float
    label: str = ""
    proceed_after: float = 0.0


@dataclass(frozen=True)
class MeasureWidth:
    """Record the gripper width at this point of the plan."""

    label: str = "width"


Step = Union[MoveL, GripperCommand, MeasureWidth]

LIFT_LABEL = "lift"   # a grasp's move up with the gripper closed: what is between the pads then was picked up
RAISE_LABEL = "raise"   # the rest of the way up to robot.lift_height, above the neighbours, at robot.raise_speed
LOWER_LABEL = "lower"   # a grasp's way down from the approach height to its contact zone, at robot.raise_speed
PRESHAPE_LABEL = "pre-shape"   # a grasp's first step: the fingers to its opening while the arm travels to it
PRESHAPE_PROCEED = 0.001   # m the fingers travel before a pre-shape lets the arm go on
RELEASE_OPENING = 0.01   # m a release opens beyond the width held, with a pre-shape and no gripper.release_gap
PLACE_CHECK_LABEL = "at place"   # the width read at the place pose before opening: still held there = picked


@dataclass(frozen=True)
class Plan:
    """An ordered list of steps for one primitive, with where it came from.

    ``refusal`` is set by a builder that already knows the request is invalid
    (a pixel outside the heightmap, say); the envelope then refuses the plan.
    """

    primitive: str
    steps: tuple[Step, ...]
    target: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    angle: float = math.nan
    refusal: str = ""
    notes: dict = field(default_factory=dict)

    @property
    def poses(self) -> list[ToolPose]:
        return [s.pose for s in self.steps if isinstance(s, MoveL)]


def tool_yaw(angle: float, wrist_yaw: float | None, config: CellConfig) -> float:
    """The wrist yaw a grasp or move along ``angle`` is made at: the equivalent (turned by pi) nearest
    ``wrist_yaw``, the yaw the tool has where the plan starts (None: the home pose's), within
    ``WRIST_YAW_LIMIT`` of the home pose's yaw."""
    home = config.robot.home.yaw
    return nearest_symmetric_yaw(angle, home if wrist_yaw is None else wrist_yaw, home, WRIST_YAW_LIMIT)


def end_yaw(plan: Plan, config: CellConfig) -> float | None:
    """The wrist yaw at the plan's last pose, as ``tool_yaw`` named it (None for a plan without moves)."""
    poses = plan.poses
    return top_down_yaw(poses[-1].matrix, config.robot.home.yaw) if poses else None


def _distance(a, b) -> float:
    return math.dist(tuple(a), tuple(b))


def _corner(radius: float, before: float, after: float) -> float:
    """The blend radius a corner between lines of lengths ``before`` and ``after`` can take: at most half of
    either (two corners of one line never overlap), 0 when that leaves less than a millimetre."""
    r = min(radius, 0.5 * before, 0.5 * after)
    return r if r >= 0.001 else 0.0


def blended_runs(steps: tuple[Step, ...]) -> list[tuple[int, int]]:
    """(first, last) step indices of every run of MoveL steps joined by blends (each but the last with
    ``blend`` > 0), in order; a run of one is a lone move."""
    runs: list[tuple[int, int]] = []
    i = 0
    while i < len(steps):
        if isinstance(steps[i], MoveL):
            j = i
            while (j + 1 < len(steps) and isinstance(steps[j], MoveL) and steps[j].blend > 0.0   # type: ignore[union-attr]
                   and isinstance(steps[j + 1], MoveL)):
                j += 1
            runs.append((i, j))
            i = j + 1
        else:
            i += 1
    return runs


def move_kind(height_at_point: float, config: CellConfig) -> str:
    """Paper III-A: a move on an object is a shift, elsewhere a push (``flgd.actions.move_kind_at``)."""
    return move_kind_at(height_at_point, config.rewards.shift_height)


def _refused(primitive: str, why: str) -> Plan:
    return Plan(primitive=primitive, steps=(), refusal=why)


def _target(action: Action, height_map: np.ndarray, config: CellConfig) -> tuple[tuple[float, float, float], float] | str:
    rows, cols = height_map.shape
    if not (0 <= action.row < rows and 0 <= action.col < cols):
        return f"pixel ({action.row}, {action.col}) is outside the {rows}x{cols} heightmap"
    h = float(height_map[action.row, action.col])
    if not math.isfinite(h):
        return f"height at pixel ({action.row}, {action.col}) is not finite ({h!r})"
    x, y, z = pixel_to_base(action.row, action.col, h, config.workspace)
    return (x, y, z), h


def slow_lift_top(z: float, surroundings_top: float, config: CellConfig) -> float:
    """Where a grasp's slow lift from fingertips at ``z`` ends: ``robot.approach_height`` above ``z``, or, with
    ``robot.contact_clearance``, once the object has risen that clearance above the highest point around the grasp
    (``surroundings_top``, above the table; an object's bottom is never below the table), whichever is lower.

    The lift stays over the grasp point, where the disc of ``robot.contact_radius`` is all the object can meet."""
    rb = config.robot
    full = z + rb.approach_height
    if rb.contact_clearance <= 0.0 or not math.isfinite(surroundings_top):
        return full
    return min(full, z + max(surroundings_top, 0.0) + rb.contact_clearance)


def slow_descent_top(z: float, surroundings_top: float, config: CellConfig) -> float:
    """Where a grasp's slow descent to fingertips at ``z`` begins: ``robot.approach_height`` above ``z``, or, with
    ``robot.contact_clearance``, that clearance above the highest point around the grasp (``contact_zone_radius``:
    the open fingers stay inside it on the way down), whichever is lower.  Above it the gripper comes straight down
    at ``raise_speed``, guarded as well (a part the camera did not see); the slanted approach still ends at the
    approach height."""
    rb = config.robot
    full = z + rb.approach_height
    if rb.contact_clearance <= 0.0 or not math.isfinite(surroundings_top):
        return full
    return min(full, max(config.workspace.table_z + max(surroundings_top, 0.0) + rb.contact_clearance, z))


def contact_zone_radius(config: CellConfig) -> float:
    """How far around a grasp its contact zone looks for the highest point: ``robot.contact_radius``, never less
    than the open fingers' reach (a descent must clear everything they can come down on)."""
    return max(config.robot.contact_radius, config.gripper.open_width / 2.0 + FINGER_DEPTH + FINGER_HALF_WIDTH)


def plan_grasp(x: float, y: float, surface_height: float, angle: float, config: CellConfig,
               surroundings_top: float = math.nan, wrist_yaw: float | None = None,
               opening: float = math.nan) -> Plan:
    """Top-down grasp with the fingers closing along ``angle`` at (x, y); heights above the table.

    ``surroundings_top``: the highest point within ``contact_zone_radius`` (``slow_lift_top``; NaN = unknown: the
    whole lift up to the approach height slow).  ``wrist_yaw``: the tool's yaw where the plan starts (``tool_yaw``;
    None: the home pose's).  ``opening`` (m; NaN = ``gripper.open_width``): the width the fingers come down at
    (``flgd.finger_preshape``); a narrower one is set as the plan's first step, while the arm travels to the
    approach pose (``PRESHAPE_LABEL``), and the fingers have stopped there before the descent."""
    if not all(map(math.isfinite, (x, y, surface_height, angle))):
        return _refused("grasp", f"non-finite grasp request x={x!r} y={y!r} "
                                 f"height={surface_height!r} angle={angle!r}")
    rb, gr, table = config.robot, config.gripper, config.workspace.table_z
    yaw = tool_yaw(angle, wrist_yaw, config)
    z = table + max(surface_height - rb.grasp_depth, config.safety.min_table_clearance)
    above, clear = z + rb.approach_height, slow_lift_top(z, surroundings_top, config)
    contact_top = slow_descent_top(z, max(surroundings_top, surface_height), config)
    lifted = table + rb.lift_height
    home = config.robot.home
    # with robot.raise_speed the lift is slow only among the neighbours (up to slow_lift_top), faster above; with
    # robot.blend_radius the raise runs on into home without stopping.  The lift itself never blends: it starts
    # where a guarded descent stopped (its length is known only then), and a blend into the raise would speed up
    # before the lift's pose, among the neighbours.
    lift: tuple[Step, ...] = (
        (MoveL(ToolPose.top_down(x, y, clear, yaw), rb.approach_speed, rb.acceleration, LIFT_LABEL),
         MoveL(ToolPose.top_down(x, y, lifted, yaw), rb.raise_speed, rb.acceleration, RAISE_LABEL,
               blend=_corner(rb.blend_radius, lifted - clear, _distance((x, y, lifted), home.position))))
        if rb.raise_speed > 0.0 and clear < lifted - 0.01 else
        (MoveL(ToolPose.top_down(x, y, lifted, yaw), rb.approach_speed, rb.acceleration, LIFT_LABEL),))
    # the fingers open at the approach pose, above everything the descent passes: a release at the place that
    # went on before they were open (gripper.release_gap) finishes during the approach
    width = gr.open_width if not math.isfinite(opening) else min(max(opening, gr.closed_width), gr.open_width)
    preshape: tuple[Step, ...] = ((GripperCommand(width, gr.force, PRESHAPE_LABEL, proceed_after=PRESHAPE_PROCEED),)
                                  if math.isfinite(opening) else ())
    steps: tuple[Step, ...] = (
        *preshape,
        MoveL(ToolPose.top_down(x, y, above, yaw), rb.speed, rb.acceleration, "approach"),
        GripperCommand(width, gr.force, "open"),
        *((MoveL(ToolPose.top_down(x, y, contact_top, yaw), rb.raise_speed, rb.acceleration, LOWER_LABEL,
                 stop_on_contact=rb.descent_contact_force),)
          if rb.raise_speed > 0.0 and contact_top < above - 0.01 else ()),
        MoveL(ToolPose.top_down(x, y, z, yaw), rb.approach_speed, rb.acceleration, "descend",
              stop_on_contact=rb.descent_contact_force),
        GripperCommand(gr.closed_width, gr.force, "close"),
        *lift,
        MoveL(ToolPose.top_down(*home.position, yaw if rb.carry_at_grasp_yaw else home.yaw), rb.speed,
              rb.acceleration, "home"),
        MeasureWidth("held"),
    )
    return Plan("grasp", steps, target=(x, y, z), angle=angle)


ABORT_LABEL = "abort"   # back up from a guarded move that met something it should not have (abort_on_contact)


def abort_steps(steps: tuple[Step, ...], i: int) -> tuple[MoveL, ...]:
    """What runs instead of the rest of ``steps`` when the guarded move ``steps[i]`` (``abort_on_contact``) met
    something: straight back to the pose of the move before it (where that guarded line began) at its speed, then
    the plan's last move (home) as planned.  Only poses of the plan itself: checked with it (``check_plan``)."""
    guarded = steps[i]
    if not isinstance(guarded, MoveL):
        raise ValueError(f"abort_steps: step {i} is not a MoveL")
    before = next((s for s in reversed(steps[:i]) if isinstance(s, MoveL)), None)
    last = next((s for s in reversed(steps[i + 1:]) if isinstance(s, MoveL)), None)
    out: tuple[MoveL, ...] = ()
    if before is not None:
        out += (MoveL(before.pose, guarded.speed, guarded.acceleration, ABORT_LABEL),)
    if last is not None:
        out += (MoveL(last.pose, last.speed, last.acceleration, last.label),)
    return out


def _travel_plan(primitive: str, x: float, y: float, z: float, angle: float, distance: float,
                 config: CellConfig, wrist_yaw: float | None) -> Plan:
    if not all(map(math.isfinite, (x, y, z, angle))):
        return _refused(primitive, f"non-finite {primitive} request x={x!r} y={y!r} z={z!r} angle={angle!r}")
    rb, gr, ws = config.robot, config.gripper, config.workspace
    yaw = tool_yaw(angle, wrist_yaw, config)
    # Keep the end of the travel over the table the camera sees.
    ex = min(max(x + distance * math.cos(angle), ws.x[0]), ws.x[1])
    ey = min(max(y + distance * math.sin(angle), ws.y[0]), ws.y[1])
    above = z + rb.approach_height
    home = config.robot.home
    steps: tuple[Step, ...] = (
        GripperCommand(gr.closed_width, gr.force, "close"),
        MoveL(ToolPose.top_down(x, y, above, yaw), rb.speed, rb.acceleration, "approach"),
        # a push comes down beside the objects: guarded, and a contact there ends it (a shift's press on the
        # object's top is meant)
        MoveL(ToolPose.top_down(x, y, z, yaw), rb.approach_speed, rb.acceleration, "descend",
              stop_on_contact=rb.descent_contact_force if primitive == "push" else 0.0,
              abort_on_contact=primitive == "push"),
        MoveL(ToolPose.top_down(ex, ey, z, yaw), rb.approach_speed, rb.acceleration, primitive),
        MoveL(ToolPose.top_down(ex, ey, above, yaw), rb.approach_speed, rb.acceleration, "retreat",
              blend=_corner(rb.blend_radius, above - z, _distance((ex, ey, above), home.position))),
        MoveL(ToolPose.top_down(*home.position, home.yaw), rb.speed, rb.acceleration, "home"),
    )
    return Plan(primitive, steps, target=(x, y, z), angle=angle,
                notes={"end": (ex, ey, z)})


def plan_push(x: float, y: float, angle: float, config: CellConfig, wrist_yaw: float | None = None) -> Plan:
    """Push along ``angle`` starting at (x, y), near table level (``wrist_yaw``: as for ``plan_grasp``)."""
    z = config.workspace.table_z + max(config.robot.push_height, config.safety.min_table_clearance)
    return _travel_plan("push", x, y, z, angle, config.robot.push_distance, config, wrist_yaw)


def plan_shift(x: float, y: float, surface_height: float, angle: float, config: CellConfig,
               wrist_yaw: float | None = None) -> Plan:
    """Press on the object top at (x, y) and drag it along ``angle`` (``wrist_yaw``: as for ``plan_grasp``)."""
    table = config.workspace.table_z
    z = table + max(surface_height - config.robot.shift_press, config.safety.min_table_clearance)
    return _travel_plan("shift", x, y, z, angle, config.robot.shift_distance, config, wrist_yaw)


CENTRING_TOLERANCE = 0.015  # m: a pixel this much below the chosen one's height is off the surface the fingers grip


def centred_grasp_pixel(height_map: np.ndarray, row: int, col: int, angle: float,
                        config: CellConfig) -> tuple[float, float]:
    """(row, col) moved along the finger pads, by at most ``robot.grasp_centring``, to the middle of the top surface
    it lies on.

    Why: an object held near one end of the pads turns under the carry and leaves the gripper on the way home
    (``flgd bench drops``: dropped objects sat a median 26 mm off the pads' centres, carried ones 14 mm).  The
    surface is the run of pixels along the pad axis through (row, col) no more than ``CENTRING_TOLERANCE`` below
    it; a lower neighbour ends it, the table too.
    """
    limit = config.robot.grasp_centring / config.workspace.resolution
    h0 = float(height_map[row, col])
    if limit <= 0.0 or not math.isfinite(h0) or h0 < config.rewards.min_height:
        return float(row), float(col)
    rows, cols = height_map.shape
    d_row, d_col = math.cos(angle), -math.sin(angle)  # the pads' axis, across the closing direction (x = col)
    reach = int(math.ceil(4.0 * limit)) + 1  # far enough to see a middle up to the limit away, past a near end

    def extent(sign: int) -> int:
        for s in range(1, reach + 1):
            r, c = int(round(row + sign * s * d_row)), int(round(col + sign * s * d_col))
            if not (0 <= r < rows and 0 <= c < cols):
                return s - 1
            h = float(height_map[r, c])
            if not math.isfinite(h) or h < h0 - CENTRING_TOLERANCE or h < config.rewards.min_height:
                return s - 1
        return reach

    offset = max(-limit, min(limit, (extent(1) - extent(-1)) / 2.0))
    return (min(max(row + offset * d_row, 0.0), rows - 1.0), min(max(col + offset * d_col, 0.0), cols - 1.0))


def highest_around(height_map: np.ndarray, row: float, col: float, radius: float, resolution: float) -> float:
    """The highest finite height (m above the table) within ``radius`` (m) of pixel (row, col); NaN if none is
    finite.  Pixels off the heightmap are not seen: the grasp's surroundings are the heightmap's own."""
    r = int(math.ceil(radius / resolution))
    rows, cols = height_map.shape
    r0, c0 = int(round(row)), int(round(col))
    lo_r, hi_r, lo_c, hi_c = max(r0 - r, 0), min(r0 + r + 1, rows), max(c0 - r, 0), min(c0 + r + 1, cols)
    if lo_r >= hi_r or lo_c >= hi_c:
        return math.nan
    patch = height_map[lo_r:hi_r, lo_c:hi_c]
    rr, cc = np.ogrid[lo_r:hi_r, lo_c:hi_c]
    inside = ((rr - row) ** 2 + (cc - col) ** 2) * resolution ** 2 <= radius ** 2
    values = patch[inside & np.isfinite(patch)]
    return float(values.max()) if values.size else math.nan


def plan_action(action: Action, height_map: np.ndarray, config: CellConfig, wrist_yaw: float | None = None) -> Plan:
    """The plan for an action chosen on ``height_map`` (metres above the table), from a tool at ``wrist_yaw``
    (``tool_yaw``; None: the home pose's).

    A move action is turned into a push or shift here (from the height at its
    pixel), whatever primitive the caller put in ``action``.
    """
    target = _target(action, height_map, config)
    if isinstance(target, str):
        return _refused(action.primitive, target)
    (x, y, _z), h = target
    if action.primitive == "grasp":
        row, col = float(action.row), float(action.col)
        if config.robot.grasp_centring > 0.0:
            row, col = centred_grasp_pixel(height_map, action.row, action.col, action.angle, config)
            x, y, _z = pixel_to_base(row, col, h, config.workspace)
        gr = config.gripper
        opening = math.nan
        if gr.preshape_margin > 0.0:
            fingertips = max(h - config.robot.grasp_depth, config.safety.min_table_clearance)
            opening = preshape_width(height_map, row, col, action.angle, fingertips, gr.open_width,
                                     gr.preshape_margin, config.workspace.resolution, config.rewards.min_height)
        return plan_grasp(x, y, h, action.angle, config,
                          surroundings_top=highest_around(height_map, row, col, contact_zone_radius(config),
                                                          config.workspace.resolution), wrist_yaw=wrist_yaw,
                          opening=opening)
    if move_kind(h, config) == "shift":
        return plan_shift(x, y, h, action.angle, config, wrist_yaw)
    return plan_push(x, y, action.angle, config, wrist_yaw)


PLACE_IS_HOME_TOLERANCE = 1e-6   # m between the home and the place position that counts as one pose


def place_is_home(config: CellConfig) -> bool:
    """Whether a grasp plan, which ends at home, ends at the place pose: the same position, and the same yaw
    (with ``robot.carry_at_grasp_yaw`` both keep the grasp's).  Its width read at home is then the place check."""
    rb = config.robot
    return (math.dist(rb.home.position, rb.place.position) <= PLACE_IS_HOME_TOLERANCE
            and (rb.carry_at_grasp_yaw or abs(rb.home.yaw - rb.place.yaw) <= 1e-9))


def release_opening(config: CellConfig, width: float | None) -> GripperCommand:
    """The release of fingers at ``width`` (m, as the grasp measured it; None = unknown): fully open, going on
    once ``gripper.release_gap`` is open; with ``gripper.preshape_margin`` only that gap (``RELEASE_OPENING``
    without one) beyond ``width``, waiting for it: the next grasp sets its own opening on the way
    (``PRESHAPE_LABEL``), and a full opening left running would make it wait."""
    gr = config.gripper
    if gr.preshape_margin > 0.0 and width is not None and math.isfinite(width):
        return GripperCommand(min(max(width, gr.closed_width) + (gr.release_gap or RELEASE_OPENING), gr.open_width),
                              gr.force, "open")
    return GripperCommand(gr.open_width, gr.force, "open", proceed_after=gr.release_gap)


def plan_release(held: bool, config: CellConfig, home: bool = True, carry_yaw: float | None = None,
                 width: float | None = None) -> Plan:
    """After a grasp: carry a held object to the place pose, read the width there and open; otherwise just open.

    The width at the place pose (``PLACE_CHECK_LABEL``) is the grasp's final judgement: an object that
    slipped out between the home pose and the place was not picked, on any cell.  ``home=False`` leaves the
    arm at the place (out of the camera's view, as home is): the next plan starts from there.  With
    ``robot.carry_at_grasp_yaw`` the place and home poses keep ``carry_yaw``, the wrist yaw the grasp ended at
    (``end_yaw`` of its plan).  With the place at home (``place_is_home``) the arm is there already and the
    grasp's width at home was read over the bin: the fingers just open (``flgd.cycle_record.held_at_place``
    judges by the grasp's width).  ``width``: the width the grasp measured, for ``release_opening``."""
    rb = config.robot
    release = release_opening(config, width)
    if not held:
        return Plan("release", (release,))
    if place_is_home(config):
        return Plan("place", (release,), target=tuple(rb.place.position))
    place = rb.place
    carry = carry_yaw if rb.carry_at_grasp_yaw and carry_yaw is not None else None
    steps: tuple[Step, ...] = (
        MoveL(ToolPose.top_down(*place.position, place.yaw if carry is None else carry), rb.speed,
              rb.acceleration, "place"),
        MeasureWidth(PLACE_CHECK_LABEL),
        release,
    )
    if home:
        steps += (MoveL(ToolPose.top_down(*rb.home.position, rb.home.yaw if carry is None else carry), rb.speed,
                        rb.acceleration, "home"),)
    return Plan("place", steps, target=tuple(place.position))


def plan_home(config: CellConfig) -> Plan:
    """Straight to the home pose with the gripper open."""
    rb, gr = config.robot, config.gripper
    home = rb.home
    return Plan("home", (
        MoveL(ToolPose.top_down(*home.position, home.yaw), rb.speed, rb.acceleration, "home"),
        GripperCommand(gr.open_width, gr.force, "open"),
    ), target=tuple(home.position))
