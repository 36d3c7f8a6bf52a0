"""Cell configuration: one YAML file describes one cell.

The file is loaded into frozen, typed dataclasses.  Every problem found is
reported with the file, the dotted key, the offending value and what was
expected, and unknown keys get a did-you-mean suggestion, because a typo in a
safety limit must never be silently ignored on a real robot.

Units are explicit and fixed: metres, radians, seconds, m/s, m/s^2.

The package, by responsibility: ``schema`` (the dataclasses), ``convert``
(YAML values to them, field by field), ``rules`` (constraints between keys),
``loader`` (the strict YAML loader, load and dump), ``learner_policy`` (which
learner settings apply) and ``messages`` (``ConfigError``).  It imports no
cell, safety or plan module: backend names come from the leaf
``flgd.backends``.
"""

from __future__ import annotations

from flgd.backends import BACKEND_GRIPPER_DRIVERS
from flgd.config.learner_policy import fine_tunes, learner_settings
from flgd.config.loader import (MAX_CONFIG_BYTES, MAX_CONFIG_VALUES, config_from_dict, config_to_dict, dump_config,
                                load_config, load_sim_config)
from flgd.config.messages import ConfigError
from flgd.config.rules import parse_emulator_address, parse_metrics_address
from flgd.config.schema import (CalibrationWatchConfig, CameraConfig, CameraPoseErrorConfig, CellConfig,
                                ExplorationConfig, FinetuneConfig, GateConfig, GripperConfig, IntrinsicsConfig,
                                LearningConfig, PoseConfig, Range, RewardConfig, RobotConfig, SafetyConfig,
                                SimConfig, StorageConfig, ToolPoseConfig, Vec3, WorkspaceConfig, param)

__all__ = [
    "ConfigError",
    "CellConfig",
    "fine_tunes",
    "learner_settings",
    "load_config",
    "config_from_dict",
    "config_to_dict",
    "dump_config",
    "load_sim_config",
    "parse_emulator_address",
    "parse_metrics_address",
    "MAX_CONFIG_BYTES",
    "MAX_CONFIG_VALUES",
    "BACKEND_GRIPPER_DRIVERS",
    "param",
    "Range",
    "Vec3",
    "WorkspaceConfig",
    "IntrinsicsConfig",
    "PoseConfig",
    "CameraConfig",
    "ToolPoseConfig",
    "RobotConfig",
    "GripperConfig",
    "SafetyConfig",
    "RewardConfig",
    "ExplorationConfig",
    "LearningConfig",
    "FinetuneConfig",
    "GateConfig",
    "StorageConfig",
    "CameraPoseErrorConfig",
    "SimConfig",
    "CalibrationWatchConfig",
]
