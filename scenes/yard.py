"""Yards: open ground with buildings, containers, walls and tanks, from nearly empty to dense.

An open plane is the textbook non-localizable place, and a model that has only seen empty fields
learns "much ground = degenerate". Whether x, y and yaw are constrained depends on how many
distinct structures are in range, so training needs open ground on both sides of that line.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .geometry import box, cylinder, ground_plane, merge, resample_polyline, seed_spread
from .scene import Scene


def _structure(rng: np.random.Generator, centre: np.ndarray, yaw: float) -> tuple[trimesh.Trimesh, float]:
    """One structure at `centre` and its footprint radius."""
    kind = rng.choice(["building", "container", "wall", "tank"], p=[0.35, 0.3, 0.2, 0.15])
    if kind == "building":
        size = (rng.uniform(4, 12), rng.uniform(3, 8), rng.uniform(3, 8))
    elif kind == "container":
        size = (6.1, 2.4, 2.6 * int(rng.integers(1, 3)))
    elif kind == "wall":
        size = (rng.uniform(8, 25), 0.3, rng.uniform(1.5, 3.0))
    else:
        radius, height = rng.uniform(1.0, 3.0), rng.uniform(3.0, 8.0)
        return cylinder((centre[0], centre[1]), radius, height), radius
    return box((centre[0], centre[1], size[2] / 2), size, yaw=yaw), float(np.hypot(size[0], size[1]) / 2)


def make_yard(seed: int = 0, structures: int | None = None, radius: float | None = None) -> Scene:
    """A 240 m plane with `structures` objects within `radius` m of the origin. Unset, the count
    spreads evenly over 3-30 across seeds (a golden-ratio sequence). A straight lane along y = 0
    leads out of the yard into the open, and a loop circles inside it; both are kept clear."""
    rng = np.random.default_rng(seed + 4000)
    structures = structures if structures is not None else int(round(3 + 27 * seed_spread(seed)))
    radius = radius or float(rng.uniform(15, 35))
    lane = resample_polyline(np.array([[-radius, 0.0, 0.0], [radius + 50.0, 0.0, 0.0]]), 1.0)
    t = np.linspace(0, 2 * np.pi, 40)
    loop = np.column_stack([0.5 * radius * np.cos(t), 0.5 * radius * np.sin(t), 0 * t])
    keep_clear = np.vstack([lane, resample_polyline(loop, 1.0)])[:, :2]
    grid_yaw = rng.uniform(0, np.pi / 2)
    parts = [ground_plane(-120, 120, -120, 120, cell=40)]
    for _ in range(20 * structures):
        if len(parts) > structures:
            break
        centre = rng.uniform(-radius, radius, 2)
        yaw = grid_yaw + rng.integers(2) * np.pi / 2 + rng.normal(0, 0.05)
        mesh, footprint = _structure(rng, centre, yaw)
        if np.min(np.linalg.norm(keep_clear - centre, axis=1)) > footprint + 2.0:
            parts.append(mesh)
    return Scene(
        name=f"yard-{seed}",
        mesh=merge(parts),
        sampling_paths=[lane, loop],
        start=np.array((lane[0, 0], lane[0, 1], 0.0)),
        goal=lane[-1, :2],
        routes={"main": lane},
        family="yard",
        seed=seed,
    )
