"""Cell configuration: one YAML file describes one cell.

The file is loaded into frozen, typed dataclasses.  Every problem found is
reported with the file, the dotted key, the offending value and what was
expected, and unknown keys get a did-you-mean suggestion, because a typo in a
safety limit must never be silently ignored on a real robot.

Units are explicit and fixed: metres, radians, seconds, m/s, m/s^2.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import reprlib
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from flgd.disk_budget import MIN_STORE_BYTES

__all__ = [
    "ConfigError",
    "CellConfig",
    "fine_tunes",
    "learner_settings",
    "load_config",
    "config_from_dict",
    "config_to_dict",
]


class ConfigError(ValueError):
    """A config file is unusable; ``problems`` lists every problem found."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = problems
        lines = "\n".join(f"  - {p}" for p in problems)
        super().__init__(f"invalid config {source}:\n{lines}")


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
    approach_speed: float = param(0.10, unit="m/s", gt=0.0, help="descents, pushes and shifts")
    descent_contact_force: float = param(
        20.0, unit="N", ge=0.0,
        help="a grasp descent stops where the fingers meet this much resistance and closes there (0 = no guard)")
    acceleration: float = param(0.8, unit="m/s^2", gt=0.0)
    tcp_offset: Vec3 = param((0.0, 0.0, 0.20), unit="m", help="flange to fingertip centre")


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
    prior_sample: str = param("", help="a prior sample file (`flgd prior-sample`: transitions of the cell the policy "
                                       "was trained in; relative to the config file); empty = none")
    prior_share: float = param(0.0, ge=0.0, lt=1.0, help="share of each update's batch drawn from prior_sample "
                                                          "instead of this cell's replay (0 = off)")


