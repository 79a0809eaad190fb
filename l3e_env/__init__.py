"""Simulation and the L3E method: world, robot, LiDAR, environments.

Importing the package registers the Gymnasium ids (`l3e/Tunnel-v0`, ...) as soon as Gymnasium is
imported, before or after, and loads nothing heavier: the simulation's modules load when a name of
theirs is first used (`l3e_env.Lidar`), so that `l3e --help` and short commands start fast."""

import sys
from collections.abc import Sequence
from importlib import import_module
from importlib.abc import Loader, MetaPathFinder
from importlib.machinery import ModuleSpec, PathFinder
from types import ModuleType
from typing import Any

from l3e_env.core.threads import PACKAGE_THREAD_ENV, settle_process_threads

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
_REGISTRATION = "gymnasium.envs.registration"
settle_process_threads(PACKAGE_THREAD_ENV)  # OpenMP threads that sleep when idle: see core/threads.py


def _register(registration: ModuleType) -> None:
    for env_id, (scene, steps) in ENV_IDS.items():
        if env_id not in registration.registry:
            registration.register(
                id=env_id,
                entry_point="l3e_env.envs.navigation:NavigationEnv",
                kwargs={"scene": scene},
                max_episode_steps=steps,
            )


class _RegisterWithGymnasium(MetaPathFinder):
    """Registers the ids the moment Gymnasium's registry loads. Gymnasium has no lazy registration
    (1.x dropped the entry-point plugins), and importing it costs more than the rest of a short
    command's start-up, so the package waits for whoever imports Gymnasium (`gym.make` included)."""

    def find_spec(self, name: str, path: Sequence[str] | None, target: ModuleType | None = None) -> ModuleSpec | None:
        if name != _REGISTRATION:
            return None
        sys.meta_path.remove(self)
        spec = PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None:
            return spec
        spec.loader = _ThenRegister(spec.loader)
        return spec


class _ThenRegister(Loader):
    def __init__(self, loader: Loader):
        self.loader = loader

    def create_module(self, spec: ModuleSpec) -> ModuleType | None:
        return self.loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        self.loader.exec_module(module)
        _register(module)


if _REGISTRATION in sys.modules:
    _register(sys.modules[_REGISTRATION])
else:
    sys.meta_path.insert(0, _RegisterWithGymnasium())

_LAZY = {
    "EnvConfig": "l3e_env.config",
    "LidarConfig": "l3e_env.config",
    "OdometryConfig": "l3e_env.config",
    "RobotConfig": "l3e_env.config",
    "Lidar": "l3e_env.sim.lidar",
    "Scan": "l3e_env.sim.lidar",
    "BeamPattern": "l3e_env.sim.lidar",
    "PATTERNS": "l3e_env.sim.lidar",
    "register_pattern": "l3e_env.sim.lidar",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'l3e_env' has no attribute '{name}'")


__all__ = [
    "EnvConfig",
    "LidarConfig",
    "OdometryConfig",
    "RobotConfig",
    "Lidar",
    "Scan",
    "BeamPattern",
    "PATTERNS",
    "register_pattern",
    "ENV_IDS",
]
