"""Fork: two ways from start to goal, a short featureless corridor and a longer rich route."""

from __future__ import annotations

import numpy as np

from .geometry import box, cylinder, ground_plane, merge, resample_polyline
from .scene import Scene


def make_fork(seed: int = 0, corridor_length: float | None = None, detour: float | None = None) -> Scene:
    """Start at the origin facing +x, goal straight ahead. The 'short' route runs through a
    smooth roofed corridor (degenerate along x); the 'rich' route loops around it at y = detour,
    past pillars and boxes."""
    rng = np.random.default_rng(seed + 4000)
    length = corridor_length or (50.0 if seed == 0 else float(rng.uniform(40, 60)))
    detour = detour or (10.0 if seed == 0 else float(rng.uniform(8, 12)))
    x0, x1, half, h = 5.0, 5.0 + length, 1.5, 3.0
    gx = x1 + 5.0
    parts = [ground_plane(-10, gx + 10, -15, detour + 10, cell=10)]
    for sign in (-1, 1):  # the smooth corridor: walls and roof
        parts.append(box(((x0 + x1) / 2, sign * (half + 0.1), h / 2), (length, 0.2, h)))
    parts.append(box(((x0 + x1) / 2, 0, h + 0.1), (length, 2 * half + 0.4, 0.2)))
    # outer boundary walls
    parts.append(box(((gx - 10) / 2 + 5, detour + 6, 1.5), (gx + 20, 0.3, 3.0)))
    parts.append(box(((gx - 10) / 2 + 5, -8, 1.5), (gx + 20, 0.3, 3.0)))
    # the rich route's geometry: pillars and boxes on both sides of y = detour
    for x in np.arange(x0, x1, 4.0):
        for side in (-1, 1):
            y = detour + side * rng.uniform(2.5, 4.0)
            if rng.random() < 0.5:
                parts.append(cylinder((x + rng.uniform(-1, 1), y), rng.uniform(0.2, 0.5), rng.uniform(1.5, 3.0)))
            else:
                centre = (x + rng.uniform(-1, 1), y, 0.75)  # draws in this order: centre, size, yaw
                size = tuple(rng.uniform(0.6, 1.8, 2)) + (1.5,)
                parts.append(box(centre, size, yaw=rng.uniform(0, np.pi)))
    short = resample_polyline(np.array([[0.0, 0, 0], [gx, 0, 0]]), 1.0)
    corners = [[0.0, 0, 0], [2.0, 0, 0], [2.0, detour, 0], [gx - 2, detour, 0], [gx - 2, 0, 0], [gx, 0, 0]]
    rich = resample_polyline(np.array(corners), 1.0)
    return Scene.two_ways(
        f"fork-{seed}", merge(parts), short, rich, "fork", seed, {"corridor": np.array([x0, -half, x1, half])}
    )
