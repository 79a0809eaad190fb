"""Localizability-aware planning on the free-space grid.

Cost of a path = its length + lambda x its expected drift. Expected drift, per metre walked
with heading theta, is  sum_i masked_i(cell, theta) * k_i : the fusion drops ICP on the axes the
detector masks (the map's `masked`, interpolated over yaw bins), and along those axes the estimate
follows leg odometry, whose error grows per metre at the rates k_i of `drift_rates`. The
shortest-path planner is the same search with lambda = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from l3e_env.config import OdometryConfig

from .freespace import FreeSpace, FreeSpaceError
from .locmap import LocalizabilityMap

# m: a free cell with less clearance is next to a blocked one, where the robot fits only square to
# the grid at the cell's centre (the planner's and the fast environment's squeeze rule)
TIGHT_CLEARANCE = 0.6
# 8-connected moves (dx, dy) in cells
MOVES = np.array([(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)])


class PlanningError(ValueError):
    """No path: the start or goal is blocked, off the grid, or the goal cannot be reached."""


def drift_rates(
    odometry: OdometryConfig | None = None, step_length: float = 0.1, lever_arm: float = 10.0
) -> np.ndarray:
    """Metres of position error per metre walked while one axis (x, y, z, roll, pitch, yaw) is
    left to leg odometry, from its noise model (l3e_env.sim.odometry.LegOdometry):
    - systematic parts grow linearly: the stride-scale error (x), the z and yaw biases; their
      expected size is sqrt(2/pi) sigma;
    - white per-step noise (sigma proportional to the step length) grows as a random walk; it is
      counted at its size over one metre of `step_length` steps, sigma * sqrt(step_length);
    - an angle error becomes a position error over the distance walked afterwards; `lever_arm`
      (m) stands for that distance, because scan-to-scan ICP never removes a heading error
      once made.
    """
    c = odometry or OdometryConfig()
    mean_abs, walk = np.sqrt(2 / np.pi), np.sqrt(step_length)
    return np.array(
        [
            mean_abs * c.scale_error_std + c.trans_noise_per_m * walk,
            c.trans_noise_per_m * walk,
            mean_abs * c.z_bias_std + c.z_noise_per_m * walk,
            lever_arm * c.rp_noise_per_m * walk,
            lever_arm * c.rp_noise_per_m * walk,
            lever_arm * (mean_abs * c.yaw_bias_std + c.yaw_noise_per_m * walk),
        ]
    )


@dataclass
class Plan:
    path: np.ndarray  # (K, 2) world x, y of cell centres, start to goal
    length: float  # metres
    expected_drift: float  # metres, sum over the path of the drift model
    cost: float  # length + lam * expected_drift (+ the clearance term)


class Planner:
    """Dijkstra on the 8-connected free cells (scipy's csgraph), with heading-dependent edge costs."""

    def __init__(
        self,
        space: FreeSpace,
        locmap: LocalizabilityMap | None = None,
        lam: float = 50.0,
        odometry: OdometryConfig | None = None,
        clearance: float = 0.75,
        clearance_weight: float = 1.0,
        tight_clearance: float = TIGHT_CLEARANCE,
        tight_weight: float = 10.0,
    ):
        if lam > 0 and locmap is None:
            raise ValueError("a localizability-aware plan (lam > 0) needs a localizability map")
        self.space, self.locmap, self.lam = space, locmap, float(lam)
        self.rates = drift_rates(odometry)
        cells = np.argwhere(space.free)
        self.cells = cells
        ids = -np.ones(space.shape, dtype=np.int64)
        ids[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
        self.ids = ids
        rows, cols, drifts, costs = [], [], [], []
        # near walls a path is longer in effect (the follower cuts corners): cost per metre grows
        # linearly to clearance_weight as the clearance falls from `clearance` to zero
        cell_clearance = space.clearance[cells[:, 0], cells[:, 1]]
        near = clearance_weight * np.clip(1 - cell_clearance / clearance, 0, 1)
        # a cell next to a blocked one is free only at yaw 0 and 90 degrees at its centre: a robot
        # turning or off by a few centimetres there hits the obstacle, so such squeezes cost
        # tight_weight more per metre and are taken only where no wider way exists
        near += tight_weight * (cell_clearance < tight_clearance)
        for dx, dy in MOVES:
            nxt = cells + (dx, dy)
            ok = space.inside(nxt)
            ok[ok] = space.free[nxt[ok, 0], nxt[ok, 1]]
            a, b = np.flatnonzero(ok), ids[nxt[ok, 0], nxt[ok, 1]]
            length = space.resolution * float(np.hypot(dx, dy))
            drift = np.zeros(len(a))
            if locmap is not None:
                mid = space.center(cells[a] + 0.5 * np.array([dx, dy]))
                masked = locmap.lookup(mid, np.full(len(a), np.arctan2(dy, dx)))
                drift = length * masked @ self.rates
            rows.append(a)
            cols.append(b)
            drifts.append(drift)
            costs.append(length * (1 + 0.5 * (near[a] + near[b])) + self.lam * drift)
        row, col, n = np.concatenate(rows), np.concatenate(cols), len(cells)
        self.graph = coo_matrix((np.concatenate(costs), (row, col)), shape=(n, n)).tocsr()
        # same sparsity as the cost graph: a plan reads its edges' drift back by (from, to)
        self.drift_graph = coo_matrix((np.concatenate(drifts), (row, col)), shape=(n, n)).tocsr()

    def _node(self, xy: np.ndarray, what: str) -> int:
        xy = np.asarray(xy, dtype=np.float64)[:2]
        if not np.isfinite(xy).all():
            raise PlanningError(f"{what} {xy} is not finite")
        idx = self.space.index(xy)
        if not self.space.inside(idx):
            raise PlanningError(f"{what} ({xy[0]:.2f}, {xy[1]:.2f}) is outside the scene's grid")
        if not self.space.free[idx[0], idx[1]]:
            raise PlanningError(
                f"{what} ({xy[0]:.2f}, {xy[1]:.2f}) is inside an obstacle or where the robot cannot stand"
            )
        return int(self.ids[idx[0], idx[1]])

    def cost_to_go(self, goal: np.ndarray) -> np.ndarray:
        """Cost from every free cell to the goal (inf where unreachable), as a grid."""
        g = self._node(goal, "goal")
        dist = dijkstra(self.graph.T.tocsr(), indices=g)  # reversed edges: costs towards the goal
        grid = np.full(self.space.shape, np.inf)
        grid[self.cells[:, 0], self.cells[:, 1]] = dist
        return grid

    def plan(self, start: np.ndarray, goal: np.ndarray) -> Plan:
        s, g = self._node(start, "start"), self._node(goal, "goal")
        dist, pred = dijkstra(self.graph, indices=s, return_predecessors=True)
        if not np.isfinite(dist[g]):
            raise PlanningError(
                f"the goal ({goal[0]:.2f}, {goal[1]:.2f}) cannot be reached from the start "
                f"({start[0]:.2f}, {start[1]:.2f}) through free space"
            )
        nodes = [g]
        while nodes[-1] != s:
            nodes.append(int(pred[nodes[-1]]))
        nodes.reverse()
        path = self.space.center(self.cells[nodes])
        length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
        drift = float(np.asarray(self.drift_graph[nodes[:-1], nodes[1:]]).sum()) if len(nodes) > 1 else 0.0
        return Plan(path, length, drift, float(dist[g]))


def expected_drift_along(path: np.ndarray, locmap: LocalizabilityMap, rates: np.ndarray) -> float:
    """The drift model summed along a walked path (K, 2+), as the planner sums it along its edges:
    each segment's length x the axes the map masks at its middle, heading along it, weighted by
    the odometry's drift rates (metres)."""
    xy = np.asarray(path, dtype=np.float64)[:, :2]
    step = np.diff(xy, axis=0)
    length = np.linalg.norm(step, axis=1)
    moved = length > 1e-9
    if not moved.any():
        return 0.0
    middle = xy[:-1][moved] + 0.5 * step[moved]
    masked = locmap.lookup(middle, np.arctan2(step[moved, 1], step[moved, 0]))
    return float(length[moved] @ (masked @ rates))


def route_of(plan: Plan, space: FreeSpace) -> np.ndarray:
    """The plan as ground points (K, 3) for the route follower."""
    idx = space.index(plan.path)
    z = np.nan_to_num(space.ground[idx[:, 0], idx[:, 1]])
    return np.column_stack([plan.path, z])


__all__ = [
    "Plan",
    "Planner",
    "PlanningError",
    "FreeSpaceError",
    "TIGHT_CLEARANCE",
    "drift_rates",
    "expected_drift_along",
    "route_of",
]
