"""A scripted pure-pursuit route follower, for demos, recordings and as a baseline policy."""

from __future__ import annotations

import numpy as np

from l3e_env.config import RobotConfig
from l3e_env.core.transforms import inverse
from scenes.geometry import polyline_length, resample_polyline

from .avoidance import FreeHeadings

CRUISE_SPEED = 1.0  # m/s, the robot stand-in's top forward speed (RobotConfig.max_twist)


def route_drive(route: np.ndarray) -> tuple[float, int]:
    """A route's length on the floor (m) and the steps of a drive along it at cruise speed."""
    length = polyline_length(np.asarray(route)[:, :2])
    return length, round(length / CRUISE_SPEED / RobotConfig.dt)


def walk_towards(
    heading_error: np.ndarray | float, speed: float = CRUISE_SPEED, turn_gain: float = 1.5
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised forward speed and yaw rate that walk towards a heading `heading_error` (rad) off
    the robot's own: forward at `speed` times the cosine of the turn (none past 90 deg), turning at
    `turn_gain` times its angle; element-wise."""
    error = np.asarray(heading_error, dtype=np.float64)
    return speed * np.clip(np.cos(error), 0.0, 1.0), np.clip(turn_gain * error, -1.0, 1.0)


class RouteFollower:
    """Steers towards a point `lookahead` metres further along the route.

    Returns normalised actions ([-1, 1] of the max twist), the environments' action space.
    Progress along the route only moves forward, so loops and U-turns in a route are followed.
    With `avoid`, a call given the scan's obstacles (FreeHeadings.obstacles) heads for the free
    heading nearest to the target's, so that a robot whose pose is off walks round what it meets.
    """

    def __init__(
        self,
        route: np.ndarray,
        lookahead: float = 2.0,
        speed: float = CRUISE_SPEED,
        turn_gain: float = 1.5,
        avoid: FreeHeadings | None = None,
    ):
        self.route = resample_polyline(np.asarray(route)[:, :2], 0.25)
        self.lookahead, self.speed, self.turn_gain, self.avoid = lookahead, speed, turn_gain, avoid
        self.index = 0

    def reset(self) -> None:
        self.index = 0

    def __call__(self, T_w_b: np.ndarray, obstacles: np.ndarray | None = None) -> np.ndarray:
        """Normalised (vx, vy, yaw rate) from the pose `T_w_b`; `obstacles`: the scan's, body-frame
        (x, y), used with `avoid`."""
        xy = T_w_b[:2, 3]
        window = self.route[self.index : self.index + 40]
        self.index += int(np.argmin(np.linalg.norm(window - xy, axis=1)))
        ahead = self.route[self.index :]
        far = np.flatnonzero(np.linalg.norm(ahead - xy, axis=1) >= self.lookahead)
        target = ahead[far[0]] if len(far) else self.route[-1]
        local = inverse(T_w_b) @ np.array([target[0], target[1], T_w_b[2, 3], 1.0])
        heading_error = float(np.arctan2(local[1], local[0]))
        if self.avoid is not None and obstacles is not None:
            heading_error = self.avoid.steer(
                obstacles, heading_error, look=min(self.avoid.look, float(np.hypot(local[0], local[1])))
            )
        forward, turn = walk_towards(heading_error, self.speed, self.turn_gain)
        return np.array([forward, 0.0, turn], dtype=np.float32)
