"""Import user meshes (OBJ, STL, PLY, GLB) as scenes, validated."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from .geometry import resample_polyline
from .scene import Scene, SceneError, validate_mesh

UP_AXES = {"z": np.eye(3), "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
           "x": np.array([[0, 0, -1.0], [0, 1, 0], [1, 0, 0]])}
FORMATS = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")


def load_mesh(path: str | Path, up_axis: str = "z", scale: float = 1.0) -> trimesh.Trimesh:
    """Load a triangle mesh file, rotate its up axis onto +z and scale it to metres."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"mesh file not found: {path}")
    if path.suffix.lower() not in FORMATS:
        raise SceneError(f"{path}: unsupported mesh format '{path.suffix}' (use one of {FORMATS})")
    if up_axis not in UP_AXES:
        raise SceneError(f"up_axis must be one of {sorted(UP_AXES)}, got '{up_axis}'")
    if not (np.isfinite(scale) and scale > 0):
        raise SceneError(f"scale must be a positive number, got {scale}")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for broken files
        raise SceneError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    if isinstance(loaded, trimesh.Scene) or not isinstance(loaded, trimesh.Trimesh):
        raise SceneError(f"{path}: file holds no triangle mesh")
    validate_mesh(loaded, str(path))
    tf = np.eye(4)
    tf[:3, :3] = UP_AXES[up_axis] * scale
    loaded.apply_transform(tf)
    return trimesh.Trimesh(loaded.vertices, loaded.faces, process=False)


def scene_from_mesh(
    path: str | Path,
    up_axis: str = "z",
    scale: float = 1.0,
    sampling_paths: list[np.ndarray] | None = None,
    start: tuple[float, float, float] | None = None,
    goal: tuple[float, float] | None = None,
) -> Scene:
    """A scene from a mesh file. Without sampling paths the scene can be driven but not labelled."""
    mesh = load_mesh(path, up_axis, scale)
    paths = [resample_polyline(np.asarray(p, dtype=np.float64), 1.0) for p in (sampling_paths or [])]
    if start is None:
        c = mesh.bounds.mean(axis=0)
        start = (c[0], c[1], 0.0)
    goal = goal if goal is not None else start[:2]
    routes = {"main": paths[0]} if paths else {}
    return Scene(name=Path(path).stem, mesh=mesh, sampling_paths=paths, start=start, goal=goal, routes=routes)
