"""Import user meshes (OBJ, STL, PLY, GLB) as scenes, validated."""

from __future__ import annotations

import hashlib
import io
import warnings
from pathlib import Path

import numpy as np
import trimesh

from .geometry import polyline_length, resample_polyline
from .names import FORMATS
from .scene import Scene, SceneError, validate_mesh

UP_AXES = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "x": np.array([[0, 0, -1.0], [0, 1, 0], [1, 0, 0]]),
}


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes: what datasets and recordings keep to tell an edited or
    replaced mesh from the one they were made with."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


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
    if len(loaded.faces) == 0:
        raise SceneError(
            f"{path}: no triangles could be read from it: the file is damaged, or it is not a "
            f"{path.suffix[1:].upper()} file"
        )
    validate_mesh(loaded, str(path))
    tf = np.eye(4)
    tf[:3, :3] = UP_AXES[up_axis] * scale
    loaded.apply_transform(tf)
    return trimesh.Trimesh(loaded.vertices, loaded.faces, process=False)


MAX_COORDINATE_M = 1e7  # a waypoint further from the origin is a wrong number or unit, not a place


def load_route(path: str | Path, up_axis: str = "z", scale: float = 1.0) -> np.ndarray:
    """Waypoints on the floor from a text file (one 'x y z' or 'x, y, z' per line; 'x y' puts the
    floor at z = 0 in a z-up file), in the mesh file's own axes and units: they are rotated and
    scaled as `load_mesh` does the mesh, so they can be read off the same model. Returns (N, 3) metres."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"route file not found: {path}")
    if up_axis not in UP_AXES:
        raise SceneError(f"up_axis must be one of {sorted(UP_AXES)}, got '{up_axis}'")
    try:
        points = np.loadtxt(io.StringIO(path.read_text().replace(",", " ")), ndmin=2, comments="#")
    except ValueError as exc:
        raise SceneError(f"{path}: not a table of numbers ({exc})") from exc
    if points.shape[1] not in (2, 3) or len(points) < 2:
        raise SceneError(f"{path}: a route is two or more lines of 'x y' or 'x y z', got shape {points.shape}")
    if not np.isfinite(points).all():
        raise SceneError(f"{path}: the route holds NaN or inf")
    if points.shape[1] == 2:
        if up_axis != "z":
            raise SceneError(f"{path}: with up axis '{up_axis}' give the waypoints as 'x y z'")
        points = np.column_stack([points, np.zeros(len(points))])
    far = float(np.abs(points).max()) * abs(scale)
    if not far <= MAX_COORDINATE_M:  # also where the product overflows
        raise SceneError(
            f"{path}: a waypoint lies {far:.3g} m from the origin, beyond any mesh's {MAX_COORDINATE_M:.0e} m: "
            "check the file's numbers and its units (--scale)"
        )
    return points @ UP_AXES[up_axis].T * scale


MIN_ROUTE_M = 0.5  # shorter than the robot: no drive, no heading to start with
LONG_ROUTE_M = 2_000.0  # a drive of over 20,000 steps: warned of, as a mesh in millimetres given no scale
MAX_ROUTE_M = 50_000.0  # no route of this tool's drives is this long: a units mix-up, refused


def check_route_length(route: np.ndarray, where: str) -> None:
    """SceneError for a route without length (identical waypoints) or of implausible length, a warning
    for a very long one: both name the scale that would fix a mesh in millimetres."""
    length = polyline_length(route[:, :2])
    hint = "if the mesh and route are in millimetres, give scale 0.001 (--scale 0.001)"
    if length < MIN_ROUTE_M:
        raise SceneError(
            f"{where} is {length:.2f} m long on the floor: give waypoints at least {MIN_ROUTE_M} m apart "
            "(two identical waypoints make no route)"
        )
    if length > MAX_ROUTE_M:
        raise SceneError(f"{where} is {length / 1000:.0f} km long: {hint}")
    if length > LONG_ROUTE_M:
        warnings.warn(
            f"{where} is {length / 1000:.1f} km long, a drive of about {length / 0.1:,.0f} steps: {hint}", stacklevel=3
        )


FLOOR_BELOW_M = 0.5  # a waypoint lies on the floor, or at most this far above it


def check_route_on_floor(mesh: trimesh.Trimesh, route: np.ndarray, where: str) -> None:
    """SceneError naming the waypoints with no floor under them within FLOOR_BELOW_M (a route written
    in other axes, or 'x y' lines over a raised floor, whose parents and drive would find no ground)."""
    origins = route + [0.0, 0.0, 1.0]
    hits, rays, _ = mesh.ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (len(route), 1)))
    below = np.full(len(route), np.inf)
    np.minimum.at(below, rays, origins[rays, 2] - hits[:, 2])
    missing = np.flatnonzero(below > 1.0 + FLOOR_BELOW_M)
    if len(missing):
        shown = ", ".join(f"({route[k, 0]:.1f}, {route[k, 1]:.1f}, {route[k, 2]:.1f})" for k in missing[:3])
        raise SceneError(
            f"{where}: {len(missing)} of its {len(route)} points have no floor within {FLOOR_BELOW_M} m "
            f"under them, e.g. {shown} m: give each waypoint's height on the floor ('x y z' lines) or "
            "let --snap-route set it, and check that --up-axis and --scale are the mesh file's"
        )


SNAP_REACH_M = 2.0  # snapping looks for the floor from this far above a waypoint down to FLOOR_BELOW_M under it


def snap_route_to_floor(mesh: trimesh.Trimesh, route: np.ndarray) -> np.ndarray:
    """The route with each waypoint's height set to the floor under it: the first upward-facing surface
    met going down from SNAP_REACH_M above the waypoint (an 'x y' route over a raised floor, or
    heights a little off). Waypoints with no such surface within reach keep their height, for
    check_route_on_floor to name."""
    route = np.array(route, dtype=np.float64)
    origins = route + [0.0, 0.0, SNAP_REACH_M]
    hits, rays, faces = mesh.ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (len(route), 1)))
    floor = np.full(len(route), -np.inf)
    up = mesh.face_normals[faces, 2] > 0.5  # a floor faces up; a roof's underside does not
    reach = hits[:, 2] >= route[rays, 2] - FLOOR_BELOW_M
    np.maximum.at(floor, rays[up & reach], hits[up & reach, 2])
    found = np.isfinite(floor)
    route[found, 2] = floor[found]
    return route


def scene_from_mesh(
    path: str | Path,
    up_axis: str = "z",
    scale: float = 1.0,
    sampling_paths: list[np.ndarray] | None = None,
    start: tuple[float, float, float] | None = None,
    goal: tuple[float, float] | None = None,
    snap_to_floor: bool = False,
) -> Scene:
    """A scene from a mesh file, its sampling paths in metres in the scene's frame (z up). The first
    path is also the route the robot drives, from its first point facing along it, unless `start`
    and `goal` say otherwise. Without sampling paths the scene can be stepped but not labelled or
    driven along a route. `snap_to_floor`: each waypoint's height is set to the floor under it first
    (snap_route_to_floor)."""
    mesh = load_mesh(path, up_axis, scale)
    paths = [resample_polyline(np.asarray(p, dtype=np.float64), 1.0) for p in (sampling_paths or [])]
    if snap_to_floor:
        paths = [snap_route_to_floor(mesh, p) for p in paths]
    (x0, y0, z0), (x1, y1, z1) = mesh.bounds
    for p in paths:  # a route in other units or axes than the mesh: say so here, not as "no ground" later
        outside = p[
            (p[:, 0] < x0 - 0.5)
            | (p[:, 0] > x1 + 0.5)
            | (p[:, 1] < y0 - 0.5)
            | (p[:, 1] > y1 + 0.5)
            | (p[:, 2] < z0 - 0.5)
            | (p[:, 2] > z1 + 0.5)
        ]
        if len(outside):
            x, y, z = outside[0]
            raise SceneError(
                f"{path}: route point ({x:.1f}, {y:.1f}, {z:.1f}) m lies outside the mesh's extent "
                f"(x {x0:.1f} to {x1:.1f}, y {y0:.1f} to {y1:.1f}, z {z0:.1f} to {z1:.1f} m): are the "
                "route's units and axes those of the mesh file (--scale, --up-axis)?"
            )
    for i, p in enumerate(paths):
        check_route_length(p, f"{path}: route {i}")
        check_route_on_floor(mesh, p, f"{path}: route {i}")
    if start is None and paths:
        (x0, y0, _), (x1, y1, _) = paths[0][:2]
        start = (x0, y0, float(np.arctan2(y1 - y0, x1 - x0)))
    elif start is None:
        c = mesh.bounds.mean(axis=0)
        start = (float(c[0]), float(c[1]), 0.0)
    end = np.asarray(goal if goal is not None else paths[0][-1, :2] if paths else start[:2], dtype=np.float64)
    routes = {"main": paths[0]} if paths else {}
    return Scene(name=Path(path).stem, mesh=mesh, sampling_paths=paths, start=np.array(start), goal=end, routes=routes)
