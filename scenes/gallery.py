"""Rock galleries: engineered tunnels whose walls keep the roughness of the rock, from nearly
smooth (shotcrete) to blocky (fresh drill-and-blast). Roughness is what decides whether ICP can
slide along a tunnel, so training needs tunnels on both sides of that line, not only smooth ones.
"""

from __future__ import annotations

import numpy as np

from .geometry import polar_profile, resample_polyline, seed_spread, smooth_noise, sweep
from .scene import Scene
from .tunnel import PROFILES


def make_gallery(seed: int = 0, roughness: float | None = None, length: float | None = None) -> Scene:
    """A gently bending tunnel with wall roughness `roughness` (m, amplitude of the smooth noise
    field on 1-5 m wavelengths). Unset, it spreads log-evenly over 0.02-0.5 m across seeds (a
    golden-ratio sequence), so any few consecutive seeds cover smooth and rough walls."""
    rng = np.random.default_rng(seed + 2000)
    if roughness is None:
        roughness = float(np.exp(np.log(0.02) + seed_spread(seed) * np.log(0.5 / 0.02)))
    length = length or float(rng.uniform(60, 110))
    profile = PROFILES[int(rng.integers(len(PROFILES)))]
    width = float(rng.uniform(3.0, 6.0))
    height = float(np.clip(width * rng.uniform(0.8, 1.1), 3.0, 6.0))
    s = np.linspace(0, length, int(length / 0.5) + 1)
    heading = np.deg2rad(rng.uniform(-25, 25)) * np.sin(np.pi * s / length * rng.uniform(0.5, 1.5))
    xy = np.column_stack([np.cumsum(np.cos(heading)), np.cumsum(np.sin(heading))]) * (s[1] - s[0])
    path = np.column_stack([xy - xy[0], np.zeros(len(s))])
    angles = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    rho, cz = polar_profile(profile, angles, width, height)
    noise = smooth_noise(rng, roughness, wavelengths=(1.0, 5.0), waves=16)
    mesh = sweep(path, angles, np.tile(rho, (len(s), 1)), np.full(len(s), cz), noise=noise)
    route = resample_polyline(path[(s > 5) & (s < length - 5)], 1.0)
    return Scene.along_route(f"gallery-{seed}", mesh, route, "gallery", seed)
