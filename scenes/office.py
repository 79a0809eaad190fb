"""Office floor: a corridor with rooms behind doors and an open hall; mostly localizable."""

from __future__ import annotations

import numpy as np

from .geometry import box, ground_plane, merge, resample_polyline
from .scene import Scene

WALL = 0.12
HEIGHT = 2.8


def _wall_with_doors(x0: float, x1: float, y: float, doors: list[float], door_width: float = 1.0) -> list:
    """A wall along x at height y from x0 to x1 with door gaps centred at `doors`."""
    parts, cursor = [], x0
    for d in sorted(doors) + [x1 + door_width / 2]:
        end = min(d - door_width / 2, x1)
        if end - cursor > 0.05:
            parts.append(box(((cursor + end) / 2, y, HEIGHT / 2), (end - cursor, WALL, HEIGHT)))
        cursor = d + door_width / 2
    return parts


def make_office(seed: int = 0, rooms_per_side: int | None = None) -> Scene:
    """Corridor along +x (2 m wide), rooms on both sides with doors, an open hall at the end."""
    rng = np.random.default_rng(seed)
    n = rooms_per_side or (5 if seed == 0 else int(rng.integers(3, 7)))
    widths = rng.uniform(3.5, 5.5, size=(2, n)) if seed else np.full((2, n), 4.5)
    depth = 5.0 if seed == 0 else float(rng.uniform(4.0, 6.0))
    half_corr = 1.0
    length = float(max(widths.sum(axis=1)))
    hall = 12.0
    parts = [ground_plane(-1, length + hall, -depth - 1, depth + 1 + hall / 2, cell=5.0)]
    ceiling = ground_plane(-1, length + hall, -depth - 1, depth + 1 + hall / 2, z=HEIGHT, cell=5.0)
    parts.append(ceiling)
    room_centres = []
    for side, sign in ((0, 1.0), (1, -1.0)):
        edges = np.concatenate([[0.0], np.cumsum(widths[side])])
        doors = list((edges[:-1] + edges[1:]) / 2 + rng.uniform(-0.8, 0.8, size=n))
        parts += _wall_with_doors(0.0, length, sign * half_corr, doors)
        parts.append(box((length / 2, sign * (half_corr + depth), HEIGHT / 2), (length, WALL, HEIGHT)))
        for e in edges:  # partition walls between rooms
            parts.append(box((e, sign * (half_corr + depth / 2), HEIGHT / 2), (WALL, depth, HEIGHT)))
        for x0, x1, dx in zip(edges[:-1], edges[1:], doors):
            room_centres.append((dx, sign * half_corr, (x0 + x1) / 2, sign * (half_corr + depth / 2)))
            if rng.random() < 0.7:  # furniture
                parts.append(box(((x0 + x1) / 2 + 0.8, sign * (half_corr + depth - 0.6), 0.4), (1.6, 0.8, 0.8)))
    parts.append(box((-0.5, 0, HEIGHT / 2), (WALL, 2 * half_corr, HEIGHT)))  # corridor end wall
    # hall: walls around an open area at the end of the corridor
    hx0, hx1, hy = length, length + hall, hall / 2
    parts.append(box((hx1, 0, HEIGHT / 2), (WALL, 2 * hy, HEIGHT)))
    for sign in (1.0, -1.0):
        parts.append(box(((hx0 + hx1) / 2, sign * hy, HEIGHT / 2), (hall, WALL, HEIGHT)))
        parts.append(box((hx0, sign * (half_corr + hy) / 2 + sign * 0.0, HEIGHT / 2), (WALL, hy - half_corr, HEIGHT)))
    for _ in range(3):  # pillars / desks in the hall
        parts.append(box((rng.uniform(hx0 + 3, hx1 - 2), rng.uniform(-hy + 2, hy - 2), 0.5), (1.0, 1.0, 1.0)))
    route = resample_polyline(np.array([[0.5, 0, 0], [length, 0, 0], [length + hall / 2, 0.0, 0]]), 1.0)
    paths = [route] + [
        resample_polyline(np.array([[dx, 0.0, 0], [dx, ry, 0], [rx, ry, 0]]), 1.0) for dx, _, rx, ry in room_centres
    ]
    return Scene(
        name=f"office-{seed}",
        mesh=merge(parts),
        sampling_paths=paths,
        start=np.array((route[0, 0], route[0, 1], 0.0)),
        goal=route[-1, :2],
        routes={"main": route},
        family="office",
        seed=seed,
    )
