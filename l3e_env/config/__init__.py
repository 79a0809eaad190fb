"""Typed configuration: one dataclass per component (`sections`), dicts and YAML in and out (`serialize`)."""

from .sections import (
    ATTITUDE_MODES,
    DESKEW_SOURCES,
    FUSION_BACKENDS,
    FUSION_MODES,
    EnvConfig,
    FusionSettings,
    LidarConfig,
    OdometryConfig,
    RobotConfig,
)
from .serialize import dump_yaml, from_dict, load_yaml, plain, settings_changed, to_dict, with_defaults

__all__ = [
    "ATTITUDE_MODES",
    "DESKEW_SOURCES",
    "FUSION_BACKENDS",
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
