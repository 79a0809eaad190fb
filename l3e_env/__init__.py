"""Simulation and the L3E method: world, robot, LiDAR, environments (registered on import)."""
from gymnasium.envs.registration import register, registry

from l3e_env.config import EnvConfig, LidarConfig, OdometryConfig, RobotConfig
from l3e_env.sim.lidar import PATTERNS, BeamPattern, Lidar, Scan, register_pattern

ENV_IDS = {
    "l3e/Tunnel-v0": "tunnel",
    "l3e/Field-v0": "field",
    "l3e/Office-v0": "office",
    "l3e/Cave-v0": "cave",
    "l3e/Mine-v0": "mine",
    "l3e/Fork-v0": "fork",
}

for _id, _scene in ENV_IDS.items():
    if _id not in registry:
        register(id=_id, entry_point="l3e_env.envs.navigation:NavigationEnv", kwargs={"scene": _scene})

__all__ = ["EnvConfig", "LidarConfig", "OdometryConfig", "RobotConfig", "Lidar", "Scan", "BeamPattern", "PATTERNS",
           "register_pattern", "ENV_IDS"]
