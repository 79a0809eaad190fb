"""Procedural layouts: random compositions of the parts that decide localizability, for training.

Each seed draws a winding walk and furnishes the space around it from a pool of parts: ground
(flat, tilted or rolling), walls and fences along or across the walk, boxes from crates to
buildings, pillars and trees, rock blobs, a ceiling, and sometimes a stretch of tunnel (smooth or
rough, of any profile) that the walk runs through. How many of each, how big, how far and how
regular are drawn too, so that the seeds span open plains, corridors, forests, yards, halls and
tubes and every mixture of them: geometry varied enough that a model learns what the parts
constrain rather than which family a scan comes from.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from .geometry import box, cylinder, merge, polar_profile, resample_polyline, smooth_noise, sweep
from .scene import Scene

PROFILES = ("circular", "horseshoe", "rectangular")


def walk_legs(rng: np.random.Generator) -> np.ndarray:
    """A ground poly-line of 3-5 straight legs of 8-25 m, turning by up to 70 deg between legs."""
    heading, point, points = float(rng.uniform(-np.pi, np.pi)), np.zeros(2), [np.zeros(2)]
    for _ in range(int(rng.integers(3, 6))):
        heading += float(rng.uniform(-1.2, 1.2))
        point = point + rng.uniform(8, 25) * np.array([np.cos(heading), np.sin(heading)])
        points.append(point)
    xy = np.array(points)
    return resample_polyline(np.column_stack([xy, np.zeros(len(xy))]), 0.5)


def ground_surface(
    rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray
) -> tuple[trimesh.Trimesh, Callable[[np.ndarray], np.ndarray]]:
    """A ground grid over the box lo-hi that is flat, gently tilted or rolling; and its height at (x, y)."""
    kind = rng.choice(["flat", "tilted", "rolling"], p=[0.5, 0.2, 0.3])
    slope = rng.uniform(-0.08, 0.08, 2) if kind == "tilted" else np.zeros(2)
    bumps = smooth_noise(rng, float(rng.uniform(0.1, 0.6)), wavelengths=(4.0, 15.0)) if kind == "rolling" else None

    def height(xy: np.ndarray) -> np.ndarray:
        xy = np.atleast_2d(xy)
        h = xy @ slope
        if bumps is not None:
            h = h + bumps(np.column_stack([xy, np.zeros(len(xy))]))
        return h

    xs, ys = np.arange(lo[0], hi[0] + 1e-9, 2.0), np.arange(lo[1], hi[1] + 1e-9, 2.0)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    verts = np.column_stack([xy, height(xy)])
    idx = np.arange(len(xy)).reshape(len(xs), len(ys))
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return trimesh.Trimesh(verts, faces, process=False), height


def clear_of(walk: np.ndarray, xy: np.ndarray, radius: float) -> bool:
    """Whether a footprint of `radius` around xy stays 1.2 m clear of the walk."""
    return bool(np.min(np.linalg.norm(walk[:, :2] - xy, axis=1)) > radius + 1.2)


def keeps_clear(part: trimesh.Trimesh, walk: np.ndarray, height) -> bool:
    """Whether the part's surface lower than 2.5 m over the ground stays 1 m clear of the walk (a tree's
    crown or a rock's bulge may reach further than its footprint, a long wall cross the walk between
    the points its placement checked): its vertices and points sampled over it, every 0.25 m or so."""
    count = int(min(4000, max(50, part.area / 0.06)))
    v = np.vstack([part.vertices, trimesh.sample.sample_surface(part, count, seed=0)[0]])
    low = v[v[:, 2] - height(v[:, :2]) < 2.5]
    if not len(low):
        return True
    gap = np.linalg.norm(low[:, None, :2] - walk[None, ::2, :2], axis=2).min()
    return bool(gap > 1.0)


def beside(rng: np.random.Generator, walk: np.ndarray, near: float, far: float) -> tuple[np.ndarray, float]:
    """A point `near`-`far` m to the side of a random station of the walk, and the walk's heading there."""
    k = int(rng.integers(1, len(walk) - 1))
    d = walk[k + 1, :2] - walk[k - 1, :2]
    heading = float(np.arctan2(d[1], d[0]))
    side = np.array([-np.sin(heading), np.cos(heading)]) * rng.choice([-1, 1])
    return walk[k, :2] + side * rng.uniform(near, far), heading


