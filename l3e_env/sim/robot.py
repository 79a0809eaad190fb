"""The legged-robot stand-in: a base box driven by a planar twist that walks on the terrain."""

from __future__ import annotations

import numpy as np

from l3e_env.config import RobotConfig
from l3e_env.core.transforms import planar_pose, yaw_of

from .world import World


def planar_motion(yaw: float, twist: np.ndarray, dt: float) -> tuple[float, float, float]:
    """World (dx, dy) and the new yaw after applying the body twist (vx, vy, yaw_rate) for dt,
    turning at the midpoint of the step."""
    mid = yaw + 0.5 * twist[2] * dt
    return (
        (np.cos(mid) * twist[0] - np.sin(mid) * twist[1]) * dt,
        (np.sin(mid) * twist[0] + np.cos(mid) * twist[1]) * dt,
        yaw + twist[2] * dt,
    )


SPAWN_HINT = (
    "; is the route's first waypoint on a floor? For a mesh given as a file, are --up-axis and --scale "
    "those of the file?"
)


class SpawnError(RuntimeError):
    """The robot cannot stand at the requested pose (inside geometry or no ground)."""


class Robot:
    """Kinematic stand-in: no leg dynamics, but ground following and wall contact are real.

    Each step integrates the twist, finds the terrain under the feet and refuses poses in
    which the base would penetrate the scene (sliding along a wall when one axis is free).
    """

    def __init__(self, world: World, config: RobotConfig | None = None):
        self.world = world
        self.config = config or world.robot_config
        self.T_w_b = np.eye(4)
        self.T_b_s = planar_pose(*self.config.lidar_offset, 0.0)
        self._z_ground = 0.0

    @property
    def T_w_s(self) -> np.ndarray:
        return self.T_w_b @ self.T_b_s

    def reset(self, x: float, y: float, yaw: float, z_ground: float = 0.0) -> np.ndarray:
        T = self.world.ground_pose(x, y, yaw, z_ground)
        if T is None:
            raise SpawnError(f"no ground under the robot at ({x:.2f}, {y:.2f}){SPAWN_HINT}")
        if self.world.in_collision(T):
            raise SpawnError(
                f"the robot at ({x:.2f}, {y:.2f}, yaw {yaw:.2f}) would be inside scene geometry{SPAWN_HINT}"
            )
        self.T_w_b = T
        self._z_ground = self._ground_height(T)
        return T

    def _ground_height(self, T: np.ndarray) -> float:
        """Terrain height under the base centre."""
        return float(T[2, 3] - self.config.standing_height / T[2, 2])

    def step(self, twist: np.ndarray) -> tuple[np.ndarray, bool]:
        """Apply (vx, vy, yaw_rate) in the body frame for one dt. Returns (T_w_b, blocked)."""
        twist = np.asarray(twist, dtype=np.float64).reshape(3)
        if not np.isfinite(twist).all():
            raise ValueError(f"twist must be finite, got {twist}")
        twist = np.clip(twist, -np.asarray(self.config.max_twist), self.config.max_twist)
        dt = self.config.dt
        x, y, yaw = self.T_w_b[0, 3], self.T_w_b[1, 3], yaw_of(self.T_w_b)
        dx, dy, new_yaw = planar_motion(yaw, twist, dt)
        candidates = [(dx, dy, new_yaw), (dx, 0.0, new_yaw), (0.0, dy, new_yaw), (0.0, 0.0, new_yaw), (0.0, 0.0, yaw)]
        for i, (cx, cy, cyaw) in enumerate(candidates):
            if i > 0 and (cx, cy, cyaw) == candidates[i - 1]:
                continue
            T = self.world.ground_pose(x + cx, y + cy, cyaw, self._z_ground)
            if T is not None and not self.world.in_collision(T):
                self.T_w_b = T
                self._z_ground = self._ground_height(T)
                return T, i > 0
        return self.T_w_b, True
