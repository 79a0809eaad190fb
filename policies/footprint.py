"""The robot's base box against the scene's obstacles in the plane, at any heading.

The free-space grid (policies.freespace) says where the box fits square to the grid at a cell's
centre, in 0.5 m cells. That is coarse enough for a fast-environment robot to walk where the
simulated one is wedged: turned 30 degrees, its corner catches a box that the cell clears, and a
policy trained on the grid keeps pushing into it. Here the obstacles' walls at the base's height
are rasterised finely (mesh cut by horizontal planes through the base's height band above the
floor), and a pose collides where the box's outline touches one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage

from l3e_env.config import RobotConfig
from scenes import Scene

from .freespace import FreeSpace


@dataclass
class Footprint:
    origin: np.ndarray  # (2,) world x, y of raster cell (0, 0)
    resolution: float
    blocked: np.ndarray  # (nx, ny) bool: an obstacle's wall at the base's height in the cell
    outline: np.ndarray  # (K, 2) points on the base box's outline, body frame

    def collides(self, x: float, y: float, yaw: float) -> bool:
        """Whether the base box at (x, y, yaw) touches an obstacle (or leaves the raster)."""
        c, s = np.cos(yaw), np.sin(yaw)
        world = self.outline @ np.array([[c, s], [-s, c]]) + (x, y)
        idx = np.rint((world - self.origin) / self.resolution).astype(np.int64)
        inside = (idx >= 0).all(axis=1) & (idx[:, 0] < self.blocked.shape[0]) & (idx[:, 1] < self.blocked.shape[1])
        if not inside.all():
            return True
        return bool(self.blocked[idx[:, 0], idx[:, 1]].any())


def box_outline(length: float, width: float, spacing: float) -> np.ndarray:
    """Points every `spacing` (or closer) around a length x width rectangle centred at the origin."""
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1], [1, 1]]) * (length / 2, width / 2)
    points = []
    for a, b in zip(corners[:-1], corners[1:]):
        n = max(int(np.ceil(np.linalg.norm(b - a) / spacing)), 1)
        points.append(a + (b - a) * np.arange(n)[:, None] / n)
    return np.concatenate(points)


def build_footprint(scene: Scene, space: FreeSpace, robot: RobotConfig | None = None,
                    resolution: float = 0.05, plane_spacing: float = 0.1) -> Footprint:
    """Rasterise the mesh's cuts at the base's height over the free space's extent; each cut
    point counts where it lies within the base's height band above the nearest known floor."""
    if not resolution > 0 or not plane_spacing > 0:
        raise ValueError(f"resolution and plane spacing must be positive, got {resolution} and {plane_spacing}")
    robot = robot or RobotConfig()
    known = np.isfinite(space.ground)
    if not known.any():
        raise ValueError(f"scene '{scene.name}': the free space knows no floor height")
    # the floor under every coarse cell: its own, else the nearest cell's that has one
    nearest = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
    floor = space.ground[nearest[0], nearest[1]]
    low, high = robot.standing_height - robot.base_size[2] / 2, robot.standing_height + robot.base_size[2] / 2
    heights = np.arange(np.nanmin(floor) + low, np.nanmax(floor) + high + plane_spacing, plane_spacing)
    lo = space.origin - space.resolution
    hi = space.origin + (np.asarray(space.shape) + 1) * space.resolution
    blocked = np.zeros(tuple(np.ceil((hi - lo) / resolution).astype(int) + 1), dtype=bool)
    for h in heights:
        segments = trimesh.intersections.mesh_plane(scene.mesh, [0.0, 0.0, 1.0], [0.0, 0.0, float(h)])
        if len(segments) == 0:
            continue
        length = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
        n = np.maximum(np.ceil(length / (resolution / 2)).astype(int), 1)
        which = np.repeat(np.arange(len(segments)), n + 1)
        t = np.concatenate([np.linspace(0.0, 1.0, k + 1) for k in n])
        points = segments[which, 0] + (segments[which, 1] - segments[which, 0]) * t[:, None]
        cell = np.clip(space.index(points[:, :2]), 0, np.asarray(space.shape) - 1)
        above = points[:, 2] - floor[cell[:, 0], cell[:, 1]]
        points = points[(above >= low) & (above <= high)]
        idx = np.rint((points[:, :2] - lo) / resolution).astype(np.int64)
        ok = (idx >= 0).all(axis=1) & (idx[:, 0] < blocked.shape[0]) & (idx[:, 1] < blocked.shape[1])
        blocked[idx[ok, 0], idx[ok, 1]] = True
    length, width = robot.base_size[0], robot.base_size[1]
    return Footprint(lo, float(resolution), blocked, box_outline(length, width, resolution / 2))
