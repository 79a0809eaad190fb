"""An IMU on the robot's base, read off a smooth trajectory through the drive's poses, so that a
recorded drive also feeds LiDAR-inertial odometry (FAST-LIO, LIO-SAM), which needs one."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

GRAVITY = 9.81


@dataclass
class ImuConfig:
    """Rate and noise of the IMU, as a MEMS unit of a legged robot's class (noise densities per
    sqrt(Hz), bias random walks per sqrt(s))."""

    rate: float = 200.0  # Hz
    gyro_noise: float = 2e-4  # rad/s/sqrt(Hz)
    accel_noise: float = 2e-3  # m/s^2/sqrt(Hz)
    gyro_bias_walk: float = 2e-5  # rad/s^2/sqrt(Hz)
    accel_bias_walk: float = 3e-4  # m/s^3/sqrt(Hz)

    def sigmas(self) -> tuple[float, float]:
        """The per-sample standard deviations of the gyro and the accelerometer."""
        return self.gyro_noise * np.sqrt(self.rate), self.accel_noise * np.sqrt(self.rate)


@dataclass
class ImuSamples:
    stamps: np.ndarray  # (N,) seconds
    gyro: np.ndarray  # (N, 3) angular rate in the body frame, rad/s
    accel: np.ndarray  # (N, 3) specific force in the body frame, m/s^2 (+g up at rest)


def imu_samples(stamps: np.ndarray, poses: list[np.ndarray], config: ImuConfig | None = None,
                rng: np.random.Generator | None = None) -> ImuSamples:
    """The IMU's readings from the first pose's time to the last at `config.rate`: position and
    rotation splines through the poses T_w_b (z up) at `stamps` (continuous angular rate and
    acceleration), plus white noise and wandering biases where `rng` is given."""
    config = config or ImuConfig()
    stamps = np.asarray(stamps, dtype=np.float64)
    if len(stamps) < 2 or len(stamps) != len(poses) or not (np.diff(stamps) > 0).all():
        raise ValueError(f"the IMU needs at least two poses at increasing times, got {len(poses)} poses "
                         f"at {len(stamps)} times")
    poses = np.asarray(poses, dtype=np.float64)
    position = CubicSpline(stamps, poses[:, :3, 3])
    rotation = RotationSpline(stamps, Rotation.from_matrix(poses[:, :3, :3]))
    t = np.arange(stamps[0], stamps[-1] + 0.5 / config.rate, 1.0 / config.rate)
    t = t[t <= stamps[-1]]
    gyro = rotation(t, 1)  # scipy gives the rate in the rotating (body) frame
    accel = rotation(t).inv().apply(position(t, 2) + np.array([0.0, 0.0, GRAVITY]))
    if rng is not None:
        gyro_sigma, accel_sigma = config.sigmas()
        step = np.sqrt(1.0 / config.rate)
        gyro = gyro + np.cumsum(rng.normal(0.0, config.gyro_bias_walk * step, gyro.shape), axis=0) \
            + rng.normal(0.0, gyro_sigma, gyro.shape)
        accel = accel + np.cumsum(rng.normal(0.0, config.accel_bias_walk * step, accel.shape), axis=0) \
            + rng.normal(0.0, accel_sigma, accel.shape)
    return ImuSamples(t, gyro, accel)
