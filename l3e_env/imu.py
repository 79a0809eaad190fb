"""An IMU on the robot's base, read off a smooth trajectory through the drive's poses, so that a
recorded drive also feeds LiDAR-inertial odometry (FAST-LIO, LIO-SAM), which needs one; with the
orientation of a nine-axis unit (LIO-SAM reads it), whose roll and pitch hold to gravity and
whose heading wanders with the magnetometer's disturbances."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import lfilter
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
    orientation: bool = True  # a nine-axis unit's orientation estimate; False: none (six-axis)
    tilt_sigma_deg: float = 0.3  # its roll and pitch error
    heading_sigma_deg: float = 2.0  # its heading error
    orientation_time: float = 30.0  # s, how long an orientation error lasts (first-order Gauss-Markov)

    def sigmas(self) -> tuple[float, float]:
        """The per-sample standard deviations of the gyro and the accelerometer."""
        return self.gyro_noise * np.sqrt(self.rate), self.accel_noise * np.sqrt(self.rate)

    def orientation_sigmas(self) -> np.ndarray:
        """The orientation error's standard deviations (rad) about x, y and z."""
        return np.deg2rad([self.tilt_sigma_deg, self.tilt_sigma_deg, self.heading_sigma_deg])


@dataclass
class ImuSamples:
    stamps: np.ndarray  # (N,) seconds
    gyro: np.ndarray  # (N, 3) angular rate in the body frame, rad/s
    accel: np.ndarray  # (N, 3) specific force in the body frame, m/s^2 (+g up at rest)
    orientation: np.ndarray | None = None  # (N, 4) x, y, z, w of the body in the world frame; None: six-axis


def imu_samples(stamps: np.ndarray, poses: list[np.ndarray], config: ImuConfig | None = None,
                rng: np.random.Generator | None = None) -> ImuSamples:
    """The IMU's readings from the first pose's time to the last at `config.rate`: position and
    rotation splines through the poses T_w_b (z up) at `stamps` (continuous angular rate and
    acceleration), plus white noise and wandering biases where `rng` is given; with
    `config.orientation`, the body's orientation, off by an error that wanders and returns (a
    Gauss-Markov process per axis in the body frame) where `rng` is given."""
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
    if not config.orientation:
        return ImuSamples(t, gyro, accel)
    attitude = rotation(t)
    if rng is not None:
        attitude = attitude * Rotation.from_rotvec(_gauss_markov(len(t), 1.0 / config.rate, config.orientation_time,
                                                                 config.orientation_sigmas(), rng))
    return ImuSamples(t, gyro, accel, attitude.as_quat())


def _gauss_markov(n: int, dt: float, time: float, sigmas: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) samples of stationary first-order Gauss-Markov processes: each axis's error has the
    standard deviation `sigmas` and forgets itself over `time` seconds."""
    keep = np.exp(-dt / time)
    drive = rng.normal(0.0, 1.0, (n, 3)) * sigmas * np.sqrt(1.0 - keep**2)
    drive[0] = rng.normal(0.0, 1.0, 3) * sigmas  # started in its stationary spread
    return lfilter([1.0], [1.0, -keep], drive, axis=0)  # e[k] = keep e[k-1] + drive[k]
