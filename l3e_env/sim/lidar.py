"""Spinning LiDAR models: beam patterns, noise, dropout; points in the sensor frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from l3e_env.config import LidarConfig
from l3e_env.core.threads import one_blas_thread
from l3e_env.core.transforms import inverse

from .patterns import PATTERNS, BeamPattern, get_pattern, register_pattern
from .raycast import RayCaster

__all__ = ["PATTERNS", "BeamPattern", "Lidar", "Scan", "get_pattern", "register_pattern"]


@dataclass
class Scan:
    """Points (float32, N x 3) in the sensor frame, with the beam and column of each point; for a
    swept revolution, each point's time (float32 s) since the revolution began, its point in the
    sensor frame of that moment, as a driver writes it."""

    points: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    pattern: BeamPattern
    times: np.ndarray | None = None

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

    def __init__(self, caster: RayCaster, config: LidarConfig | None = None, pattern: BeamPattern | None = None):
        """`pattern`: beams to cast in place of the config's model's (a thinned revolution, say)."""
        self.config = config or LidarConfig()
        self.pattern = pattern or get_pattern(self.config.model)
        self.caster = caster
        self.max_range = self.config.max_range or self.pattern.max_range
        self.min_range = self.pattern.min_range if self.config.min_range is None else self.config.min_range
        self._dirs = self.pattern.directions()
        self._origins = self.pattern.origins()  # None: every ray leaves the sensor's origin
        idx = np.arange(len(self._dirs))
        beam, column = np.divmod(idx, self.pattern.n_azimuth)
        self._beam, self._column = beam.astype(np.int16), column.astype(np.int16)
        self._firing = self.pattern.firing_share(self._dirs)

    def scan(
        self,
        T_w_s: np.ndarray,
        rng: np.random.Generator | None = None,
        start: np.ndarray | None = None,
        period: float = 0.1,
    ) -> Scan:
        """Scan from sensor pose T_w_s. Noise and dropout need `rng`; without it the scan is exact.

        `start`: the sensor's pose when the revolution began, `period` seconds before T_w_s. Each
        ray is then cast from the pose at its firing time (rotation slerped, position linear
        between the two), and the scan carries each point's time since `start`."""
        T_w_s = np.asarray(T_w_s, dtype=np.float64)
        if T_w_s.shape != (4, 4) or not np.isfinite(T_w_s).all():
            raise ValueError("sensor pose must be a finite 4x4 matrix")
        with one_blas_thread():  # a 131k x 3 product starts BLAS threads that spin on a busy machine
            if start is None:
                dirs_w = self._dirs @ T_w_s[:3, :3].T.astype(np.float32)
                origin = T_w_s[:3, 3] if self._origins is None else self._origins @ T_w_s[:3, :3].T + T_w_s[:3, 3]
            else:
                dirs_w, origin = self._swept_rays(np.asarray(start, dtype=np.float64), T_w_s, period)
        r = self.caster.cast(origin, dirs_w, self.max_range)
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
        if self._origins is not None:
            points += np.take(self._origins, idx, axis=0)
        times = None if start is None else (np.take(self._firing, idx) * period).astype(np.float32)
        return Scan(points, np.take(self._beam, idx), np.take(self._column, idx), self.pattern, times)

    def _swept_rays(self, start: np.ndarray, end: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
        """World directions and origins of every ray, each from the pose at its firing time."""
        if start.shape != (4, 4) or not np.isfinite(start).all():
            raise ValueError("the revolution's start pose must be a finite 4x4 matrix")
        if not period > 0:
            raise ValueError(f"a revolution lasts a positive time, not {period} s")
        turn = Rotation.from_matrix(start[:3, :3].T @ end[:3, :3]).as_rotvec()
        dirs_w = _turned(self._dirs.astype(np.float64), turn, self._firing) @ start[:3, :3].T
        origins = start[:3, 3] + self._firing[:, None] * (end[:3, 3] - start[:3, 3])
        if self._origins is not None:
            origins = origins + _turned(self._origins, turn, self._firing) @ start[:3, :3].T
        dirs_w = dirs_w.astype(np.float32)
        return dirs_w, origins


def deskew(points: np.ndarray, motion: np.ndarray, pattern: BeamPattern) -> np.ndarray:
    """The points of a swept revolution, each in the sensor frame of its firing time, in the sensor
    frame at the revolution's end; `motion` is the sensor's motion over the revolution (its end pose
    in its start frame), taken as steady within it, as LiDAR odometry deskews with a motion
    estimate; `pattern` says when each azimuth fires. float32 (N, 3)."""
    motion = np.asarray(motion, dtype=np.float64)
    share = pattern.firing_share(points)
    turn = Rotation.from_matrix(motion[:3, :3]).as_rotvec()
    at_start = _turned(np.asarray(points, dtype=np.float64), turn, share) + share[:, None] * motion[:3, 3]
    return ((at_start - motion[:3, 3]) @ motion[:3, :3]).astype(np.float32)


DESKEW_STEPS = 2  # odometry steps averaged into the motion a revolution is deskewed with


def deskew_motion(
    steps: list[np.ndarray] | np.ndarray, gyro: np.ndarray | None = None, mounting: np.ndarray | None = None
) -> np.ndarray:
    """The motion to deskew a revolution with, from the odometry's last steps (oldest first; the
    result is in their frame): the mean of the last DESKEW_STEPS, rotations averaged on SO(3). One
    step's leg odometry carries its white noise whole, which doubled ICP's yaw error on a steady
    walk; two steps halve the noise's variance and still follow a weaving walk's turns
    (`studies/deskew_step_error.py`). `gyro`, the gyro's rotation over the revolution (3x3, in
    the steps' frame), replaces the odometry's rotation, as LiDAR-inertial odometry deskews: it is
    the revolution's own turn, near exact, where the legs' turn is noisy and lags a weaving walk.
    `mounting` (the sensor in the steps' frame, T_b_s): the motion is then the sensor's, the body's
    carried through the mounting, so the lever arm turns with the rotation."""
    recent = [np.asarray(m, dtype=np.float64) for m in steps[-DESKEW_STEPS:]]
    mean = np.eye(4)
    if recent:
        mean[:3, 3] = np.mean([m[:3, 3] for m in recent], axis=0)
    if gyro is not None:
        mean[:3, :3] = gyro
    elif recent:
        mean[:3, :3] = Rotation.from_matrix(np.array([m[:3, :3] for m in recent])).mean().as_matrix()
    if mounting is None:
        return mean
    mounting = np.asarray(mounting, dtype=np.float64)
    return inverse(mounting) @ mean @ mounting


def _turned(vectors: np.ndarray, turn: np.ndarray, share: np.ndarray) -> np.ndarray:
    """Each vector rotated by its `share` of the rotation vector `turn` (Rodrigues' formula: about
    6x faster than building a scipy Rotation per ray)."""
    angle = float(np.linalg.norm(turn))
    if angle < 1e-12:
        return vectors
    axis = turn / angle
    cos, sin = np.cos(share * angle)[:, None], np.sin(share * angle)[:, None]
    return vectors * cos + np.cross(axis, vectors) * sin + np.outer(vectors @ axis, axis) * (1.0 - cos)
