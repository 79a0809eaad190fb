"""Spinning LiDAR models: beam patterns, noise, dropout; points in the sensor frame."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import LidarConfig
from .raycast import RayCaster


@dataclass(frozen=True)
class BeamPattern:
    """Elevation angles (deg) of the beams and azimuth steps per revolution."""

    name: str
    elevations_deg: tuple[float, ...]
    n_azimuth: int
    max_range: float
    min_range: float
    image_width: int  # default width of the range image in observations

    @property
    def n_beams(self) -> int:
        return len(self.elevations_deg)

    def directions(self) -> np.ndarray:
        """Unit ray directions (B*A, 3) in the sensor frame, beam-major."""
        el = np.deg2rad(np.asarray(self.elevations_deg))[:, None]
        az = (2 * np.pi * np.arange(self.n_azimuth) / self.n_azimuth)[None, :]
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], axis=-1)
        return d.reshape(-1, 3).astype(np.float32)


PATTERNS: dict[str, BeamPattern] = {
    # Velodyne VLP-16: 16 beams over +-15 deg, 0.2 deg azimuth at 10 Hz, 100 m.
    "vlp16": BeamPattern("vlp16", tuple(np.linspace(-15, 15, 16)), 1800, 100.0, 0.5, 360),
    # Ouster OS0-128: 128 beams over +-45 deg, 1024 columns at 10 Hz, 50 m (datasheet, 80 % targets).
    "os0-128": BeamPattern("os0-128", tuple(np.linspace(-45, 45, 128)), 1024, 50.0, 0.3, 256),
}


def register_pattern(pattern: BeamPattern) -> None:
    """Add a user-defined beam pattern, usable by name in LidarConfig.model."""
    if pattern.n_beams < 1 or pattern.n_azimuth < 1 or not pattern.max_range > pattern.min_range >= 0:
        raise ValueError(f"invalid beam pattern {pattern}")
    PATTERNS[pattern.name] = pattern


def get_pattern(name: str) -> BeamPattern:
    if name not in PATTERNS:
        raise ValueError(f"unknown LiDAR model '{name}'; known: {sorted(PATTERNS)}")
    return PATTERNS[name]


@dataclass
class Scan:
    """Points (float32, N x 3) in the sensor frame, with the beam and column of each point."""

    points: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    pattern: BeamPattern

    def __len__(self) -> int:
        return len(self.points)

    def range_image(self, width: int | None = None) -> np.ndarray:
        """(beams, width) float32 ranges; 0 where there is no return. Columns are pooled by the
        nearest return, so a thin obstacle is not lost when the image is narrower than the scan."""
        width = width or self.pattern.image_width
        if self.pattern.n_azimuth % width:
            raise ValueError(f"range image width {width} must divide {self.pattern.n_azimuth} columns")
        k = self.pattern.n_azimuth // width
        full = np.full(self.pattern.n_beams * self.pattern.n_azimuth, np.inf, dtype=np.float32)
        # each (beam, column) holds at most one return, so a plain scatter suffices
        full[self.beam.astype(np.int64) * self.pattern.n_azimuth + self.column] = np.linalg.norm(self.points, axis=1)
        img = full.reshape(self.pattern.n_beams, width, k).min(axis=2)
        img[np.isinf(img)] = 0.0
        return img


class Lidar:
    """Casts one revolution from a sensor pose with a RayCaster backend."""

    def __init__(self, caster: RayCaster, config: LidarConfig | None = None):
        self.config = config or LidarConfig()
        self.pattern = get_pattern(self.config.model)
        self.caster = caster
        self.max_range = self.config.max_range or self.pattern.max_range
        self.min_range = self.pattern.min_range if self.config.min_range is None else self.config.min_range
        self._dirs = self.pattern.directions()
        idx = np.arange(len(self._dirs))
        beam, column = np.divmod(idx, self.pattern.n_azimuth)
        self._beam, self._column = beam.astype(np.int16), column.astype(np.int16)

    def scan(self, T_w_s: np.ndarray, rng: np.random.Generator | None = None) -> Scan:
        """Scan from sensor pose T_w_s. Noise and dropout need `rng`; without it the scan is exact."""
        T_w_s = np.asarray(T_w_s, dtype=np.float64)
        if T_w_s.shape != (4, 4) or not np.isfinite(T_w_s).all():
            raise ValueError("sensor pose must be a finite 4x4 matrix")
        dirs_w = self._dirs @ T_w_s[:3, :3].T.astype(np.float32)
        r = self.caster.cast(T_w_s[:3, 3], dirs_w, self.max_range)
        keep = np.isfinite(r)
        if rng is not None and self.config.dropout > 0:
            keep &= rng.random(r.shape, dtype=np.float32) >= self.config.dropout
        idx = np.flatnonzero(keep)
        r = r[idx]
        if rng is not None and self.config.range_noise_std > 0:
            r += self.config.range_noise_std * rng.standard_normal(len(r), dtype=np.float32)
        inside = (r >= self.min_range) & (r < self.max_range)
        if not inside.all():
            idx, r = idx[inside], r[inside]
        points = np.take(self._dirs, idx, axis=0)  # np.take: about 2x faster than fancy indexing here
        points *= r[:, None]
        return Scan(points, np.take(self._beam, idx), np.take(self._column, idx), self.pattern)
