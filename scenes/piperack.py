"""Pipe racks: open steel structures of columns, beams and long pipes over a plain, walked under.

The held-out family of the classifier's protocol: it is neither a tube, nor a room, nor a plain.
There are no walls; what holds the sensor is thin structure: columns every few metres (x), the
rows of columns and the long pipes (y, z, roll, pitch, yaw), the ground. Across seeds the bays run
from short (every axis held) to long and bare (x held by little more than the next column).
"""

from __future__ import annotations

import numpy as np
import trimesh

from .geometry import box, ground_plane, merge, resample_polyline, seed_spread
from .scene import Scene


def _pipe(x0: float, x1: float, y: float, z: float, radius: float) -> trimesh.Trimesh:
    """A horizontal pipe along x from x0 to x1 at (y, z)."""
    tf = np.eye(4)
    tf[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # the cylinder's z axis along world x
    tf[:3, 3] = ((x0 + x1) / 2, y, z)
    return trimesh.creation.cylinder(radius=radius, height=x1 - x0, sections=12, transform=tf)


def make_piperack(seed: int = 0, bay: float | None = None, length: float | None = None) -> Scene:
    """A rack `length` m along +x (40-90 m) whose column pairs stand every `bay` m. Unset, the bay
    spreads over 3-14 m across seeds (a golden-ratio sequence); width (4-9 m), tiers (1-3), pipes
    (2-10) and clutter on the ground are drawn from the seed."""
    rng = np.random.default_rng(seed + 7000)
    bay = bay or float(3.0 + seed_spread(seed) * 11.0)
    length = length or float(rng.uniform(40, 90))
    width = float(rng.uniform(4, 9))
    tiers = int(rng.integers(1, 4))
    tier_h = float(rng.uniform(3.0, 4.5))
    top = tiers * tier_h
    half = width / 2
    xs = np.arange(0.0, length + 1e-9, bay)
    parts = [ground_plane(-30, length + 30, -30, 30, cell=15)]
    for x in xs:
        for y in (-half, half):
            parts.append(box((x, y, top / 2), (0.3, 0.3, top)))  # columns
        for k in range(1, tiers + 1):
            parts.append(box((x, 0.0, k * tier_h), (0.25, width, 0.35)))  # cross beams
    for k in range(1, tiers + 1):
        for y in (-half, half):
            parts.append(box((length / 2, y, k * tier_h), (length, 0.2, 0.3)))  # longitudinal beams
    for _ in range(int(rng.integers(2, 11))):
        k = int(rng.integers(1, tiers + 1))
        r = float(rng.uniform(0.08, 0.4))
        parts.append(_pipe(0.0, length, float(rng.uniform(-half + 0.5, half - 0.5)), k * tier_h + 0.2 + r, r))
    # clutter beside the walkway: pumps, skids, valves (none on some seeds)
    for _ in range(int(rng.poisson(rng.uniform(0, 1.2) * length / 10))):
        side = rng.choice([-1, 1])
        parts.append(
            box(
                (rng.uniform(0, length), side * rng.uniform(1.5, half + 3), 0.5),
                (rng.uniform(0.5, 2.5), rng.uniform(0.5, 1.5), rng.uniform(0.5, 2.0)),
                yaw=rng.uniform(0, np.pi),
            )
        )
    route = resample_polyline(np.array([[0.0, 0.0, 0.0], [length, 0.0, 0.0]]), 1.0)
    return Scene(
        name=f"piperack-{seed}",
        mesh=merge(parts),
        sampling_paths=[route],
        start=np.array((0.0, 0.0, 0.0)),
        goal=route[-1, :2],
        routes={"main": route},
        family="piperack",
        seed=seed,
    )
