"""Chambers: large rock rooms, from smooth domes to blocky caverns.

In a round smooth room yaw slides and in a rough one nothing does; a model that has seen only
tubes and boxy rooms has no idea which, so training needs rooms on both sides of that line.
"""

from __future__ import annotations

import numpy as np

from .geometry import box, merge, resample_polyline, seed_spread, smooth_noise, sweep
from .scene import Scene


def make_chamber(seed: int = 0, roughness: float | None = None, radius: float | None = None) -> Scene:
    """A closed room along +x, `radius` m at its widest (6-16 m), its walls displaced by a smooth
    noise field of amplitude `roughness` (m). Unset, roughness spreads log-evenly over 0.03-1.2 m
    across seeds (a golden-ratio sequence)."""
    rng = np.random.default_rng(seed + 5000)
    if roughness is None:
        roughness = float(np.exp(np.log(0.03) + seed_spread(seed) * np.log(1.2 / 0.03)))
    radius = radius or float(rng.uniform(6, 16))
    length = float(rng.uniform(1.5, 3.0) * radius)
    s = np.arange(0.0, length + 1e-9, 0.5)
    angles = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    section = np.maximum(np.sin(np.pi * s / length) ** 0.5 * radius, 1.5)
    rho = np.tile(section[:, None], (1, len(angles)))
    rho *= 1 + 0.3 * np.cos(angles)[None, :] ** 2 * rng.uniform(-1, 0.5)  # low or tall vaults
    cz = 0.35 * section * rng.uniform(0.7, 1.3)
    path = np.column_stack([s, 0 * s, 0 * s])
    wall = sweep(path, angles, rho, cz, noise=smooth_noise(rng, roughness, wavelengths=(2.0, 10.0)), close_end=True)
    cap = box((-0.3, 0.0, 2.0), (0.6, 4.0, 4.0))  # the narrow start is closed too
    inner = (s > 0.15 * length) & (s < 0.85 * length)
    middle = length / 2
    paths = [
        resample_polyline(path[inner], 1.0),
        resample_polyline(np.array([[middle, -0.5 * radius, 0], [middle, 0.5 * radius, 0]]), 1.0),
    ]
    return Scene(
        name=f"chamber-{seed}",
        mesh=merge([wall, cap]),
        sampling_paths=paths,
        start=np.array((paths[0][0, 0], 0.0, 0.0)),
        goal=paths[0][-1, :2],
        routes={"main": paths[0]},
        family="chamber",
        seed=seed,
    )
