"""Typed configuration: one dataclass per component (`sections`), dicts and YAML in and out (`serialize`)."""
from .sections import (ATTITUDE_MODES, NOISE_STREAMS, EnvConfig, FusionOptions, LidarConfig,
                       LoopFusionConfig, OdometryConfig, RobotConfig)
from .serialize import dump_yaml, from_dict, load_yaml, plain, settings_changed, to_dict

__all__ = ["ATTITUDE_MODES", "NOISE_STREAMS", "EnvConfig", "FusionOptions", "LidarConfig", "LoopFusionConfig",
           "OdometryConfig", "RobotConfig", "dump_yaml", "from_dict", "load_yaml", "plain", "settings_changed",
           "to_dict"]
