"""Long smooth tunnels: the textbook case of a non-localizable axis along the tunnel."""

from __future__ import annotations

import numpy as np

from .geometry import polar_profile, resample_polyline, sweep
from .scene import Scene

PROFILES = ("circular", "horseshoe", "rectangular")


def make_tunnel(
    seed: int = 0,
    profile: str | None = None,
    length: float | None = None,
    width: float | None = None,
    height: float | None = None,
    bend_deg: float = 0.0,
) -> Scene:
    """A tunnel along +x starting at the origin. Unset parameters are drawn from the seed
    (seed 0 gives the reference: a 120 m horseshoe tunnel, 4.5 m wide)."""
    rng = np.random.default_rng(seed)
    if seed == 0:
        profile, length, width, height = profile or "horseshoe", length or 120.0, width or 4.5, height or 4.5
    profile = profile or PROFILES[int(rng.integers(len(PROFILES)))]
    length = length or float(rng.uniform(80, 150))
    width = width or float(rng.uniform(3.0, 6.0))
    height = height or float(np.clip(width * rng.uniform(0.8, 1.1), 3.0, 6.0))
    if profile not in PROFILES:
        raise ValueError(f"unknown tunnel cross-section '{profile}' (choose from {PROFILES})")
    s = np.linspace(0, length, int(length / 1.0) + 1)
    heading = np.deg2rad(bend_deg) * (s / length)
    xy = np.column_stack([np.cumsum(np.cos(heading)) * (s[1] - s[0]), np.cumsum(np.sin(heading)) * (s[1] - s[0])])
    xy -= xy[0]
    path = np.column_stack([xy, np.zeros(len(s))])
    angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rho, cz = polar_profile(profile, angles, width, height)
    mesh = sweep(path, angles, np.tile(rho, (len(s), 1)), np.full(len(s), cz))
    inner = path[(s > 5) & (s < length - 5)]
    route = resample_polyline(inner, 1.0)
    return Scene.along_route(f"tunnel-{seed}", mesh, route, "tunnel", seed)
