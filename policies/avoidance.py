"""Keeping clear of what the LiDAR sees: a navigation stack's local obstacle avoidance under any policy.

A policy steers on the fused estimate, which may be a metre off to one side after a long walk; the
map's free corridor then lies a metre off the real one, and a robot that trusts it brushes the
buttresses and corners it cannot see in its estimate. Real robots keep clear of what their sensor
sees now, whatever their map says: `KeepClear` takes the policy's command and the current scan, and
where a return stands within `margin` of the base's outline it slows the walk towards it and slides
the robot sideways away from it, in proportion to how close it is. The ground is left out by height.
"""
from __future__ import annotations

import numpy as np

from l3e_env.config import RobotConfig


class KeepClear:
    """`__call__(action, points)`: the normalised twist (vx, vy, yaw rate) adjusted for the scan's
    points (N, 3, sensor frame). `margin` (m): the gap to the base box inside which a return pushes;
    returns lower than `ground_below` m under the sensor count as ground."""

    def __init__(self, robot: RobotConfig | None = None, margin: float = 0.6, ground_below: float = 0.55,
                 above: float = 0.6):
        if not margin > 0:
            raise ValueError(f"the margin is a positive distance, got {margin}")
        self.robot = robot or RobotConfig()
        self.margin, self.ground_below, self.above = float(margin), float(ground_below), float(above)
        self.half = np.asarray(self.robot.base_size[:2], dtype=np.float64) / 2
        self.offset = np.asarray(self.robot.lidar_offset[:2], dtype=np.float64)
        self.pushes = 0  # steps on which a return was inside the margin

    def __call__(self, action: np.ndarray, points: np.ndarray) -> np.ndarray:
        action = np.asarray(action, dtype=np.float32).copy()
        pts = np.asarray(points, dtype=np.float64)
        near = pts[(pts[:, 2] > -self.ground_below) & (pts[:, 2] < self.above)]
        if len(near) == 0:
            return action
        xy = near[:, :2] + self.offset  # the base's frame (the sensor sits over its centre)
        outside = np.maximum(np.abs(xy) - self.half, 0.0)
        gap = np.hypot(outside[:, 0], outside[:, 1])
        k = int(np.argmin(gap))
        if gap[k] >= self.margin:
            return action
        self.pushes += 1
        closeness = 1.0 - gap[k] / self.margin  # 0 at the margin, 1 in contact
        away = -xy[k] / max(float(np.linalg.norm(xy[k])), 1e-6)
        if away[0] < 0 and action[0] > 0:  # the return is ahead: slow the walk towards it
            action[0] *= float(1.0 - closeness * min(1.0, -away[0] * 1.5))
        action[1] = float(np.clip(action[1] + 2.0 * closeness * away[1], -1.0, 1.0))
        return action
