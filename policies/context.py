"""One scene made ready for navigation: its free space and localizability map, both cached."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from l3e_env.config import RobotConfig, to_dict
from l3e_env.core.files import write_atomic
from scenes import Scene, make_scene

from . import MAP_RESOLUTION
from .freespace import FreeSpace, build_free_space, reachable_from
from .locmap import LocalizabilityMap, MapBuild, MapGrid, default_cache_dir, get_map, settings_digest


@dataclass
class SceneContext:
    scene: Scene
    space: FreeSpace  # the part connected to the start
    locmap: LocalizabilityMap | None

    @property
    def built_map(self) -> LocalizabilityMap:
        """The localizability map, or ValueError where the context was made without one."""
        if self.locmap is None:
            raise ValueError(f"scene {self.scene.name} has no localizability map here (made with detector None)")
        return self.locmap


def free_space(
    scene: Scene,
    cache_dir: str | Path | None = None,
    resolution: float = 0.5,
    robot: RobotConfig | None = None,
    progress: bool = False,
) -> FreeSpace:
    """The free space reachable from the scene's start, cached beside the maps."""
    robot = robot or RobotConfig()
    key = {
        "scene": scene.name,
        "faces": int(len(scene.mesh.faces)),
        "bounds": scene.bounds.round(3).tolist(),
        "start": scene.start.round(3).tolist(),
        "resolution": resolution,
        "robot": to_dict(robot),
    }
    path = Path(cache_dir or default_cache_dir()) / f"{scene.name}-free-{settings_digest(key)}.npz"
    if path.exists():
        with np.load(path) as z:
            return FreeSpace(z["origin"], float(z["resolution"]), z["free"], z["ground"], z["clearance"])
    space = reachable_from(build_free_space(scene, resolution, robot, progress=progress), scene.start[:2])
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(
        path,
        lambda fh: np.savez(
            fh,
            origin=space.origin,
            resolution=space.resolution,
            free=space.free,
            ground=space.ground,
            clearance=space.clearance,
        ),
    )
    return space


def scene_context(
    name: str,
    detector: str | None = "learned",
    cache_dir: str | Path | None = None,
    build: bool | MapBuild = True,
    grid: MapGrid | None = None,
    progress: bool = False,
    scene_params: dict | None = None,
) -> SceneContext:
    """Scene, free space and (unless detector is None) its localizability map on `grid` (positions
    MAP_RESOLUTION apart by default), built as `build` says where it is not cached (get_map; True:
    with `progress`); `scene_params` go to make_scene (a mesh scene's up axis, scale and route)."""
    scene = make_scene(name, **(scene_params or {}))
    space = free_space(scene, cache_dir, progress=progress)
    locmap = None
    if detector is not None:
        grid = grid or MapGrid(resolution=MAP_RESOLUTION)
        how = MapBuild(progress=progress) if build is True else build
        locmap = get_map(scene, space, detector, cache_dir, how, grid)
    return SceneContext(scene, space, locmap)
