"""Typed configuration: one dataclass per component (`sections`), dicts and YAML in and out (`serialize`)."""

from .sections import (
    ATTITUDE_MODES,
    DATASET_PRESETS,
    DESKEW_SOURCES,
    FUSION_BACKENDS,
    FUSION_MODES,
    GROUND_MODES,
    LABELLERS,
    EnvConfig,
    FusionSettings,
    LidarConfig,
    OdometryConfig,
    RobotConfig,
)
from .serialize import dump_yaml, from_dict, load_yaml, plain, settings_changed, to_dict, with_defaults

__all__ = [
    "ATTITUDE_MODES",
    "GROUND_MODES",
    "DESKEW_SOURCES",
    "DATASET_PRESETS",
    "FUSION_BACKENDS",
    "LABELLERS",
    "FUSION_MODES",
    "EnvConfig",
    "FusionSettings",
    "LidarConfig",
    "OdometryConfig",
    "RobotConfig",
    "dump_yaml",
    "from_dict",
    "load_yaml",
    "plain",
    "settings_changed",
    "to_dict",
    "with_defaults",
]