def piece(rng: np.random.Generator, kind: str, xy: np.ndarray, heading: float, z0: float, walk: np.ndarray) -> list:
    """One piece of furniture of `kind` at `xy` (none where it would stand on the walk)."""
    out: list[trimesh.Trimesh] = []
    if kind == "box":
        size = rng.uniform(0.4, 1.0, 3) * rng.choice([1.5, 4.0, 12.0])
        if clear_of(walk, xy, 0.5 * float(np.hypot(size[0], size[1]))):
            out.append(box((xy[0], xy[1], z0 + size[2] / 2), tuple(size), yaw=float(rng.uniform(0, np.pi))))
    elif kind in ("pillar", "tree"):
        r = float(rng.uniform(0.1, 0.6)) if kind == "pillar" else float(rng.uniform(0.1, 0.3))
        h = float(rng.uniform(2.5, 8.0))
        if clear_of(walk, xy, r if kind == "pillar" else 2.0):
            out.append(cylinder((xy[0], xy[1]), r, h, z0=z0))
            if kind == "tree":
                crown = trimesh.creation.icosphere(1, radius=float(rng.uniform(1.0, 2.5)))
                out.append(crown.apply_translation((xy[0], xy[1], z0 + h)))
    elif kind == "rock":
        r = float(rng.uniform(0.3, 3.0))
        if clear_of(walk, xy, r * 1.3):
            rock = trimesh.creation.icosphere(2, radius=r)
            rock.vertices *= 1 + 0.25 * rng.standard_normal((len(rock.vertices), 1))
            out.append(rock.apply_translation((xy[0], xy[1], z0 + 0.3)))
    else:  # a wall along the walk (parallel: the corridor kind) or at an angle to it
        along = rng.random() < 0.6
        wall_len = float(rng.uniform(5, 40))
        yaw = heading if along else heading + float(rng.uniform(0.3, np.pi - 0.3))
        centre = xy + wall_len / 2 * np.array([np.cos(yaw), np.sin(yaw)]) * (0 if along else 1)
        ends = centre + np.outer([-0.5, 0.5], [np.cos(yaw), np.sin(yaw)]) * wall_len
        samples = ends[0] + np.linspace(0, 1, 12)[:, None] * (ends[1] - ends[0])
        if all(clear_of(walk, p, 0.3) for p in samples):
            h = float(rng.uniform(1.0, 6.0))
            out.append(box((centre[0], centre[1], z0 + h / 2), (wall_len, 0.3, h), yaw=yaw))
    return out


def _tunnel_stretch(rng: np.random.Generator, walk: np.ndarray) -> trimesh.Trimesh:
    """A stretch of tunnel of random profile and roughness along 20-60 m of the walk."""
    a = int(rng.integers(0, len(walk) // 2))
    b = min(len(walk), a + int(rng.uniform(20, 60) / 0.5))
    stretch = walk[a:b]
    width = float(rng.uniform(3.0, 8.0))
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    rho, cz = polar_profile(str(rng.choice(PROFILES)), angles, width, float(rng.uniform(3.0, 6.0)))
    roughness = float(np.exp(rng.uniform(np.log(0.01), np.log(0.8))))
    noise = smooth_noise(rng, roughness, wavelengths=(1.0, 6.0))
    return sweep(stretch, angles, np.tile(rho, (len(stretch), 1)), np.full(len(stretch), cz), noise=noise)


def make_layout(seed: int = 0) -> Scene:
    """One procedural layout (see the module's text); the walk is its route and sampling path."""
    rng = np.random.default_rng(seed + 9000)
    walk = walk_legs(rng)
    lo, hi = walk[:, :2].min(axis=0) - 35, walk[:, :2].max(axis=0) + 35
    ground, height = ground_surface(rng, lo, hi)
    walk[:, 2] = height(walk[:, :2])
    parts = [ground]
    spread = float(np.exp(rng.uniform(np.log(2.0), np.log(25.0))))  # how far from the walk the furniture stands
    density = float(rng.choice([0.0, 1.0, 3.0, 8.0], p=[0.1, 0.25, 0.35, 0.3]))  # parts per 10 m of walk
    length = float(np.linalg.norm(np.diff(walk[:, :2], axis=0), axis=1).sum())
    regular = rng.random() < 0.4  # evenly spaced rows (a colonnade, a fence) or scattered
    furniture: list[trimesh.Trimesh] = []
    for i in range(int(rng.poisson(density * length / 10))):
        kind = rng.choice(["box", "pillar", "tree", "rock", "wall"], p=[0.3, 0.2, 0.15, 0.15, 0.2])
        if regular:
            k = int((i * 7) % max(len(walk) - 2, 1)) + 1
            d = walk[k + 1, :2] - walk[k - 1, :2]
            heading = float(np.arctan2(d[1], d[0]))
            xy = walk[k, :2] + np.array([-np.sin(heading), np.cos(heading)]) * (spread / 2 + 1.5) * (-1) ** i
        else:
            xy, heading = beside(rng, walk, 1.5, 1.5 + spread)
        z0 = float(height(xy)[0]) - 0.3  # sunk a little: rolling ground leaves no gap beneath
        furniture += piece(rng, str(kind), xy, heading, z0, walk)
    parts += [part for part in furniture if keeps_clear(part, walk, height)]
    if rng.random() < 0.25:  # a ceiling over the whole walk: a hall
        z = float(rng.uniform(3.0, 8.0))
        parts.append(box(((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, z + 0.1), (hi[0] - lo[0], hi[1] - lo[1], 0.2)))
    if rng.random() < 0.35:  # a stretch of tunnel that the walk runs through
        parts.append(_tunnel_stretch(rng, walk))
    route = resample_polyline(walk, 1.0)
    return Scene.along_route(f"layout-{seed}", merge(parts), route, "layout", seed)
