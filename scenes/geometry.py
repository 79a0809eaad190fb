"""Mesh-building helpers shared by the procedural scene families."""

from __future__ import annotations

import numpy as np
import trimesh


def box(center: tuple[float, float, float], size: tuple[float, float, float], yaw: float = 0.0) -> trimesh.Trimesh:
    """An axis-aligned (then yawed) box given by centre and full size."""
    tf = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    tf[:2, :2] = [[c, -s], [s, c]]
    tf[:3, 3] = center
    return trimesh.creation.box(extents=size, transform=tf)


def seed_spread(seed: int) -> float:
    """A number in [0, 1) that covers the interval evenly over any few consecutive seeds (the
    golden-ratio sequence), so a family's seeds span its range of a parameter."""
    return (seed * 0.6180339887) % 1.0


def ground_plane(x0: float, x1: float, y0: float, y1: float, z: float = 0.0, cell: float = 0.0) -> trimesh.Trimesh:
    """A flat rectangle at height z, split into cells of about `cell` m (0: two triangles)."""
    nx = max(1, int(np.ceil((x1 - x0) / cell))) if cell > 0 else 1
    ny = max(1, int(np.ceil((y1 - y0) / cell))) if cell > 0 else 1
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    verts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])
    idx = np.arange(gx.size).reshape(nx + 1, ny + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return trimesh.Trimesh(verts, faces, process=False)


def cylinder(center_xy: tuple[float, float], radius: float, height: float, z0: float = 0.0) -> trimesh.Trimesh:
    """A vertical cylinder standing on z0."""
    tf = np.eye(4)
    tf[:3, 3] = (center_xy[0], center_xy[1], z0 + height / 2)
    return trimesh.creation.cylinder(radius=radius, height=height, sections=24, transform=tf)


def smooth_noise(
    rng: np.random.Generator, amplitude: float, wavelengths: tuple[float, float] = (1.5, 6.0), waves: int = 12
):
    """A smooth random scalar field R^3 -> R (sum of random plane waves), for rock-like walls."""
    dirs = rng.normal(size=(waves, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    k = dirs * (2 * np.pi / rng.uniform(*wavelengths, size=(waves, 1)))
    phase = rng.uniform(0, 2 * np.pi, size=waves)
    amp = amplitude / np.sqrt(waves / 2)

    def field(points: np.ndarray) -> np.ndarray:
        return amp * np.sin(points @ k.T + phase).sum(axis=1)

    return field


def polar_profile(kind: str, angles: np.ndarray, width: float, height: float) -> tuple[np.ndarray, float]:
    """Radius per angle around a centre height for a star-shaped tunnel cross-section.

    Returns (rho, centre_z); the floor is the line z = 0. `kind` is circular, horseshoe or
    rectangular. Polar form lets consecutive stations morph (tunnel into cavern) by
    interpolating rho.
    """
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        if kind == "circular":
            r = width / 2
            return np.full_like(angles, r), 0.45 * r
        if kind == "horseshoe":
            half, wall = width / 2, max(height - width / 2, 0.5)
            box_rho = np.minimum(half / np.abs(c), wall / np.abs(s))
            return np.where(s > 0, half, box_rho), wall
        if kind == "rectangular":
            half, hz = width / 2, height / 2
            return np.minimum(half / np.abs(c), hz / np.abs(s)), hz
    raise ValueError(f"unknown tunnel cross-section '{kind}' (circular, horseshoe, rectangular)")


def sweep(
    path: np.ndarray,
    angles: np.ndarray,
    rho: np.ndarray,
    centre_z: np.ndarray,
    noise=None,
    close_end: bool = False,
) -> trimesh.Trimesh:
    """Sweep a star-shaped cross-section along a ground poly-line into a tube.

    path (K,3) are floor points; rho (K,P) radii at `angles` (P,) around a centre centre_z (K,)
    above the floor; everything below the floor is flattened onto it, so the robot has ground.
    Cross-sections stay vertical (frames from the horizontal tangent), as real tunnels do.
    `noise` displaces the walls and roof (not the floor) radially.
    """
    path = np.asarray(path, dtype=np.float64)
    k, p = rho.shape
    tangent = np.gradient(path[:, :2], axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    left = np.column_stack([-tangent[:, 1], tangent[:, 0], np.zeros(k)])
    y_local = rho * np.cos(angles)[None, :]
    z_local = centre_z[:, None] + rho * np.sin(angles)[None, :]
    if noise is not None:
        base = path[:, None, :] + left[:, None, :] * y_local[..., None]
        base[..., 2] += z_local
        d = noise(base.reshape(-1, 3)).reshape(k, p)
        fade = np.clip(z_local / 0.6, 0.0, 1.0)  # keep the floor walkable
        y_local = y_local + d * fade * np.cos(angles)[None, :]
        z_local = z_local + d * fade * np.sin(angles)[None, :]
    z_local = np.maximum(z_local, 0.0)
    verts = path[:, None, :] + left[:, None, :] * y_local[..., None]
    verts[..., 2] += z_local
    idx = np.arange(k * p).reshape(k, p)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel(), nxt[:-1].ravel()
    faces = [np.column_stack([a, b, c]), np.column_stack([a, c, d])]
    verts = verts.reshape(-1, 3)
    if close_end:
        centre = path[-1] + np.array([0.0, 0.0, centre_z[-1]])
        verts = np.vstack([verts, centre])
        ring = idx[-1]
        faces.append(np.column_stack([ring, np.roll(ring, -1), np.full(p, len(verts) - 1)]))
    return trimesh.Trimesh(verts, np.concatenate(faces), process=False)


def resample_polyline(points: np.ndarray, spacing: float) -> np.ndarray:
    """Points along a poly-line every `spacing` metres (endpoints kept)."""
    points = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(np.ceil(s[-1] / spacing)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, points[:, i]) for i in range(points.shape[1])])


def polyline_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(np.asarray(points), axis=0), axis=1).sum())


def merge(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    mesh = trimesh.util.concatenate(parts)
    assert isinstance(mesh, trimesh.Trimesh)  # meshes joined are a mesh (trimesh types it as any geometry)
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
