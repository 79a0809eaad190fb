"""What a learned navigation policy sees, computed the same way in fast training and in the
full pipeline: the goal, free-space ranges and the localizability map's drift ahead, all from
the free-space grid and the cached map at the robot's (estimated) planar pose."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from .freespace import FreeSpace
from .locmap import LocalizabilityMap, heading_bins
from .planner import Planner, drift_rates

SECTORS = 16  # body-frame directions, counter-clockwise from straight ahead
RANGE = 8.0  # m, free-space ranges are capped here
LOOKAHEAD = (1.0, 2.0, 3.0, 4.0, 6.0, 8.0)  # m, where the drift ahead is sampled along each sector
GOAL_SCALE = 30.0  # m


class PolicyView:
    """obs = [goal x, y in the body frame / GOAL_SCALE (clipped to [-1, 1]), distance / GOAL_SCALE,
    shortest-path direction (cos, sin) in the body frame, SECTORS free ranges / RANGE,
    SECTORS drift-ahead values, drift rate here, localizability-aware path direction (cos, sin)];
    drift values are sum_i masked_i * k_i / max(k) (policies.planner.drift_rates), heading along
    the sector: 1 means the worst single axis lost.

    The aware direction is downhill on the planner's cost-to-go (length + lam x expected drift) over
    the whole map: the drift ahead reaches 8 m, and without it the policy cannot tell how far a
    detour should keep from a degenerate corridor it does not see yet."""

    size = 8 + 2 * SECTORS
    ranges = slice(5, 5 + SECTORS)
    drift_ahead = slice(5 + SECTORS, 5 + 2 * SECTORS)
    aware = slice(6 + 2 * SECTORS, 8 + 2 * SECTORS)

    def __init__(self, space: FreeSpace, locmap: LocalizabilityMap, goal: np.ndarray, lam: float = 50.0):
        self.space, self.locmap, self.goal = space, locmap, np.asarray(goal, dtype=np.float64)[:2]
        rates = drift_rates()
        self.scale = float(rates.max())
        # expected drift per metre (m/m) for every grid cell and mapped heading: a table, so that the
        # thousands of lookups per second of fast training are array indexing
        nx, ny = space.shape
        centres = space.center(np.stack(np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"), -1).reshape(-1, 2))
        self.table = (locmap.masked @ rates)[locmap.nearest(centres)].reshape(nx, ny, len(locmap.yaws))
        # shortest distances through free space
        self.to_go = Planner(space, lam=0.0, clearance_weight=0.0, tight_weight=0.0).cost_to_go(self.goal)
        self.downhill = _downhill_headings(self.to_go)
        self.aware_downhill = _downhill_headings(Planner(space, locmap, lam=lam).cost_to_go(self.goal))
        self.angles = np.arange(SECTORS) * 2 * np.pi / SECTORS
        self.observation_space = spaces.Box(-1.0, float(rates.sum() / self.scale), (self.size,), np.float32)

    def distance_to_go(self, xy: np.ndarray) -> float:
        """Shortest free-space distance to the goal from the cell of xy (inf if blocked or cut off)."""
        idx = self.space.index(xy)
        if not self.space.inside(idx):
            return float("inf")
        return float(self.to_go[idx[0], idx[1]])

    def shortest_direction(self, xy: np.ndarray) -> float:
        """World heading towards the neighbouring cell with the least distance to go (towards the
        goal itself where no neighbour is closer, or off the grid)."""
        return self._downhill_direction(xy, self.downhill)

    def _downhill_direction(self, xy: np.ndarray, downhill: np.ndarray) -> float:
        idx = self.space.index(xy)
        if self.space.inside(idx) and np.isfinite(heading := downhill[idx[0], idx[1]]):
            return float(heading)
        return float(np.arctan2(*(self.goal - xy)[::-1]))

    def clearance(self, xy: np.ndarray) -> float:
        """Distance (m) from the cell of xy to the nearest blocked cell; 0 off the grid."""
        idx = self.space.index(xy)
        return float(self.space.clearance[idx[0], idx[1]]) if self.space.inside(idx) else 0.0

    def drift_rate(self, xy: np.ndarray, heading: np.ndarray | float) -> np.ndarray:
        """Expected drift per metre walked (m/m) at points (..., 2) with headings (...), linear
        between the map's heading bins; 0 off the grid."""
        idx = self.space.index(xy)
        ok = self.space.inside(idx)
        ix, iy = np.where(ok, idx[..., 0], 0), np.where(ok, idx[..., 1], 0)
        lo, hi, w = heading_bins(np.asarray(heading), self.table.shape[2])
        value = (1 - w) * self.table[ix, iy, lo] + w * self.table[ix, iy, hi]
        return np.where(ok, value, 0.0)

    def __call__(self, x: float, y: float, yaw: float) -> np.ndarray:
        xy = np.array([x, y])
        c, s = np.cos(yaw), np.sin(yaw)
        d = self.goal - xy
        goal_b = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
        path = self.shortest_direction(xy) - yaw
        aware = self._downhill_direction(xy, self.aware_downhill) - yaw
        world = yaw + self.angles
        ranges = self.space.ray_distances(xy, world, RANGE)
        ahead = np.asarray(LOOKAHEAD)
        pts = xy + ahead[None, :, None] * np.stack([np.cos(world), np.sin(world)], -1)[:, None, :]
        values = self.drift_rate(pts, np.repeat(world[:, None], len(ahead), axis=1)) / self.scale
        reach = ahead[None, :] <= ranges[:, None] + 1e-9  # drift beyond a wall is not on the way
        drift_ahead = np.where(reach.any(1), (values * reach).sum(1) / np.maximum(reach.sum(1), 1), 0.0)
        obs = np.concatenate(
            [
                np.clip(goal_b / GOAL_SCALE, -1, 1),
                [min(np.linalg.norm(d) / GOAL_SCALE, 1.0)],
                [np.cos(path), np.sin(path)],
                ranges / RANGE,
                drift_ahead,
                [self.drift_rate(xy, yaw) / self.scale],
                [np.cos(aware), np.sin(aware)],
            ]
        )
        return obs.astype(np.float32)


def _downhill_headings(to_go: np.ndarray) -> np.ndarray:
    """Per cell, the heading (rad) to the 8-neighbour with the least distance to go, NaN where no
    neighbour is closer than the cell; ties go to the first neighbour in (dx, dy) order."""
    steps = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]
    padded = np.pad(to_go, 1, constant_values=np.inf)
    nx, ny = to_go.shape
    around = np.stack([padded[1 + dx : 1 + dx + nx, 1 + dy : 1 + dy + ny] for dx, dy in steps])
    best = np.argmin(around, axis=0)
    headings = np.array([np.arctan2(dy, dx) for dx, dy in steps])[best]
    closer = np.take_along_axis(around, best[None], 0)[0] < to_go
    return np.where(closer, headings, np.nan)
