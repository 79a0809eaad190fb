"""Local obstacle avoidance from the live scan, under a policy that steers on its estimate.

A robot that follows a plan on its fused estimate walks into walls where the estimate is off: at a
turn taken a few metres early it faces the block it should have walked round. Navigation stacks
keep a local layer that looks at the current scan, which shows the obstacles where they are,
whatever the estimate believes. This is that layer, kept small: the returns at the base's height
are the obstacles; a heading is free where a corridor as wide as the base (and a margin) is clear
for `look` metres; the heading the policy wants is kept where free, else the free heading that
turns least from it and from the robot's own heading together is taken. Hand-written: the
navigation libraries on the registry (ROS's local planners, nav2) need a ROS install.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from l3e_env.config import RobotConfig


@dataclass(frozen=True)
class FreeHeadings:
    """Free headings around the base from one scan's returns."""

    half_width: float = 0.4  # m: the base's half width (0.25) and a margin
    front: float = 0.45  # m: the base's half length, from its centre to its nose
    look: float = 1.5  # m clear ahead of the nose for a heading to count as free
    resolution: float = np.radians(10.0)  # candidate headings this far apart

    def __post_init__(self):
        if self.half_width <= 0 or self.front < 0 or self.look <= 0 or not 0 < self.resolution <= np.pi / 2:
            raise ValueError(
                f"FreeHeadings needs half_width > 0, front >= 0, look > 0 and a resolution in (0, pi/2], got {self}"
            )

    @staticmethod
    def obstacles(
        points_s: np.ndarray,
        T_b_s: np.ndarray,
        robot: RobotConfig | None = None,
        above_ground: float = 0.2,
        above_base: float = 0.3,
    ) -> np.ndarray:
        """The scan's returns (sensor frame, (N, 3)) that the base would hit, as body-frame (x, y):
        those from `above_ground` m over the floor under the feet to `above_base` m over the base's top."""
        robot = robot or RobotConfig()
        points = np.asarray(points_s, dtype=np.float64)[:, :3] @ T_b_s[:3, :3].T + T_b_s[:3, 3]
        floor = -robot.standing_height
        top = 0.5 * robot.base_size[2]
        keep = (points[:, 2] > floor + above_ground) & (points[:, 2] < top + above_base)
        return points[keep, :2]

    def free_distance(self, obstacles: np.ndarray, headings: np.ndarray) -> np.ndarray:
        """Metres clear ahead of the nose along each body-frame heading (rad), inf where nothing is."""
        headings = np.atleast_1d(np.asarray(headings, dtype=np.float64))
        if len(obstacles) == 0:
            return np.full(len(headings), np.inf)
        c, s = np.cos(headings)[:, None], np.sin(headings)[:, None]
        along = c * obstacles[None, :, 0] + s * obstacles[None, :, 1]
        across = -s * obstacles[None, :, 0] + c * obstacles[None, :, 1]
        ahead = np.where((np.abs(across) < self.half_width) & (along > 0), along - self.front, np.inf)
        return np.maximum(ahead.min(axis=1), 0.0)

    def steer(self, obstacles: np.ndarray, desired: float, look: float | None = None) -> float:
        """The heading to walk (body frame, rad): `desired` where it is clear for `look` m (default
        self.look); else, of the clear headings, the one that turns least from `desired` and from the
        robot's own heading together (as a vector field histogram weighs its target and its turn), so
        that a robot meeting a block it should have passed goes on along it rather than back;
        `desired` where none is clear (the policy's recovery deals with that)."""
        look = self.look if look is None else look
        desired = float(np.angle(np.exp(1j * desired)))
        if self.free_distance(obstacles, np.array([desired]))[0] >= look:  # the usual case, one heading
            return desired
        candidates = np.arange(-np.pi, np.pi, self.resolution)
        free = self.free_distance(obstacles, candidates) >= look
        if not free.any():
            return desired
        turn = np.abs(np.angle(np.exp(1j * (candidates - desired)))) + np.abs(candidates)
        return float(candidates[free][np.argmin(turn[free])])

    def guard(self, action: np.ndarray, obstacles: np.ndarray, turn_gain: float = 1.5) -> np.ndarray:
        """A normalised (vx, vy, yaw rate) with its walk forward kept off what is ahead: where the way
        straight ahead is not clear, the robot turns towards the free heading `steer` picks and slows by
        its angle's cosine (for policies that give a twist, not a heading)."""
        action = np.asarray(action, dtype=np.float32).copy()
        if action[0] <= 0 or self.free_distance(obstacles, np.zeros(1))[0] >= self.look:
            return action
        heading = self.steer(obstacles, 0.0)
        action[0] *= max(float(np.cos(heading)), 0.0)
        action[2] = float(np.clip(turn_gain * heading, -1.0, 1.0))
        return action
