"""The cell config's schema: one frozen dataclass per section, each field with its default, unit and limits.

Units are explicit and fixed: metres, radians, seconds, m/s, m/s^2.  The limits given to ``param`` are checked
by ``flgd.config.convert``; what holds between keys is in ``flgd.config.rules``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

__all__ = [
    "param", "Range", "Vec3", "WorkspaceConfig", "IntrinsicsConfig", "PoseConfig", "CameraConfig", "ToolPoseConfig",
    "RobotConfig", "GripperConfig", "SafetyConfig", "RewardConfig", "ExplorationConfig", "LearningConfig",
    "FinetuneConfig", "GateConfig", "StorageConfig", "CameraPoseErrorConfig", "SimConfig", "CalibrationWatchConfig",
    "CellConfig",
]


def param(default: Any = dataclasses.MISSING, *, unit: str | None = None, gt: float | None = None,
          ge: float | None = None, le: float | None = None, lt: float | None = None,
          help: str = "", default_factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field with range limits and a unit used for validation and messages."""
    meta = {"unit": unit, "gt": gt, "ge": ge, "le": le, "lt": lt, "help": help}
    if default_factory is not dataclasses.MISSING:
        return field(default_factory=default_factory, metadata=meta)
    return field(default=default, metadata=meta)


Range = tuple[float, float]
Vec3 = tuple[float, float, float]


# --------------------------------------------------------------------------- sections

