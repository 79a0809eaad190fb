"""Where the robot can stand: a 2-D grid of a scene's free space, made with the robot's own
ground and collision checks so that planned cells are cells the simulated robot can occupy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from tqdm import tqdm

from l3e_env.config import RobotConfig
from l3e_env.sim.world import World
from scenes import Scene


class FreeSpaceError(ValueError):
    """A scene without free space, or a point outside it: the message says which."""


@dataclass
class FreeSpace:
    """free[ix, iy] is True where the robot's base fits at both yaw 0 and 90 degrees on ground
    within `max_step_up` of the floor level `z_ref`; cell (ix, iy) has its centre at
    origin + (ix, iy) * resolution. `clearance` is the distance (m) to the nearest blocked cell."""

    origin: np.ndarray  # (2,) world x, y of cell (0, 0)
    resolution: float
    free: np.ndarray  # (nx, ny) bool
    ground: np.ndarray  # (nx, ny) float, terrain height under the cell centre (NaN: no ground)
    clearance: np.ndarray  # (nx, ny) float metres

    @property
    def shape(self) -> tuple[int, int]:
        return self.free.shape  # type: ignore[return-value]

    def index(self, xy: np.ndarray) -> np.ndarray:
        """Integer cell index of world points (..., 2), unclipped."""
        return np.rint((np.asarray(xy, dtype=np.float64) - self.origin) / self.resolution).astype(np.int64)

    def center(self, index: np.ndarray) -> np.ndarray:
        return self.origin + np.asarray(index, dtype=np.float64) * self.resolution

    def inside(self, index: np.ndarray) -> np.ndarray:
        index = np.asarray(index)
        return (
            (index[..., 0] >= 0)
            & (index[..., 1] >= 0)
            & (index[..., 0] < self.shape[0])
            & (index[..., 1] < self.shape[1])
        )

    def is_free(self, xy: np.ndarray) -> np.ndarray:
        """Whether world points (..., 2) fall in free cells (False off the grid)."""
        idx = self.index(xy)
        ok = self.inside(idx)
        out = np.zeros(ok.shape, dtype=bool)
        out[ok] = self.free[idx[ok][:, 0], idx[ok][:, 1]]
        return out

    def free_centers(self) -> np.ndarray:
        """(K, 2) world x, y of every free cell."""
        return self.center(np.argwhere(self.free))

    def ray_distances(
        self, xy: np.ndarray, angles: np.ndarray, max_range: float, step: float | None = None
    ) -> np.ndarray:
        """Distance from `xy` to the first blocked cell along each world angle, capped at max_range."""
        step = step or self.resolution / 2
        r = np.arange(step, max_range + 1e-9, step)
        unit = np.stack([np.cos(angles), np.sin(angles)], -1)
        pts = np.asarray(xy)[None, None, :] + r[None, :, None] * unit[:, None, :]
        blocked = ~self.is_free(pts)
        first = np.where(blocked.any(axis=1), blocked.argmax(axis=1), len(r))
        return np.where(first < len(r), r[np.minimum(first, len(r) - 1)] - step, max_range)


def grid_axes(scene: Scene, resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell centres aligned to multiples of `resolution` over the scene's footprint."""
    (x0, y0, _), (x1, y1, _) = scene.bounds
    xs = np.arange(np.floor(x0 / resolution), np.ceil(x1 / resolution) + 1) * resolution
    ys = np.arange(np.floor(y0 / resolution), np.ceil(y1 / resolution) + 1) * resolution
    return np.array([xs[0], ys[0]]), xs, ys


def build_free_space(
    scene: Scene,
    resolution: float = 0.5,
    robot: RobotConfig | None = None,
    z_ref: float | None = None,
    progress: bool = False,
) -> FreeSpace:
    """Test every cell with the simulated robot: ground under its feet near the start's floor
    level, and no penetration of its base box at yaw 0 or 90 degrees."""
    if not resolution > 0:
        raise ValueError(f"free-space resolution must be positive, got {resolution}")
    robot = robot or RobotConfig()
    z_ref = float(scene.route[0, 2]) if z_ref is None else z_ref
    origin, xs, ys = grid_axes(scene, resolution)
    free = np.zeros((len(xs), len(ys)), dtype=bool)
    ground = np.full((len(xs), len(ys)), np.nan)
    world = World(scene, robot)
    try:
        for ix in tqdm(range(len(xs)), desc=f"free space {scene.name}", unit="col", disable=not progress):
            for iy, y in enumerate(ys):
                T = world.ground_pose(float(xs[ix]), float(y), 0.0, z_ref)
                if T is None or abs(T[2, 3] - robot.standing_height - z_ref) > robot.max_step_up:
                    continue
                ground[ix, iy] = T[2, 3] - robot.standing_height
                T90 = world.ground_pose(float(xs[ix]), float(y), np.pi / 2, z_ref)
                free[ix, iy] = not world.in_collision(T) and T90 is not None and not world.in_collision(T90)
    finally:
        world.close()
    if not free.any():
        raise FreeSpaceError(
            f"scene '{scene.name}' has no cell where the robot can stand at floor level "
            f"{z_ref:.2f} m (grid {len(xs)} x {len(ys)} at {resolution} m)"
        )
    clearance = ndimage.distance_transform_edt(free) * resolution
    return FreeSpace(origin, float(resolution), free, ground, clearance)


def reachable_from(space: FreeSpace, xy: np.ndarray) -> FreeSpace:
    """The part of the free space connected (8-neighbourhood) to the cell at `xy`: the rest of a
    scene, behind walls, is of no use to a robot starting there and costs map time."""
    idx = space.index(xy)
    if not space.is_free(xy):
        raise FreeSpaceError(
            f"({xy[0]:.2f}, {xy[1]:.2f}) is not in the free space: inside an obstacle, off the "
            f"ground or outside the grid"
        )
    labels, _ = ndimage.label(space.free, structure=np.ones((3, 3)))
    free = labels == labels[idx[0], idx[1]]
    return FreeSpace(
        space.origin, space.resolution, free, space.ground, ndimage.distance_transform_edt(free) * space.resolution
    )
