"""The Scene container: a triangle mesh plus the paths that say where a robot may stand."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh


class SceneError(ValueError):
    """A scene or mesh that cannot be used: the message names the problem."""


def _as_polyline(points: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 2:
        raise SceneError(f"{what} must be an (K>=2, 3) array of ground points, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise SceneError(f"{what} contains NaN or infinite coordinates")
    return arr


@dataclass
class Scene:
    """Static geometry of one environment.

    `sampling_paths` are poly-lines of ground points (metres, world frame) around which the
    label generator samples sensor poses, as in the paper. `routes` are named poly-lines from
    `start` to `goal` for the robot to drive; `start` is (x, y, yaw) and `goal` (x, y).
    """

    name: str
    mesh: trimesh.Trimesh
    sampling_paths: list[np.ndarray]
    start: np.ndarray
    goal: np.ndarray
    routes: dict[str, np.ndarray] = field(default_factory=dict)
    family: str = "custom"
    seed: int = 0
    # named places (the mine's yard, tunnel and quarry) as ground-plane boxes (x0, y0, x1, y1)
    regions: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        validate_mesh(self.mesh, self.name)
        self.sampling_paths = [
            _as_polyline(p, f"scene '{self.name}' sampling path {i}") for i, p in enumerate(self.sampling_paths)
        ]
        self.routes = {k: _as_polyline(v, f"scene '{self.name}' route '{k}'") for k, v in self.routes.items()}
        self.start = np.asarray(self.start, dtype=np.float64).reshape(3)
        self.goal = np.asarray(self.goal, dtype=np.float64).reshape(2)
        if not (np.isfinite(self.start).all() and np.isfinite(self.goal).all()):
            raise SceneError(f"scene '{self.name}': start or goal is not finite")

    @classmethod
    def along_route(cls, name: str, mesh: trimesh.Trimesh, route: np.ndarray, family: str, seed: int) -> Scene:
        """A scene whose one route is also its sampling path; the robot starts facing along it."""
        heading = float(np.arctan2(route[1, 1] - route[0, 1], route[1, 0] - route[0, 0]))
        return cls(
            name=name,
            mesh=mesh,
            sampling_paths=[route],
            start=np.array((route[0, 0], route[0, 1], heading)),
            goal=route[-1, :2],
            routes={"main": route},
            family=family,
            seed=seed,
        )

    @classmethod
    def two_ways(
        cls,
        name: str,
        mesh: trimesh.Trimesh,
        short: np.ndarray,
        rich: np.ndarray,
        family: str,
        seed: int,
        regions: dict[str, np.ndarray],
    ) -> Scene:
        """A navigation scene: from the origin facing +x to the end of both routes, a `short` way
        and a longer `rich` one (the default route); both are sampling paths."""
        return cls(
            name=name,
            mesh=mesh,
            sampling_paths=[short, rich],
            start=np.array((0.0, 0.0, 0.0)),
            goal=short[-1, :2],
            routes={"short": short, "rich": rich, "main": rich},
            family=family,
            seed=seed,
            regions=regions,
        )

    @property
    def route(self) -> np.ndarray:
        """The default route: 'main' if present, else the first one."""
        if not self.routes:
            raise SceneError(f"scene '{self.name}' has no route")
        return self.routes.get("main", next(iter(self.routes.values())))

    def region_of(self, xy: np.ndarray) -> str | None:
        """The first named region (x0, y0, x1, y1 in the world's ground plane) holding the point, if any."""
        for name, (x0, y0, x1, y1) in self.regions.items():
            if x0 <= xy[0] <= x1 and y0 <= xy[1] <= y1:
                return name
        return None

    @property
    def bounds(self) -> np.ndarray:
        return np.asarray(self.mesh.bounds, dtype=np.float64)

    def summary(self) -> str:
        ext = self.bounds[1] - self.bounds[0]
        return (
            f"{self.name} ({self.family}, seed {self.seed}): {len(self.mesh.faces)} triangles, "
            f"extent {ext[0]:.0f} x {ext[1]:.0f} x {ext[2]:.0f} m, {len(self.sampling_paths)} sampling paths, "
            f"routes {sorted(self.routes)}"
        )


def validate_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> None:
    """Raise SceneError if the mesh is empty, has NaN vertices or bad face indices."""
    if not isinstance(mesh, trimesh.Trimesh):
        raise SceneError(f"{name}: expected a triangle mesh, got {type(mesh).__name__}")
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise SceneError(f"{name}: the mesh is empty (no triangles)")
    if not np.isfinite(mesh.vertices).all():
        raise SceneError(f"{name}: the mesh has NaN or infinite vertex coordinates")
    if mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices):
        raise SceneError(f"{name}: face indices point outside the vertex array")
    if float(mesh.area) <= 0.0:
        raise SceneError(f"{name}: the mesh has zero surface area")