@dataclass(frozen=True)
class GateConfig:
    """The champion/challenger gate (flgd/learning/gate.py): learned weights act only once shown better."""

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
    depth_outliers: float = param(0.0, ge=0.0, le=0.1,
                                  help="share of valid pixels with a gross depth error, uniform in +-3 cm (flying "
                                       "pixels, speckle) (with depth_noise on)")
    stereo_shadow: bool = param(False, help="no depth reading where a nearer surface hides a pixel from the D415's "
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


def fine_tunes(cfg: CellConfig) -> tuple[bool, str]:
    """(whether the daemon fine-tunes, why): it does when a policy is given, and trains from scratch when not."""
    if cfg.policy:
        return True, (f"policy {cfg.policy} is a trained policy: the learner fine-tunes it with the finetune "
                      "settings, and exploration continues from the training steps the policy records")
    return False, ("no policy is given: a fresh network learns from scratch with the learning settings "
                   "(exploration from step 0)")


def learner_settings(cfg: CellConfig, fine_tune: bool) -> CellConfig:
    """``cfg`` with the finetune section's learner settings in ``learning`` when ``fine_tune``, else unchanged."""
    if not fine_tune:
        return cfg
    ft = cfg.finetune
    return dataclasses.replace(cfg, learning=dataclasses.replace(
        cfg.learning, learning_rate=ft.learning_rate, updates_per_action=ft.updates_per_action,
        batchnorm=ft.batchnorm, min_replay=ft.min_replay, anchor_weight=ft.anchor_weight))


# --------------------------------------------------------------------------- loading

# A cell config is a few KiB; the caps keep a wrong or hostile file from hanging check-config or the daemon
# (PyYAML parses ~200 KiB/s, and a few lines of YAML aliases can stand for billions of values).
MAX_CONFIG_BYTES = 256 * 1024
MAX_CONFIG_VALUES = 20000  # scalars, lists and mappings after expanding aliases; sim.yaml has ~250
_MAX_QUOTE = 80  # characters of a value quoted in an error message

_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = _REPR.maxlong = 60
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 6
_REPR.maxlevel = 3


def _quote(value: Any) -> str:
    """A short repr for error messages: a value of megabytes, or a list of millions, is summarised."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 200:
        try:
            return f"an integer of {len(str(abs(value)))} digits"
        except ValueError:  # beyond what str() converts
            return f"an integer of about {int(value.bit_length() * math.log10(2)) + 1} digits"
    try:
        text = _REPR.repr(value)
    except Exception:  # a repr that fails must not hide the actual problem
        text = f"<{type(value).__name__}>"
    return text if len(text) <= _MAX_QUOTE else text[:_MAX_QUOTE - 3] + "..."


def _key_name(raw_key: Any) -> str:
    name = str(raw_key) if not isinstance(raw_key, int) or raw_key.bit_length() <= 200 else _quote(raw_key)
    return name if len(name) <= _MAX_QUOTE else name[:_MAX_QUOTE - 3] + "..."


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        return f"a list of {len(args)} {_type_name(args[0])}s"
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return {float: "number", int: "integer", bool: "boolean (true/false)", str: "string"}.get(tp, str(tp))


def _describe_limits(meta: dict) -> str:
    parts = []
    for key, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
        if meta.get(key) is not None:
            parts.append(f"{op} {meta[key]}")
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    return (" " + " and ".join(parts) + unit) if parts else unit


def _convert(value: Any, tp: Any, key: str, meta: dict, problems: list[str], source: str) -> Any:
    """Convert one YAML value to ``tp``; on failure record a problem and return MISSING."""
    origin = typing.get_origin(tp)
    expected = _type_name(tp) + _describe_limits(meta)

    def bad(why: str = "") -> Any:
        extra = f" ({why})" if why else ""
        problems.append(f"{key}: got {_quote(value)}, expected {expected}{extra}")
        return dataclasses.MISSING

    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            return bad()
        return _build(tp, value, key, problems, source)
    if origin is Literal:
        return value if value in typing.get_args(tp) else bad()
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            return bad()
        out = []
        for i, (v, a) in enumerate(zip(value, args)):
            c = _convert(v, a, f"{key}[{i}]", meta, problems, source)
            if c is dataclasses.MISSING:
                return dataclasses.MISSING
            out.append(c)
        return tuple(out)
    if tp is bool:
        return value if isinstance(value, bool) else bad()
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            return bad()
        if not -2**63 <= value < 2**63:
            return bad("does not fit a 64-bit integer")
        return _check_range(value, key, meta, expected, problems)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return bad()
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an integer with hundreds of digits does not fit a float
            finite = False
        if not finite:
            return bad("not a finite number")
        return _check_range(float(value), key, meta, expected, problems)
    if tp is str:
        if isinstance(value, str):
            return value if "\x00" not in value else bad("a NUL character (\\x00) cannot be part of a path or name")
        # A camera serial number or a host written without quotes is read by YAML as a number or a date.
        return bad("quote the value to make it a string" if isinstance(value, (int, float)) and
                   not isinstance(value, bool) else "")
    raise TypeError(f"unsupported config field type {tp!r} at {key}")


def _check_range(value: float, key: str, meta: dict, expected: str, problems: list[str]) -> Any:
    checks = (("gt", lambda v, b: v > b), ("ge", lambda v, b: v >= b),
              ("lt", lambda v, b: v < b), ("le", lambda v, b: v <= b))
    for name, ok in checks:
        bound = meta.get(name)
        if bound is not None and not ok(value, bound):
            problems.append(f"{key}: got {_quote(value)}, expected {expected}")
            return dataclasses.MISSING
    return value


def _build(cls: type, data: dict, prefix: str, problems: list[str], source: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for raw_key, value in data.items():
        key = f"{prefix}.{_key_name(raw_key)}" if prefix else _key_name(raw_key)
        if raw_key not in fields or raw_key == "source":
            close = difflib.get_close_matches(_key_name(raw_key), [n for n in fields if n != "source"], n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            valid = ", ".join(n for n in fields if n != "source")
            problems.append(f"{key}: unknown key{hint} (valid keys here: {valid})")
            continue
        f = fields[raw_key]
        converted = _convert(value, hints[raw_key], key, dict(f.metadata), problems, source)
        if converted is not dataclasses.MISSING:
            kwargs[raw_key] = converted
    try:
        return cls(**kwargs)
    except TypeError as exc:  # a field without default that was not given
        problems.append(f"{prefix or '<top>'}: {exc}")
        return dataclasses.MISSING


def _check_relations(cfg: CellConfig, problems: list[str]) -> None:
    """Constraints between keys, which single-field limits cannot express."""
    _check_backend(cfg, problems)
    if 0.0 < cfg.gate.max_share < cfg.gate.share:
        problems.append(f"gate.max_share: got {cfg.gate.max_share!r}, expected 0 (off) or >= gate.share "
                        f"({cfg.gate.share!r})")
    for key in ("min_attempts", "drop_min_attempts"):
        if getattr(cfg.gate, key) > cfg.gate.max_attempts:
            problems.append(f"gate.{key}: got {getattr(cfg.gate, key)}, expected <= gate.max_attempts "
                            f"({cfg.gate.max_attempts})")
    _check_device(cfg, problems)
    if 0 < cfg.storage.max_bytes < MIN_STORE_BYTES:
        problems.append(f"storage.max_bytes: got {cfg.storage.max_bytes}, expected 0 (no byte budget) or >= "
                        f"{MIN_STORE_BYTES} bytes (64 MiB: a useful replay beside a month's action log)")
    if cfg.finetune.prior_share > 0.0 and not cfg.finetune.prior_sample:
        problems.append(f"finetune.prior_share: got {cfg.finetune.prior_share!r} with no finetune.prior_sample, "
                        "expected a prior sample file (`flgd prior-sample`) or prior_share 0")
    ws, sf = cfg.workspace, cfg.safety
    for name in ("x", "y", "z"):
        lo, hi = getattr(ws, name)
        if not lo < hi:
            problems.append(f"workspace.{name}: got {[lo, hi]!r}, expected min < max")
        elo, ehi = getattr(sf, f"envelope_{name}")
        if not elo < ehi:
            problems.append(f"safety.envelope_{name}: got {[elo, ehi]!r}, expected min < max")
    if any(p.startswith(("workspace.", "safety.")) for p in problems):
        return  # the checks below compare these ranges
    for name in ("x", "y"):
        span = getattr(ws, name)[1] - getattr(ws, name)[0]
        cells = span / ws.resolution
        if abs(cells - round(cells)) > 1e-6 * max(1.0, cells):
            problems.append(f"workspace.resolution: got {ws.resolution!r}, expected a value that divides "
                            f"the workspace {name} span {span:.4f} m into whole pixels")
    rows, cols = ws.shape
    if min(rows, cols) < 32 or max(rows, cols) > 2048:
        problems.append(f"workspace: heightmap would be {rows}x{cols} px, expected 32..2048 px per side")
    for name in ("x", "y"):
        lo, hi = getattr(ws, name)
        elo, ehi = getattr(sf, f"envelope_{name}")
        if lo < elo or hi > ehi:
            problems.append(f"workspace.{name}: {[lo, hi]!r} is not inside safety.envelope_{name} "
                            f"{[elo, ehi]!r}; the whole workspace must be reachable safely")
    if ws.z[0] < sf.envelope_z[0] - 1e-9:
        problems.append(f"safety.envelope_z: lower bound {sf.envelope_z[0]!r} is below the table "
                        f"(workspace.z[0] = {ws.z[0]!r}); expected >= the table height")
    if ws.z[1] > sf.envelope_z[1] + 1e-9:
        problems.append(f"workspace.z: {list(ws.z)!r} is not inside safety.envelope_z {list(sf.envelope_z)!r}; "
                        f"expected the top of the region <= {sf.envelope_z[1]!r}, the whole workspace must be "
                        "reachable safely")
    # Home and place are checked as the safety envelope checks every pose of a plan (flgd/safety.py), so
    # a config that passes here cannot have its first homing refused.  Their tilt is 0 by construction:
    # a tool pose has only a yaw (a roll or pitch key is refused as unknown), so max_tilt always holds.
    floor = ws.table_z + sf.min_table_clearance
    for pose_key in ("home", "place"):
        pose = getattr(cfg.robot, pose_key)
        for axis, v in zip("xyz", pose.position):
            elo, ehi = getattr(sf, f"envelope_{axis}")
            if not elo <= v <= ehi:
                problems.append(f"robot.{pose_key}.position: {axis} = {v!r} is outside "
                                f"safety.envelope_{axis} {[elo, ehi]!r}")
        if pose.position[2] < floor - 1e-9:
            problems.append(f"robot.{pose_key}.position: z = {pose.position[2]!r} is below the table clearance "
                            f"floor {floor:.4f} m (workspace.z[0] {ws.table_z!r} + safety.min_table_clearance "
                            f"{sf.min_table_clearance!r}); expected z >= {floor:.4f}")
    hx, hy = cfg.robot.home.position[0], cfg.robot.home.position[1]
    if ws.x[0] <= hx <= ws.x[1] and ws.y[0] <= hy <= ws.y[1]:
        problems.append(f"robot.home.position: (x, y) = ({hx!r}, {hy!r}) is over the workspace (x {list(ws.x)!r}, "
                        f"y {list(ws.y)!r}); every picture is taken with the arm at home, so the arm would be in "
                        "every heightmap. Expected a home beside the workspace, out of the camera's view")
    rb = cfg.robot
    for key in ("speed", "approach_speed"):
        if getattr(rb, key) > sf.max_speed:
            problems.append(f"robot.{key}: got {getattr(rb, key)!r} m/s, expected <= safety.max_speed "
                            f"({sf.max_speed!r} m/s)")
    if rb.acceleration > sf.max_acceleration:
        problems.append(f"robot.acceleration: got {rb.acceleration!r} m/s^2, expected <= "
                        f"safety.max_acceleration ({sf.max_acceleration!r} m/s^2)")
    if ws.z[0] + rb.lift_height > sf.envelope_z[1]:
        problems.append(f"robot.lift_height: table + {rb.lift_height!r} m is above safety.envelope_z "
                        f"upper bound {sf.envelope_z[1]!r}")
    gr = cfg.gripper
    if gr.closed_width >= gr.open_width:
        problems.append(f"gripper.closed_width: got {gr.closed_width!r}, expected < gripper.open_width "
                        f"({gr.open_width!r})")
    if not gr.closed_width < gr.success_threshold < gr.open_width:
        problems.append(f"gripper.success_threshold: got {gr.success_threshold!r}, expected between "
                        f"closed_width and open_width")
    ex = cfg.exploration
    if ex.epsilon_end > ex.epsilon_start:
        problems.append(f"exploration.epsilon_end: got {ex.epsilon_end!r}, expected <= epsilon_start "
                        f"({ex.epsilon_start!r})")
    if cfg.rewards.shift_height < cfg.rewards.min_height:
        problems.append(f"rewards.shift_height: got {cfg.rewards.shift_height!r}, expected >= "
                        f"rewards.min_height ({cfg.rewards.min_height!r})")
    intr = cfg.camera.intrinsics
    if not (0 <= intr.cx < intr.width and 0 <= intr.cy < intr.height):
        problems.append(f"camera.intrinsics: principal point ({intr.cx}, {intr.cy}) lies outside the "
                        f"{intr.width}x{intr.height} image")
    for key in ("table_shade", "light_ambient", "light_diffuse", "object_friction"):
        lo, hi = getattr(cfg.sim, key)
        if lo > hi:
            problems.append(f"sim.{key}: got {[lo, hi]!r}, expected min <= max")
    if not 0 < cfg.camera.depth_range[0] < cfg.camera.depth_range[1]:
        problems.append(f"camera.depth_range: got {list(cfg.camera.depth_range)!r}, expected 0 < min < max")
    if not cfg.state_dir:
        problems.append("state_dir: got '', expected a directory path")
    if cfg.metrics:
        try:
            parse_metrics_address(cfg.metrics)
        except ValueError as exc:
            problems.append(f"metrics: {exc}")


def parse_metrics_address(text: str) -> tuple[str, int]:
    """(host, port) of ``HOST:PORT`` (``[::1]:PORT`` for IPv6), or of a bare ``PORT`` on the loopback
    (the page needs no login: reaching it from elsewhere is something to ask for); ValueError saying what
    was expected.

    Port 0 asks the system for a free port (the daemon logs the one it got).
    """
    expected = "expected HOST:PORT such as 127.0.0.1:9808, a PORT alone for the loopback, or '' for no metrics"
    if text.isdigit():
        if int(text) > 65535:
            raise ValueError(f"got {_quote(text)}: port is not a number 0..65535; {expected}")
        return "127.0.0.1", int(text)
    host, sep, port_text = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or any(c.isspace() for c in host) or (":" in host and not text.startswith("[")):
        raise ValueError(f"got {_quote(text)}, {expected}")
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ValueError(f"got {_quote(text)}: port {_quote(port_text)} is not a number 0..65535; {expected}")
    return host, int(port_text)


# Gripper drivers each cell can drive.  A backend not listed here takes any driver: the simulated cell
# ignores gripper.driver (it simulates the RG2 itself), which also lets a real-cell config be swapped to
# the simulator with `flgctl backend sim`.
BACKEND_GRIPPER_DRIVERS: dict[str, tuple[str, ...]] = {
    "ur5e": ("rg2_xmlrpc", "tool_digital_output"),
}


def _check_backend(cfg: CellConfig, problems: list[str]) -> None:
    """The backend must be registered and the gripper driver one it can drive (no hardware library imported:
    the registry maps names to "module:attribute" strings)."""
    from flgd.cell import available_cells  # here, not at the top: flgd.cell imports this module

    names = available_cells()
    if cfg.backend not in names:
        close = difflib.get_close_matches(cfg.backend, names, n=1)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        problems.append(f"backend: got {cfg.backend!r}, expected one of {', '.join(repr(n) for n in names)}{hint}")
        return
    drivers = BACKEND_GRIPPER_DRIVERS.get(cfg.backend)
    if drivers is not None and cfg.gripper.driver not in drivers:
        problems.append(f"gripper.driver: got {cfg.gripper.driver!r}, expected one of "
                        f"{', '.join(repr(d) for d in drivers)} for backend {cfg.backend!r}")


def _check_device(cfg: CellConfig, problems: list[str]) -> None:
    """``learning.device: cuda`` needs a CUDA device on this machine; found here, it is a config error
    before anything starts, not a traceback from the learner.  torch is imported only in that case."""
    if cfg.learning.device != "cuda":
        return
    try:
        import torch
        available = bool(torch.cuda.is_available())
    except Exception as exc:  # a broken torch install: say so here rather than later
        problems.append(f"learning.device: got 'cuda', but torch cannot be asked for CUDA devices ({exc}); "
                        "expected 'cpu' or 'auto'")
        return
    if not available:
        problems.append("learning.device: got 'cuda', but torch finds no CUDA device on this machine (CPU-only "
                        "torch build, or no usable NVIDIA driver); expected 'cpu' or 'auto' (see docs/real-cell.md: "
                        "A GPU on the cell PC)")


_MERGE_TAG = "tag:yaml.org,2002:merge"


def _check_expansion(root: yaml.Node, limit: int) -> None:
    """Refuse a document that stands for more than ``limit`` values once its aliases are expanded, or whose
    aliases refer to themselves, before anything is built from it (counted per distinct node, so the check
    itself stays as small as the file)."""
    sizes: dict[int, int] = {}
    open_nodes: set[int] = set()

    def size(node: yaml.Node) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in open_nodes:
            raise yaml.constructor.ConstructorError(
                None, None, "an alias refers to the node that contains it, expected a finite config",
                node.start_mark)
        open_nodes.add(key)
        total = 1
        if isinstance(node, yaml.SequenceNode):
            children = node.value
        elif isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        else:
            children = []
        for child in children:
            total += size(child)
            if total > limit:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the document stands for more than {limit} values once its aliases (*name) are "
                                "expanded, expected a cell config (a few hundred values)", node.start_mark)
        open_nodes.discard(key)
        sizes[key] = total
        return total

    size(root)


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys (with plain YAML the last one silently wins), alias bombs and
    integers too long to read; merge keys (``<<: *defaults``) work, their keys overridden by explicit ones."""

    def construct_document(self, node):
        _check_expansion(node, MAX_CONFIG_VALUES)
        return super().construct_document(node)

    def construct_yaml_int(self, node):
        try:
            return super().construct_yaml_int(node)
        except ValueError:  # more digits than Python converts (sys.get_int_max_str_digits)
            raise yaml.constructor.ConstructorError(
                None, None, f"an integer of {len(str(node.value))} characters is too long, expected a number of "
                            f"at most {sys.get_int_max_str_digits()} digits", node.start_mark) from None

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:
                continue  # merged keys may be overridden; only explicit keys must be unique
            key = self.construct_object(key_node, deep=deep)
            try:
                hash(key)
            except TypeError:  # "? [a, b]" or "? {a: 1}": a list or mapping as a key is never a config key
                raise yaml.constructor.ConstructorError(
                    None, None, f"a {type(key).__name__} cannot be a key, expected a plain name",
                    key_node.start_mark) from None
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {_quote(key)} (first at line {seen[key] + 1})", key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_constructor("tag:yaml.org,2002:int", _StrictLoader.construct_yaml_int)


# YAML 1.1 (PyYAML) reads ``5e-4`` as a string; engineers write learning rates that way, so
# exponent floats without a dot are numbers here too, as in YAML 1.2.
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def config_from_dict(data: Any, source: str = "<dict>") -> CellConfig:
    """Build and validate a config from parsed YAML; raises ConfigError listing every problem."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(source, [f"<top>: got {type(data).__name__}, expected a mapping of sections"])
    problems: list[str] = []
    cfg = _build(CellConfig, data, "", problems, source)
    if cfg is dataclasses.MISSING or problems:
        raise ConfigError(source, problems or ["could not build the config"])
    _check_relations(cfg, problems)
    if problems:
        raise ConfigError(source, problems)
    return dataclasses.replace(cfg, source=source)


def load_config(path: str | os.PathLike) -> CellConfig:
    """Read, parse and validate a YAML config file."""
    p = Path(path)
    source = str(p)
    text = _read_config_text(p)
    try:
        data = yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(source, [f"invalid YAML{where}: {problem}"]) from None
    except RecursionError:  # PyYAML parses recursively: thousands of nested brackets exhaust the stack
        raise ConfigError(source, ["invalid YAML: nested too deeply, expected a mapping of sections"]) from None
    if data is None:  # not defaults: an empty file would run the cell against /var/lib/flgd
        raise ConfigError(source, ["the file is empty (or only comments), expected a mapping of sections such as "
                                   "backend, state_dir, workspace (see cell_config/sim.yaml)"])
    cfg = config_from_dict(data, source)
    # A relative state directory or policy file is relative to the config file, not to the cwd.
    if not os.path.isabs(cfg.state_dir):
        cfg = dataclasses.replace(cfg, state_dir=str((p.parent / cfg.state_dir).resolve()))
    if cfg.policy and not os.path.isabs(cfg.policy):
        cfg = dataclasses.replace(cfg, policy=str((p.parent / cfg.policy).resolve()))
    if cfg.finetune.prior_sample and not os.path.isabs(cfg.finetune.prior_sample):
        cfg = dataclasses.replace(cfg, finetune=dataclasses.replace(
            cfg.finetune, prior_sample=str((p.parent / cfg.finetune.prior_sample).resolve())))
    if cfg.learning.init_trunk and not os.path.isabs(cfg.learning.init_trunk):
        cfg = dataclasses.replace(cfg, learning=dataclasses.replace(
            cfg.learning, init_trunk=str((p.parent / cfg.learning.init_trunk).resolve())))
    return cfg


def _read_config_text(p: Path) -> str:
    """The file's text, refusing (ConfigError) a directory, a file over MAX_CONFIG_BYTES or one not UTF-8.

    At most the cap is ever read, so a device or a file that grows cannot hold the loader.
    """
    source = str(p)
    cap_text = f"at most {MAX_CONFIG_BYTES // 1024} KiB (a cell config is a few KiB)"
    try:
        size = p.stat().st_size if p.is_file() else 0
        if size > MAX_CONFIG_BYTES:
            raise ConfigError(source, [f"is {size / 1024:.0f} KiB, expected a YAML file of {cap_text}"])
        with open(p, "rb") as f:
            data = f.read(MAX_CONFIG_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(source, ["file not found"]) from None
    except IsADirectoryError:
        raise ConfigError(source, ["is a directory, expected a YAML file"]) from None
    except OSError as exc:
        raise ConfigError(source, [f"cannot read: {exc.strerror or exc}"]) from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(source, [f"holds more than {MAX_CONFIG_BYTES // 1024} KiB, expected a YAML file of "
                                   f"{cap_text}"])
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(source, [f"cannot read: not UTF-8 text ({exc.reason} at byte {exc.start})"]) from None


def load_sim_config(path: str | os.PathLike, why: str) -> CellConfig:
    """``load_config`` for commands that only run in sim_cell: any other backend is a ``ConfigError`` saying
    ``why``."""
    cfg = load_config(path)
    if cfg.backend != "sim":
        raise ConfigError(str(path), [f"backend: got {cfg.backend!r}, expected 'sim' ({why})"])
    return cfg


def config_to_dict(cfg: Any) -> Any:
    """The effective config as plain YAML-able data (tuples become lists)."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)
                if f.name != "source"}
    if isinstance(cfg, tuple):
        return [config_to_dict(v) for v in cfg]
    return cfg


def dump_config(cfg: CellConfig) -> str:
    return yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=None)

