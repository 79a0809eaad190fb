"""Simulation and the L3E method: world, robot, LiDAR, environments (registered on import).

Importing the package registers the Gymnasium ids and nothing heavier: the simulation's modules load
when a name of theirs is first used (`l3e_env.Lidar`), so that `l3e --help` and short commands start
fast."""
from importlib import import_module
from typing import Any

from gymnasium.envs.registration import register, registry

# id -> (scene, the episode's step limit: 3x the route at full speed, as NavigationEnv sets it; a test
# keeps the two equal, so that Gymnasium's TimeLimit and the environment truncate on the same step)
ENV_IDS = {
    "l3e/Tunnel-v0": ("tunnel", 3240),
    "l3e/Field-v0": ("field", 2400),
    "l3e/Office-v0": ("office", 840),
    "l3e/Cave-v0": ("cave", 2643),
    "l3e/Mine-v0": ("mine", 4753),
    "l3e/Fork-v0": ("fork", 2400),
}

for _id, (_scene, _steps) in ENV_IDS.items():
    if _id not in registry:
        register(id=_id, entry_point="l3e_env.envs.navigation:NavigationEnv", kwargs={"scene": _scene},
                 max_episode_steps=_steps)

_LAZY = {
    "EnvConfig": "l3e_env.config", "LidarConfig": "l3e_env.config", "OdometryConfig": "l3e_env.config",
    "RobotConfig": "l3e_env.config", "Lidar": "l3e_env.sim.lidar", "Scan": "l3e_env.sim.lidar",
    "BeamPattern": "l3e_env.sim.lidar", "PATTERNS": "l3e_env.sim.lidar", "register_pattern": "l3e_env.sim.lidar",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'l3e_env' has no attribute '{name}'")


__all__ = ["EnvConfig", "LidarConfig", "OdometryConfig", "RobotConfig", "Lidar", "Scan", "BeamPattern", "PATTERNS",
           "register_pattern", "ENV_IDS"]
