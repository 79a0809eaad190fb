"""Caves: noise-displaced tubes whose radius swells into chambers."""

from __future__ import annotations

import numpy as np

from .geometry import resample_polyline, smooth_noise, sweep
from .scene import Scene


def _wander(
    rng: np.random.Generator, length: float, step: float = 1.0, turn: float = 0.08, slope: float = 0.06
) -> np.ndarray:
    """A smooth random ground path: heading and grade follow filtered random walks."""
    n = int(length / step) + 1
    heading = np.cumsum(np.convolve(rng.normal(0, turn, n), np.ones(8) / 8, mode="same"))
    grade = np.clip(np.convolve(rng.normal(0, slope, n), np.ones(15) / 15, mode="same") * 3, -0.15, 0.15)
    d = np.column_stack([np.cos(heading), np.sin(heading), grade]) * step
    d[0] = 0
    return np.cumsum(d, axis=0)


def make_cave(seed: int = 0, length: float | None = None, chambers: int | None = None) -> Scene:
    """A winding cave passage (radius 1.6-3 m) with a few chambers (radius up to ~9 m)."""
    rng = np.random.default_rng(seed + 1000)
    length = length or float(rng.uniform(70, 120))
    chambers = chambers if chambers is not None else int(rng.integers(1, 4))
    path = _wander(rng, length)
    s = np.arange(len(path), dtype=np.float64)
    base = rng.uniform(1.6, 3.0)
    radius = base * (1 + 0.15 * np.sin(s / rng.uniform(4, 9) + rng.uniform(0, 6)))
    for c in rng.uniform(0.2, 0.85, size=chambers) * s[-1]:
        radius += rng.uniform(3, 6) * np.exp(-0.5 * ((s - c) / rng.uniform(3, 6)) ** 2)
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    rho = np.tile(radius[:, None], (1, len(angles)))
    rho *= 1 + 0.25 * np.cos(angles)[None, :] ** 2 * rng.uniform(-1, 1)  # flattened or tall sections
    mesh = sweep(path, angles, rho, 0.4 * radius, noise=smooth_noise(rng, 0.35 * base), close_end=True)
    route = resample_polyline(path[4:-4], 1.0)
    return Scene.along_route(f"cave-{seed}", mesh, route, "cave", seed)
