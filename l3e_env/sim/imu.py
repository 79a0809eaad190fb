"""An IMU on the robot's base, read off a smooth trajectory through the drive's poses, so that a
recorded drive also feeds LiDAR-inertial odometry (FAST-LIO, LIO-SAM), which needs one; with the
orientation of a nine-axis unit (LIO-SAM reads it), whose roll and pitch hold to gravity and
whose heading wanders with the magnetometer's disturbances, and with the jolts of a walking
robot's footfalls, which the stand-in's smooth drive does not have."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, RotationSpline

from l3e_env.config import ATTITUDE_MODES, RobotConfig

GRAVITY = 9.81


@dataclass(frozen=True)
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
    footfall_rate: float = 3.0  # Hz, footfalls (a trot's diagonal pairs) while the body moves
    footfall_accel: float = 3.0  # m/s^2, peak vertical jolt of a footfall (0: no footfalls)
    footfall_gyro: float = 0.3  # rad/s, peak roll and pitch rate of a footfall
    jolt_frequency: float = 20.0  # Hz, the body's ring after an impact
    jolt_time: float = 0.03  # s, how fast it dies away

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


def imu_samples(
    stamps: np.ndarray, poses: list[np.ndarray], config: ImuConfig | None = None, rng: np.random.Generator | None = None
) -> ImuSamples:
    """The IMU's readings from the first pose's time to the last at `config.rate`: position and
    rotation splines through the poses T_w_b (z up) at `stamps` (continuous angular rate and
    acceleration), plus white noise and wandering biases where `rng` is given; with
    `config.orientation`, the body's orientation, off by an error that wanders and returns (a
    Gauss-Markov process per axis in the body frame) where `rng` is given."""
    config = config or ImuConfig()
    stamps = np.asarray(stamps, dtype=np.float64)
    if len(stamps) < 2 or len(stamps) != len(poses) or not (np.diff(stamps) > 0).all():
        raise ValueError(
            f"the IMU needs at least two poses at increasing times, got {len(poses)} poses at {len(stamps)} times"
        )
    T_w_b = np.asarray(poses, dtype=np.float64)
    from scipy.interpolate import CubicSpline  # scipy.interpolate loads slowly: only where an IMU is simulated

    position = CubicSpline(stamps, T_w_b[:, :3, 3])
    rotation = RotationSpline(stamps, Rotation.from_matrix(T_w_b[:, :3, :3]))
    t = np.arange(stamps[0], stamps[-1] + 0.5 / config.rate, 1.0 / config.rate)
    t = t[t <= stamps[-1] + 1e-9]  # the last pose's own sample, whatever the rounding of the steps
    gyro = rotation(t, 1)  # scipy gives the rate in the rotating (body) frame
    accel = rotation(t).inv().apply(position(t, 2) + np.array([0.0, 0.0, GRAVITY]))
    if rng is not None:
        gyro_sigma, accel_sigma = config.sigmas()
        step = np.sqrt(1.0 / config.rate)
        gyro = (
            gyro
            + np.cumsum(rng.normal(0.0, config.gyro_bias_walk * step, gyro.shape), axis=0)
            + rng.normal(0.0, gyro_sigma, gyro.shape)
        )
        accel = (
            accel
            + np.cumsum(rng.normal(0.0, config.accel_bias_walk * step, accel.shape), axis=0)
            + rng.normal(0.0, accel_sigma, accel.shape)
        )
    attitude = None
    if config.orientation:
        body = rotation(t)
        if rng is not None:
            body = body * Rotation.from_rotvec(
                _gauss_markov(len(t), 1.0 / config.rate, config.orientation_time, config.orientation_sigmas(), rng)
            )
        attitude = body.as_quat()
    if rng is not None and config.footfall_accel > 0:  # drawn last: the other draws stay as they were
        walking = (np.linalg.norm(position(t, 1)[:, :2], axis=1) > WALKING_SPEED) | (np.abs(gyro[:, 2]) > WALKING_TURN)
        jolt_gyro, jolt_accel = footfall_jolts(walking, config, rng)
        gyro, accel = gyro + jolt_gyro, accel + jolt_accel
    return ImuSamples(t, gyro, accel, attitude)


class StepGyro:
    """The rotation a gyro integrates over one step, in the body frame, as IMU preintegration gives
    it: the true rotation, turned by the bias and the white noise of the samples within the step.
    LiDAR-inertial odometry deskews a revolution's rotation with it. Footfall jolts are left out:
    the simulated revolution does not shake with them either. The bias starts at zero (a gyro is
    calibrated standing still) and wanders as `ImuConfig.gyro_bias_walk` says."""

    def __init__(self, config: ImuConfig | None = None, rng: np.random.Generator | None = None):
        self.config = config or ImuConfig()
        self.reset(rng or np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        self.rng, self.bias = rng, np.zeros(3)

    def measure(self, R_w_prev: np.ndarray, R_w_cur: np.ndarray, dt: float) -> np.ndarray:
        """The integrated rotation from the body's orientation `R_w_prev` to `R_w_cur` over `dt` s
        (3x3, in the body frame at the step's start)."""
        c = self.config
        self.bias = self.bias + self.rng.normal(0.0, c.gyro_bias_walk * np.sqrt(dt), 3)
        error = self.bias * dt + self.rng.normal(0.0, c.gyro_noise * np.sqrt(dt), 3)  # white rate noise, integrated
        true = np.asarray(R_w_prev, dtype=np.float64).T @ np.asarray(R_w_cur, dtype=np.float64)
        return true @ Rotation.from_rotvec(error).as_matrix()


WALKING_SPEED = 0.05  # m/s: slower, and not turning, the robot stands and its feet stay put
WALKING_TURN = 0.1  # rad/s
JOLT_LENGTH = 12  # jolt times: a jolt is cut off there


def footfall_jolts(walking: np.ndarray, config: ImuConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(gyro, accel) added by footfalls, in the body frame, at the IMU's samples: while `walking`,
    a footfall every 1 / footfall_rate s, each a ring of the body that starts at rest and dies
    away, so it leaves no velocity, position or angle behind (what integrating odometry needs).

    A jolt moves the body by a s exp(-s / T) sin(w s) after the impact (s the time since it): the
    rate and the acceleration are its first and second differences between samples, so that
    summing the samples, as an integrator does, returns exactly to rest. Vertical jolts all push
    up, by 0.7-1.3 of `footfall_accel`; the diagonal pairs alternate, so sideways sway (0.3 of it)
    and roll change sign from footfall to footfall; fore-aft (0.3) and pitch take a random sign."""
    dt = 1.0 / config.rate
    phase = np.cumsum(walking * config.footfall_rate * dt)
    falls = np.flatnonzero(np.diff(np.floor(phase), prepend=0.0) > 0)
    s = np.arange(0.0, JOLT_LENGTH * config.jolt_time + 2.0 * dt, dt)
    shape = np.concatenate(
        [[0.0], s * np.exp(-s / config.jolt_time) * np.sin(2.0 * np.pi * config.jolt_frequency * s), [0.0, 0.0]]
    )  # cut off at rest: what is left at 12 T, a 1e-5 of the jolt, is dropped
    rate_kernel = np.diff(shape)[1:] / dt  # the impact at a sample moves the body from the next one on
    accel_kernel = np.diff(shape, 2) / dt**2
    rate_peak, accel_peak = np.abs(rate_kernel).max(), np.abs(accel_kernel).max()
    alternate = np.where(np.arange(len(falls)) % 2 == 0, 1.0, -1.0)
    size = rng.uniform(0.7, 1.3, len(falls))[:, None]
    sign = rng.choice([-1.0, 1.0], (len(falls), 2))
    ones, zeros = np.ones(len(falls)), np.zeros(len(falls))
    n = len(walking)
    jolt_gyro, jolt_accel = np.zeros((n, 3)), np.zeros((n, 3))
    jolt_accel[falls] = (
        size * (config.footfall_accel / accel_peak) * np.stack([0.3 * sign[:, 0], 0.3 * alternate, ones], 1)
    )
    jolt_gyro[falls] = size * (config.footfall_gyro / rate_peak) * np.stack([alternate, sign[:, 1], zeros], 1)
    for k in range(3):  # each footfall's impulse spread into its jolt
        jolt_accel[:, k] = np.convolve(jolt_accel[:, k], accel_kernel)[:n]
        jolt_gyro[:, k] = np.convolve(jolt_gyro[:, k], rate_kernel)[:n]
    return jolt_gyro, jolt_accel


ATTITUDE_EVERY = 10  # steps between two attitude factors in the fusion (1 s at 10 Hz)


def attitude_sigmas(
    mode: str, config: ImuConfig | None = None, every: float = ATTITUDE_EVERY * RobotConfig.dt, correlated: bool = True
) -> np.ndarray | None:
    """The sigmas (rad, about the body's x, y, z) with which the fusion takes the nine-axis unit's
    orientation, one reading every `every` seconds: "tilt" takes roll and pitch, which gravity
    holds, and leaves the heading out (inf), as underground, where a magnetometer reads the rock
    and the machines; "full" takes the magnetometer's heading too; "none" takes nothing (None).

    The unit's error lasts `orientation_time` (a first-order Gauss-Markov process, correlation
    r = exp(-every / time) from one reading to the next), and the fusion takes each reading as
    independent. `correlated`: each is weighted as the share of one independent reading that it is,
    its sigma the error's times sqrt((1 + r) / (1 - r)), so that readings over a long walk hold the
    tilt as well as the error's mean over that walk, not as well as that many independent readings
    would (about 8 times the error's sigma with a reading a second and a 30 s error). Else each
    with the error's own sigma: over-sure of the readings' mean, which is what holds the tilt
    where nothing else does against the registrations' chain, whose small biases a step are not in
    its noise either (the fusion's choice: correlated while a ground patch holds the pose;
    detection.pipeline.LocalizationPipeline.attitude_weights, docs/decisions.md)."""
    if mode not in ATTITUDE_MODES:
        raise ValueError(f"attitude must be one of {ATTITUDE_MODES}, got {mode!r}")
    if mode == "none":
        return None
    config = config or ImuConfig()
    r = float(np.exp(-every / config.orientation_time))
    sigmas = config.orientation_sigmas() * (np.sqrt((1.0 + r) / (1.0 - r)) if correlated else 1.0)
    return sigmas if mode == "full" else np.r_[sigmas[:2], np.inf]


class StepAttitude:
    """The nine-axis unit's orientation once a step: the body's rotation turned by the error that
    `imu_samples` gives its orientation (a Gauss-Markov process per body axis, started in its
    stationary spread), drawn at the step's rate. The fusion takes it as an absolute attitude."""

    def __init__(self, config: ImuConfig | None = None, rng: np.random.Generator | None = None):
        self.config = config or ImuConfig()
        self.reset(rng or np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        self.rng, self.error = rng, None

    def measure(self, R_w_b: np.ndarray, dt: float) -> np.ndarray:
        """The unit's orientation (3x3) of the body at `R_w_b`, `dt` s after the last reading."""
        sigmas = self.config.orientation_sigmas()
        if self.error is None:
            self.error = self.rng.normal(0.0, 1.0, 3) * sigmas
        else:
            keep = np.exp(-dt / self.config.orientation_time)
            self.error = keep * self.error + self.rng.normal(0.0, 1.0, 3) * sigmas * np.sqrt(1.0 - keep**2)
        return np.asarray(R_w_b, dtype=np.float64) @ Rotation.from_rotvec(self.error).as_matrix()


def attitude_readings(
    poses: np.ndarray, dt: float, config: ImuConfig | None = None, rng: np.random.Generator | None = None
) -> np.ndarray:
    """`StepAttitude`'s readings (N, 3, 3) at poses T_w_b taken every `dt` s."""
    unit = StepAttitude(config, rng)
    return np.array([unit.measure(T[:3, :3], dt) for T in np.asarray(poses, dtype=np.float64)])


def _gauss_markov(n: int, dt: float, time: float, sigmas: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) samples of stationary first-order Gauss-Markov processes: each axis's error has the
    standard deviation `sigmas` and forgets itself over `time` seconds."""
    keep = np.exp(-dt / time)
    drive = rng.normal(0.0, 1.0, (n, 3)) * sigmas * np.sqrt(1.0 - keep**2)
    drive[0] = rng.normal(0.0, 1.0, 3) * sigmas  # started in its stationary spread
    from scipy.signal import lfilter  # scipy.signal loads slowly: only where an IMU is simulated

    return lfilter([1.0], [1.0, -keep], drive, axis=0)  # e[k] = keep e[k-1] + drive[k]
