"""Open field: a large flat plane; x, y and yaw are unobservable away from structures."""

from __future__ import annotations

import numpy as np

from .geometry import box, cylinder, ground_plane, merge, resample_polyline
from .scene import Scene


def make_field(seed: int = 0, size: float = 300.0, structures: int | None = None, canopy: bool | None = None) -> Scene:
    """A `size` x `size` m plane; a few structures (and optionally a tree canopy) near the start,
    so the start is localizable and the open part beyond it is not."""
    rng = np.random.default_rng(seed)
    structures = 3 if structures is None and seed == 0 else structures
    structures = int(rng.integers(0, 5)) if structures is None else structures
    canopy = bool(rng.random() < 0.4) if canopy is None else canopy
    half = size / 2
    parts = [ground_plane(-half, half, -half, half, cell=size / 6)]
    for _ in range(structures):
        cx, cy = rng.uniform(-14, -4), rng.uniform(-8, 8)
        if abs(cy) < 2.0:
            cy = 2.0 * np.sign(cy + 1e-9) + cy
        parts.append(box((cx, cy, 1.25), (rng.uniform(1, 4), rng.uniform(1, 4), 2.5), yaw=rng.uniform(0, np.pi)))
    if canopy:
        for _ in range(8):
            cx, cy = rng.uniform(-15, 0), rng.choice([-1, 1]) * rng.uniform(3, 10)
            parts.append(cylinder((cx, cy), 0.25, 4.0))
            parts.append(cylinder((cx, cy), 2.0, 1.0, z0=4.0))
    route = resample_polyline(np.array([[0.0, 0.0, 0.0], [80.0, 0.0, 0.0]]), 1.0)
    return Scene(
        name=f"field-{seed}",
        mesh=merge(parts),
        sampling_paths=[route, np.array([[-15.0, 0, 0], [0.0, 0, 0]])],
        start=np.array((0.0, 0.0, 0.0)),
        goal=route[-1, :2],
        routes={"main": route},
        family="field",
        seed=seed,
    )