@dataclass(frozen=True)
class WorkspaceConfig:
    """The table region seen by the heightmap, in the robot base frame."""

    x: Range = param((-0.724, -0.276), unit="m", help="min, max of the heightmap region")
    y: Range = param((-0.224, 0.224), unit="m")
    z: Range = param((0.0, 0.3), unit="m", help="table surface height, top of the region")
    resolution: float = param(0.002, unit="m/px", gt=0.0, le=0.05)

    @property
    def table_z(self) -> float:
        return self.z[0]

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the heightmap: rows follow y, columns follow x."""
        return (int(round((self.y[1] - self.y[0]) / self.resolution)),
                int(round((self.x[1] - self.x[0]) / self.resolution)))


@dataclass(frozen=True)
class IntrinsicsConfig:
    width: int = param(640, unit="px", gt=0)
    height: int = param(480, unit="px", gt=0)
    fx: float = param(615.0, unit="px", gt=0.0)
    fy: float = param(615.0, unit="px", gt=0.0)
    cx: float = param(320.0, unit="px")
    cy: float = param(240.0, unit="px")


@dataclass(frozen=True)
class PoseConfig:
    """A rigid pose in the robot base frame: position and roll/pitch/yaw.

    The rotation is R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (extrinsic x-y-z).
    """

    position: Vec3 = param((0.0, 0.0, 0.0), unit="m")
    rpy: Vec3 = param((0.0, 0.0, 0.0), unit="rad")


@dataclass(frozen=True)
class CameraConfig:
    """The RGB-D camera.  Its optical frame follows OpenCV: x right, y down, z forward."""

    serial: str = param("", help="device serial number; empty picks the only camera")
    intrinsics: IntrinsicsConfig = param(default_factory=IntrinsicsConfig)
    depth_scale: float = param(0.001, unit="m/unit", gt=0.0, help="metres per raw depth unit")
    depth_range: Range = param((0.15, 2.0), unit="m", help="valid depth readings")
    pose: PoseConfig = param(default_factory=lambda: PoseConfig(position=(-0.5, 0.0, 0.62),
                                                               rpy=(math.pi, 0.0, -math.pi / 2)))
    fps: int = param(30, unit="Hz", gt=0)
    frame_timeout: float = param(2.0, unit="s", gt=0.0)
    depth_scale_correction: float = param(1.0, ge=0.9, le=1.1,
                                          help="real cell: multiplies the device's depth scale; "
                                               "measured by `flgd calibrate`")
    spatial_filter: bool = param(False, help="real cell: librealsense edge-preserving spatial depth filter")
    temporal_filter: bool = param(False, help="real cell: librealsense temporal filter over a few "
                                              "consecutive frames per capture")
    hole_filling: bool = param(False, help="real cell: librealsense hole filling of missing depth")
    emulator: str = param("", help="real cell: HOST:PORT of `flgd emulate`'s camera feed, read through a "
                                   "librealsense software device instead of a camera; empty = the real D415")
    depth_fill: Literal["lowest", "inpaint", "none"] = param(
        "none", help="heightmap cells without a depth reading, every cell: lowest = the lowest height on the hole's "
                     "rim (holes in objects get their height, shadows beside them the table's), inpaint = OpenCV "
                     "inpainting, none = table height (unfilled; what the shipped policy was trained on)")


@dataclass(frozen=True)
class ToolPoseConfig:
    """A top-down tool pose: TCP position and rotation about the vertical axis."""

    position: Vec3 = param((0.0, 0.0, 0.0), unit="m")
    yaw: float = param(0.0, unit="rad")


@dataclass(frozen=True)
class RobotConfig:
    host: str = param("", help="controller address (real cell)")
    home: ToolPoseConfig = param(default_factory=lambda: ToolPoseConfig((-0.45, 0.30, 0.30), 0.0),
                                 help="where every picture is taken from: beside the workspace, out of the camera's view")
    place: ToolPoseConfig = param(default_factory=lambda: ToolPoseConfig((-0.5, 0.32, 0.30), 0.0),
                                  help="where a grasped object is released, outside the heightmap")
    approach_height: float = param(0.10, unit="m", gt=0.0, help="above the target before descending")
    lift_height: float = param(0.25, unit="m", gt=0.0, help="TCP height above the table after a grasp")
    grasp_depth: float = param(0.03, unit="m", ge=0.0, help="how far below the surface the fingertips go")
    push_height: float = param(0.012, unit="m", gt=0.0, help="TCP height above the table during a push")
    push_distance: float = param(0.10, unit="m", gt=0.0)
    shift_press: float = param(0.012, unit="m", ge=0.0, help="how far below the top surface a shift presses")
    shift_distance: float = param(0.06, unit="m", gt=0.0)
    speed: float = param(0.25, unit="m/s", gt=0.0, help="free moves")
    approach_speed: float = param(0.10, unit="m/s", gt=0.0,
                                  help="descents, pushes and shifts, and a grasp's lift (up to the approach height "
                                       "when raise_speed is set)")
    raise_speed: float = param(0.0, unit="m/s", ge=0.0,
                               help="a grasp's straight moves above its contact zone: the lift above "
                                    "robot.approach_height over the grasp (or above robot.contact_clearance), where the "
                                    "object has left its neighbours, and with contact_clearance the way down to the "
                                    "zone (0 = the whole lift and descent at approach_speed)")
    contact_clearance: float = param(
        0.0, unit="m", ge=0.0, le=0.10,
        help="a grasp is slow only this far above the highest point the heightmap shows within "
             "robot.contact_radius of the grasp: its guarded descent starts there and its slow lift ends once the "
             "object has risen that far above it (never higher than robot.approach_height over the grasp point; "
             "0 = slow over the whole approach height); with raise_speed")
    contact_radius: float = param(0.08, unit="m", gt=0.0, le=0.20,
                                  help="how far around a grasp robot.contact_clearance looks for the highest point "
                                       "(never less than the open fingers' reach, 6.85 cm with the RG2 open 85 mm)")
    blend_radius: float = param(
        0.0, unit="m", ge=0.0,
        help="free moves of a plan run into each other through a corner of this radius instead of stopping at each "
             "pose: a grasp's raise into home, a push's or shift's retreat into home (0 = stop at every pose); "
             "<= safety.max_blend_radius")
    grasp_centring: float = param(
        0.0, unit="m", ge=0.0, le=0.05,
        help="a grasp moves along the finger pads towards the middle of the top surface it was chosen on, by at most "
             "this much, so that the object sits between the pads' centres (0 = grasp where the policy chose)")
    descent_contact_force: float = param(
        20.0, unit="N", ge=0.0,
        help="a grasp descent stops where the fingers meet this much resistance and closes there (0 = no guard)")
    acceleration: float = param(0.8, unit="m/s^2", gt=0.0)
    tcp_offset: Vec3 = param((0.0, 0.0, 0.20), unit="m", help="flange to fingertip centre")
    carry_at_grasp_yaw: bool = param(
        False, help="a picked object is carried home and to the place at the wrist angle it was grasped at, so the "
                    "wrist turns once a pick (from the last grasp's angle to the next) instead of twice (its yaw in "
                    "the bin does not matter)")
    capture_on_the_way: bool = param(
        False, help="with decide_while_placing: take the next picture on a grasp's move home, once a 12 cm cylinder "
                    "around the tool (an object up to 24 cm long held across its middle) is out of the camera's "
                    "view, and decide while the arm carries on; off: the picture is taken at home")
    decide_while_placing: bool = param(
        True, help="after a grasp held at home: take the next picture there (or on the way, capture_on_the_way), "
                   "decide while the arm places, and start the next plan from the place pose instead of going home "
                   "first (flgd train: always off)")


@dataclass(frozen=True)
class GripperConfig:
    driver: Literal["sim", "rg2_xmlrpc", "tool_digital_output"] = param("sim")
    open_width: float = param(0.085, unit="m", gt=0.0, le=0.110)
    closed_width: float = param(0.0, unit="m", ge=0.0)
    force: float = param(40.0, unit="N", gt=0.0, le=40.0)
    success_threshold: float = param(0.005, unit="m", gt=0.0,
                                     help="measured width above this after lifting = object held")
    xmlrpc_port: int = param(41414, gt=0, lt=65536)
    digital_output: int = param(0, ge=0, le=7, help="tool output that closes the gripper")
    timeout: float = param(5.0, unit="s", gt=0.0)
    release_gap: float = param(0.0, unit="m", ge=0.0, le=0.110,
                               help="a release goes on once the fingers opened this far (the object is let go): "
                                    "the arm moves on while they open the rest of the way (0 = wait until open); "
                                    "with preshape_margin the release opens only this far and waits")
    preshape_margin: float = param(0.0, unit="m", ge=0.0, le=0.03,
                                   help="a grasp opens only as wide as its fingers need to land free beside the "
                                        "object, with this much free space inside each pad, set while the arm "
                                        "travels to it; a release opens only a release gap (0 = open fully)")


@dataclass(frozen=True)
class SafetyConfig:
    """The box the TCP may never leave, and motion caps."""

    envelope_x: Range = param((-0.80, -0.20), unit="m")
    envelope_y: Range = param((-0.40, 0.40), unit="m")
    envelope_z: Range = param((0.0, 0.45), unit="m")
    min_table_clearance: float = param(0.004, unit="m", ge=0.0, help="lowest TCP height above the table")
    max_tilt: float = param(0.05, unit="rad", ge=0.0, le=math.pi / 2,
                            help="tool axis deviation from straight down")
    max_speed: float = param(0.5, unit="m/s", gt=0.0)
    max_acceleration: float = param(1.5, unit="m/s^2", gt=0.0)
    max_blend_radius: float = param(0.05, unit="m", ge=0.0, le=0.2,
                                    help="largest radius a move may blend into the next one with (0 = every move "
                                         "stops at its pose)")


@dataclass(frozen=True)
class RewardConfig:
    """Thresholds of the FLG rewards and masks (paper III-B, III-D); why these values: docs/configuration.md."""

    delta: float = param(0.01, unit="m", gt=0.0, help="height rise that counts a pixel in mu")
    tau1: int = param(500, unit="px", ge=0, help="mu above this rewards a move")
    tau2: int = param(200, unit="px", ge=0, help="eta above this rewards a move")
    min_height: float = param(0.01, unit="m", gt=0.0, help="object/background height threshold")
    min_object_area: float = param(100.0, unit="mm^2", ge=0.0, le=10000.0,
                                   help="a connected region above min_height smaller than this is depth noise, "
                                        "not an object (0 = every pixel counts)")
    clutter_dilation: int = param(11, unit="px", ge=1, help="kernel size of the clutter quantization map")
    move_mask_dilation: int = param(21, unit="px", ge=1, help="kernel size turning rho_g into rho_m")
    shift_height: float = param(0.01, unit="m", gt=0.0, help="a move point higher than this is a shift")
    move_reward: float = param(0.5, ge=0.0)


@dataclass(frozen=True)
class ExplorationConfig:
    epsilon_start: float = param(0.5, ge=0.0, le=1.0)
    epsilon_end: float = param(0.05, ge=0.0, le=1.0)
    epsilon_decay_steps: int = param(1000, ge=1)
    top_m: int = param(10, ge=1, help="anti-repeat: choose among the M best actions")
    failed_grasps_trigger: int = param(2, ge=1, help="consecutive failed grasps that force a move")
    curriculum_steps: int = param(0, ge=0, help="steps with fewer moves at the start (set by `flgd train "
                                                  "--curriculum`; 0 = none)")
    curriculum_move_probability: float = param(0.2, ge=0.0, le=1.0,
                                               help="chance a chosen move is kept during the curriculum")
    masks: bool = param(True, help="use the grasp/move masks (false = DPEN ablation)")
    grasp_only: bool = param(False, help="never choose a move (paper's Grasping-only mode, Table II)")
    grasp_in_view: bool = param(True, help="a grasp only at rotations whose open fingers come down inside the "
                                           "heightmap: a finger beyond its edge lands where the camera has no "
                                           "height (on an object pushed out of the workspace)")
    finger_clearance: float = param(0.0, unit="m", ge=0.0, le=0.1,
                                    help="a grasp only where nothing under either open finger stands higher than "
                                         "the grasped surface less this: the fingertips get this far down the "
                                         "object before they touch anything (0 = off; at most robot.grasp_depth)")
    side_taper: float = param(0.0, unit="m", ge=0.0, le=0.05,
                              help="a grasp only where both sides the open pads close on narrow by at most this "
                                   "over the centimetre above the fingertips (flgd.side_slope): a sloping side "
                                   "squeezes the object up out of the grip (0 = off)")
    last_resort_grasps: bool = param(False, help="where no grasp and no move is left in view "
                                                 "(exploration.grasp_in_view) while an object is still seen at the "
                                                 "border, grasp it without that limit (the descent is guarded: a "
                                                 "finger meeting a hidden part stops on it) instead of stopping; "
                                                 "moves stay limited")
    twin_grasps: bool = param(False, help="act on the mean of a grasp's two rotations (theta and theta + pi close "
                                          "the two-finger gripper the same way) instead of each alone")
    failure_memory: bool = param(True, help="remember, per scene, where a grasp failed and where a move changed "
                                            "nothing, and do not choose there again until the heightmap changes "
                                            "there (false = the paper's rules alone)")
    failure_radius: float = param(0.012, unit="m", gt=0.0, le=0.1,
                                  help="radius of the region a failed action suppresses")
    failure_rotations: int = param(1, ge=0, help="rotation steps either side of a failed action's that it "
                                                 "suppresses too")
    failure_retries: int = param(1, ge=0, le=10, help="failures at the same spot before it is suppressed, beyond "
                                                      "the first (1 = one more try there)")
    stuck_after: int = param(15, ge=0, unit="actions", help="actions without a successful grasp after which the "
                                                            "cell declares itself stuck (0 = never)")
    stuck_action: Literal["pause", "continue"] = param(
        "pause", help="a stuck cell that cannot re-lay its own scene: pause until `flgctl start`, or record it "
                      "and continue with a clean failure memory")


@dataclass(frozen=True)
class LearningConfig:
    network: Literal["fast", "densenet121", "rho-fcn", "rho-fcn-fast"] = param("fast")
    rotations: int = param(16, ge=1)
    gamma: float = param(0.5, ge=0.0, lt=1.0)
    learning_rate: float = param(1e-4, gt=0.0)
    weight_decay: float = param(1e-5, ge=0.0)
    batch_size: int = param(4, ge=1)
    updates_per_action: int = param(1, ge=0)
    target_update_every: int = param(50, ge=1, unit="updates")
    mirror_probability: float = param(0.0, ge=0.0, le=1.0,
                                      help="chance a replayed transition is trained as its mirror image")
    next_argmax_max_age: int = param(0, ge=0, unit="updates",
                                     help="reuse a next state's double-DQN argmax this long (0 = always recompute)")
    actor_argmax: bool = param(False, help="keep each next state's double-DQN argmax for as long as the state is "
                                           "replayed: the a' of the decision that acted on it (or, where none was "
                                           "recorded, the learner's first) is never recomputed, so a target costs "
                                           "one or two rotations of the target network (`flgd train`'s recipe)")
    grasp_twins: Literal["both", "one"] = param(
        "both", help="a replayed grasp trains its rotation and the theta+pi twin ('both'), or one of the two drawn "
                     "at random ('one': a grasp's update forwards one rotated image instead of two)")
    max_backlog: int = param(0, ge=0, unit="updates",
                             help="most scheduled updates the background learner may owe; more are dropped "
                                  "(0 = no limit)")
    init_trunk: str = param("", help="trunk file from `flgd pretrain` that a fresh network starts from (relative "
                                     "to the config file); empty = random initial weights")
    replay_capacity: int = param(20000, ge=1)
    min_replay: int = param(0, ge=0, unit="transitions",
                            help="no update is scheduled until the replay holds this many transitions (0 = learn "
                                 "from the first); a fine-tune's first updates otherwise fit a handful of "
                                 "transitions")
    priority_alpha: float = param(0.6, ge=0.0, le=1.0)
    priority_beta_start: float = param(0.4, ge=0.0, le=1.0)
    priority_beta_steps: int = param(5000, ge=1)
    priority_epsilon: float = param(0.01, gt=0.0)
    huber_delta: float = param(1.0, gt=0.0)
    anchor_weight: float = param(0.0, ge=0.0, unit="per squared weight",
                                 help="L2-SP: each update's loss adds this times the sum of squared differences "
                                      "between the trained weights and the acting champion's (0 = off)")
    batchnorm: Literal["batch", "frozen"] = param(
        "batch", help="'batch': BatchNorm normalises each update's batch and moves its running statistics "
                      "(training from scratch); 'frozen': updates use and keep the network's running statistics "
                      "(fine-tuning a trained policy, whose statistics a batch of 4 transitions would drift)")
    checkpoint_every: int = param(100, ge=1, unit="updates")
    sync_every: int = param(0, ge=0, unit="updates",
                            help="`flgd train --workers`: a worker gets the learner's weights with its next cycle "
                                 "once they are this many updates newer than its own (0 = after every action's "
                                 "updates, as in one process)")
    wait_for_updates: bool = param(False, help="each cycle waits until the learner has run the updates scheduled "
                                               "before it (gives a fast simulated cell the learner time a real cell's "
                                               "~9 s cycle gives; off on a real cell)")
    threads: int = param(0, ge=0, help="torch CPU threads; 0 = all cores")
    device: Literal["cpu", "cuda", "auto"] = param("auto")
    seed: int = param(0, ge=0)


@dataclass(frozen=True)
class FinetuneConfig:
    """The learner and exploration settings used instead of ``learning``'s when a trained policy is given.

    Why a section of its own: the settings that train a network from scratch (a high learning rate, several
    updates per action, BatchNorm moving with every batch) degrade a trained policy within a few hundred
    updates (BENCHMARKS.md, fine-tuning), so a daemon started from a policy must not inherit them.
    """

    learning_rate: float = param(1e-5, gt=0.0)
    updates_per_action: int = param(1, ge=0)
    batchnorm: Literal["batch", "frozen"] = param("frozen", help="see learning.batchnorm")
    min_replay: int = param(100, ge=0, unit="transitions",
                            help="warm-up: no update until the replay holds this many of this cell's transitions")
    max_epsilon: float = param(0.05, ge=0.0, le=1.0,
                               help="exploration continues from the policy's recorded training steps on the "
                                    "exploration schedule, never above this")
    anchor_weight: float = param(0.0, ge=0.0, unit="per squared weight", help="see learning.anchor_weight")
    actor_argmax: bool = param(False, help="see learning.actor_argmax; off for a fine-tune: behind the gate the "
                                           "acting weights lag the learner's by whole hand-overs")
    grasp_twins: Literal["both", "one"] = param("both", help="see learning.grasp_twins")
    prior_sample: str = param("", help="a prior sample file (`flgd prior-sample`: transitions of the cell the policy "
                                       "was trained in; relative to the config file); empty = none")
    prior_share: float = param(0.0, ge=0.0, lt=1.0, help="share of each update's batch drawn from prior_sample "
                                                          "instead of this cell's replay (0 = off)")


@dataclass(frozen=True)
class GateConfig:
    """The champion/challenger gate (flgd/gate/statistics.py): learned weights act only once shown better."""

    enabled: bool = param(True, help="false = the learner's weights act as soon as they are handed over, "
                                     "unvetted (unsafe: a fine-tune that makes the policy worse keeps acting)")
    handover_every: int = param(100, ge=1, unit="updates",
                                help="the learner hands its weights over every N updates, whatever its backlog")
    share: float = param(0.5, gt=0.0, lt=1.0, help="chance a greedy decision is made by the challenger")
    max_share: float = param(0.0, ge=0.0, lt=1.0,
                             help="above share: a challenger doing better gets up to this share of the greedy "
                                  "decisions (rising with P(better) from share at 0.5 to max_share at 0.9, after "
                                  "drop_min_attempts of its actions); 0 = the share stays gate.share")
    min_attempts: int = param(60, ge=1, unit="actions", help="challenger actions before it may be promoted")
    max_attempts: int = param(100, ge=1, unit="actions",
                              help="a challenger not shown better within this many actions is dropped")
    promote_confidence: float = param(0.98, gt=0.5, lt=1.0, help="P(challenger better) that promotes it")
    drop_min_attempts: int = param(40, ge=1, unit="actions", help="challenger actions before an early drop")
    drop_confidence: float = param(0.99, gt=0.5, lt=1.0, help="P(challenger worse) that drops it early")
    rollback_min_attempts: int = param(60, ge=1, unit="actions",
                                       help="a promoted champion's own actions before it may be rolled back")
    rollback_confidence: float = param(0.99, gt=0.5, lt=1.0,
                                       help="P(champion worse than its predecessor's record) that rolls it back")
    keep_champions: int = param(5, ge=1, help="earlier champions whose files are kept for rollbacks")


@dataclass(frozen=True)
class StorageConfig:
    """The disk the state directory may use and must leave free (flgd/disk_budget.py, docs/real-cell.md "Disk").

    Why: nothing may move whose record cannot be written, so the cell stops at a floor of free space, before
    the disk is full; and the store keeps to a budget, whatever the heightmap size or the replay capacity.
    """

    min_free_bytes: int = param(1 << 30, unit="bytes", ge=0,
                                help="below this much free space on the state directory's filesystem the daemon "
                                     "goes to FAULT before the next motion, and reset is refused until there is more")
    max_bytes: int = param(2 << 30, unit="bytes", ge=0,
                           help="the store (database and its write-ahead log) stays under this; the oldest replay "
                                "transitions are deleted first (0 = no byte budget, learning.replay_capacity only)")
    action_log_days: float = param(365.0, unit="days", ge=0.0,
                                   help="action-log rows older than this are deleted (0 = kept forever); flgctl stats "
                                        "covers what is kept")


@dataclass(frozen=True)
class CameraPoseErrorConfig:
    """How far the simulated camera's true pose is off ``camera.pose`` (a miscalibrated cell).

    The renderer uses the true pose; the frame, and so perception, carries the configured one, as on a real cell
    whose hand-eye calibration is off.  Zero = the camera is exactly where the config says.
    """

    position: Vec3 = param((0.0, 0.0, 0.0), unit="m", ge=-0.05, le=0.05,
                           help="true position minus configured position, in the robot base frame")
    rpy: Vec3 = param((0.0, 0.0, 0.0), unit="rad", ge=-0.1, le=0.1,
                      help="rotation of the true optical frame relative to the configured one, about the "
                           "camera's own axes (roll about its x, pitch about its y, yaw about its optical axis)")


@dataclass(frozen=True)
class SimConfig:
    """Used only by the simulated cell.

    The keys after ``time_step`` describe how this simulated cell differs from the one the shipped policy was
    trained in (its camera calibration, depth noise, colours, lighting, object physics): a second, different cell
    on which to measure what fine-tuning gains (``cell_config/sim-shifted.yaml``).  Their defaults are the
    training cell; ranges drawn per scene or per object apply when ``domain_randomization`` is on.
    """

    objects: int = param(10, ge=0, le=60)
    object_set: str = param("blocks", help="comma-separated items, each drawn equally often: 'blocks', a block shape, "
                                             "a named novel object, or a pybullet_data URDF glob")
    depth_noise: bool = param(True)
    domain_randomization: bool = param(True)
    seed: int = param(0, ge=0)
    packed_scenes: float = param(0.0, ge=0.0, le=1.0,
                                 help="share of new random scenes that are packed arrangements (rows of blocks "
                                      "laid flush, sim_cell.packed) instead of dropped clutter")
    scene: str = param("", help="scene file to load instead of random clutter")
    time_step: float = param(1.0 / 240.0, unit="s", gt=0.0, le=0.01)
    camera_pose_error: CameraPoseErrorConfig = param(default_factory=CameraPoseErrorConfig)
    depth_noise_std: float = param(0.001, unit="m", ge=0.0, le=0.02,
                                   help="std of the per-pixel depth noise at 0.5 m; it grows with the square of "
                                        "the distance (with depth_noise on)")
    depth_dropout: float = param(0.002, ge=0.0, le=0.5, help="share of pixels with no depth reading (with "
                                                             "depth_noise on)")
    depth_edge_holes: float = param(0.5, ge=0.0, le=1.0,
                                    help="chance that a pixel at a depth edge (a step > 8 mm to a neighbour) has "
                                         "no reading, as stereo matching fails there (with depth_noise on)")
    depth_outliers: float = param(0.003, ge=0.0, le=0.1,
                                  help="share of valid pixels with a gross depth error, uniform in +-3 cm (flying "
                                       "pixels, speckle) (with depth_noise on)")
    stereo_shadow: bool = param(True, help="no depth reading where a nearer surface hides a pixel from the D415's "
                                            "right imager, 55 mm beside the left (with depth_noise on)")
    table_shade: Range = param((0.25, 0.6), ge=0.0, le=1.0,
                               help="grey level range of the table top, drawn per scene")
    object_color_shift: Vec3 = param((0.0, 0.0, 0.0), ge=-1.0, le=1.0,
                                     help="added to the RGB colour of random and packed objects (0..1 per channel, then "
                                          "clipped); objects of a scene file keep theirs")
    light_ambient: Range = param((0.45, 0.75), ge=0.0, le=1.0, help="ambient light coefficient range, per scene")
    light_diffuse: Range = param((0.25, 0.5), ge=0.0, le=1.0, help="diffuse light coefficient range, per scene")
    object_friction: Range = param((0.4, 0.9), ge=0.0, le=2.0,
                                   help="lateral friction range of random objects, drawn per object")
    object_mass_scale: float = param(1.0, ge=0.2, le=5.0,
                                     help="multiplies the mass of every object the cell spawns")


@dataclass(frozen=True)
class CalibrationWatchConfig:
    """The watch on the camera's calibration (``flgd.calibration_watch``): the table plane every frame shows,
    against where ``camera.pose`` puts it.  A bumped camera makes grasps miss everywhere while nothing faults;
    past these limits the daemon says so (event, status, metric) and names ``flgd calibrate``."""

    enabled: bool = param(True, help="fit the table plane in every cycle's frame and report a drift")
    max_tilt_degrees: float = param(0.5, unit="deg", gt=0.0, le=10.0,
                                    help="table tilt in the heightmap beyond which the camera has moved")
    max_offset_mm: float = param(5.0, unit="mm", gt=0.0, le=100.0,
                                 help="table height (at the workspace centre) beyond which the camera has moved")
    window: int = param(5, ge=1, le=100, unit="frames", help="the estimate is the median of the newest frames")
    confirm_frames: int = param(3, ge=1, le=1000, unit="frames",
                                help="consecutive estimates beyond a limit before a drift is reported (and "
                                     "within 80 % of both before it is cleared)")


@dataclass(frozen=True)
class CellConfig:
    backend: str = param("sim", help="registered cell name: sim, ur5e, ...")
    name: str = param("", help="free-form cell name recorded in policies and logs")
    workspace: WorkspaceConfig = param(default_factory=WorkspaceConfig)
    camera: CameraConfig = param(default_factory=CameraConfig)
    robot: RobotConfig = param(default_factory=RobotConfig)
    gripper: GripperConfig = param(default_factory=GripperConfig)
    safety: SafetyConfig = param(default_factory=SafetyConfig)
    rewards: RewardConfig = param(default_factory=RewardConfig)
    exploration: ExplorationConfig = param(default_factory=ExplorationConfig)
    learning: LearningConfig = param(default_factory=LearningConfig)
    finetune: FinetuneConfig = param(default_factory=FinetuneConfig)
    gate: GateConfig = param(default_factory=GateConfig)
    storage: StorageConfig = param(default_factory=StorageConfig)
    sim: SimConfig = param(default_factory=SimConfig)
    calibration_watch: CalibrationWatchConfig = param(default_factory=CalibrationWatchConfig)
    policy: str = param("", help="policy file loaded at start (relative to the config file); "
                                   "empty = a fresh network")
    state_dir: str = param("/var/lib/flgd", help="replay store, logs and checkpoints")
    metrics: str = param("", help="HOST:PORT where `flgd run` serves Prometheus metrics (e.g. 127.0.0.1:9808); "
                                  "empty = off")
    source: str = param("<defaults>", help="file this config came from (set by the loader)")

