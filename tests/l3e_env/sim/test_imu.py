"""The IMU read off the drive's poses: true to the motion, integrable back to the poses, noisy as configured."""

import numpy as np
import pytest
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from l3e_env.core.transforms import pose_to_matrix
from l3e_env.sim.imu import GRAVITY, ImuConfig, StepGyro, attitude_readings, attitude_sigmas, imu_samples


def _circle(t: np.ndarray, radius: float = 5.0, rate: float = 0.2) -> list[np.ndarray]:
    """Walking a circle anticlockwise, facing along it, at `rate` rad/s, on a floor that rises gently."""
    return [
        pose_to_matrix([radius * np.sin(rate * s), radius * (1 - np.cos(rate * s)), 0.5 + 0.02 * s, 0.0, 0.0, rate * s])
        for s in t
    ]


def test_a_circle_reads_its_turn_rate_and_centripetal_acceleration_plus_gravity():
    stamps = np.arange(0.0, 10.01, 0.1)
    imu = imu_samples(stamps, _circle(stamps))
    assert imu.stamps[0] == 0.0 and imu.stamps[-1] == pytest.approx(10.0) and len(imu.stamps) == 2001
    middle = (imu.stamps > 1.0) & (imu.stamps < 9.0)  # away from the splines' free ends
    np.testing.assert_allclose(imu.gyro[middle], np.tile([0.0, 0.0, 0.2], (middle.sum(), 1)), atol=1e-4)
    # the centre lies to the left (+y in the body frame): v^2 / r = 1^2 / 5
    np.testing.assert_allclose(imu.accel[middle], np.tile([0.0, 0.2, GRAVITY], (middle.sum(), 1)), atol=2e-3)


def test_integrating_the_noise_free_imu_returns_to_the_poses():
    """Strapdown integration from the first pose and the spline's own start velocity stays
    within a centimetre of a 10 s drive that turns, climbs and pitches."""
    stamps = np.arange(0.0, 10.01, 0.1)
    poses = [
        pose_to_matrix(
            [
                3 * np.sin(0.3 * s),
                s + 0.5 * np.sin(s),
                0.3 * np.sin(0.5 * s),
                0.05 * np.sin(s),
                0.08 * np.sin(0.7 * s),
                0.4 * s,
            ]
        )
        for s in stamps
    ]
    imu = imu_samples(stamps, poses, ImuConfig(rate=400.0))
    dt = 1.0 / 400.0
    R, p = poses[0][:3, :3].copy(), poses[0][:3, 3].copy()
    v = CubicSpline(stamps, np.array(poses)[:, :3, 3])(0.0, 1)
    errors = []
    for k in range(len(imu.stamps) - 1):
        # midpoint rule on the rotation; the acceleration averaged over the sample interval
        w = 0.5 * (imu.gyro[k] + imu.gyro[k + 1])
        R_next = R @ Rotation.from_rotvec(w * dt).as_matrix()
        a = 0.5 * (R @ imu.accel[k] + R_next @ imu.accel[k + 1]) - np.array([0.0, 0.0, GRAVITY])
        p, v, R = p + v * dt + 0.5 * a * dt**2, v + a * dt, R_next
        if (k + 1) % 40 == 0:  # at each pose's time
            errors.append(np.linalg.norm(p - poses[(k + 1) // 40][:3, 3]))
    assert len(errors) == 100 and max(errors) < 0.01


def test_noise_and_biases_are_as_configured_at_rest(rng):
    stamps = np.arange(0.0, 20.01, 0.1)
    still = [pose_to_matrix([1.0, 2.0, 0.5, 0.0, 0.0, 0.3])] * len(stamps)
    config = ImuConfig(gyro_bias_walk=0.0, accel_bias_walk=0.0)
    imu = imu_samples(stamps, still, config, rng)
    gyro_sigma, accel_sigma = config.sigmas()
    np.testing.assert_allclose(imu.gyro.std(axis=0), gyro_sigma, rtol=0.05)
    np.testing.assert_allclose(imu.accel.std(axis=0), accel_sigma, rtol=0.05)
    np.testing.assert_allclose(imu.accel.mean(axis=0), [0.0, 0.0, GRAVITY], atol=5 * accel_sigma / np.sqrt(len(stamps)))
    drifting = imu_samples(stamps, still, ImuConfig(gyro_noise=0.0, accel_noise=0.0, gyro_bias_walk=1e-3), rng)
    # a random walk: its spread after 20 s is the walk's density times sqrt(20 s)
    assert 0.2 * 1e-3 * np.sqrt(20) < np.abs(drifting.gyro[-1]).max() < 5 * 1e-3 * np.sqrt(20)


def test_the_orientation_is_the_body_s_own_off_by_errors_that_wander_and_return(rng):
    """Noise-free: the pose's rotation at each pose's time. Noisy: tilt and heading errors with the
    configured spreads in the body frame, correlated over about `orientation_time`, not drifting."""
    stamps = np.arange(0.0, 10.01, 0.1)
    poses = _circle(stamps)
    imu = imu_samples(stamps, poses)
    at_poses = Rotation.from_quat(imu.orientation[::20])  # 200 Hz: every 20th sample is at a pose
    truth = Rotation.from_matrix(np.array(poses)[:, :3, :3])
    assert len(at_poses) == len(truth) and (at_poses.inv() * truth).magnitude().max() < 1e-9
    assert imu_samples(stamps, poses, ImuConfig(orientation=False)).orientation is None
    long = np.arange(0.0, 3000.0, 1.0)
    still = [pose_to_matrix([0.0, 0.0, 0.5, 0.0, 0.0, 1.0])] * len(long)
    config = ImuConfig(rate=20.0, orientation_time=10.0)
    error = (
        Rotation.from_matrix(still[0][:3, :3]).inv()
        * Rotation.from_quat(imu_samples(long, still, config, rng).orientation)
    ).as_rotvec()
    np.testing.assert_allclose(error.std(axis=0), config.orientation_sigmas(), rtol=0.2)
    heading = error[:, 2]
    lag = int(10.0 * config.rate)  # one correlation time apart: e^-1 of the spread shared
    assert np.corrcoef(heading[:-lag], heading[lag:])[0, 1] == pytest.approx(np.exp(-1), abs=0.12)
    assert abs(np.corrcoef(heading[: -20 * lag], heading[20 * lag :])[0, 1]) < 0.15


def test_the_step_rate_attitude_is_the_body_s_own_off_by_the_orientation_s_errors(rng):
    """What the fusion takes once a second: the pose's rotation turned by the same Gauss-Markov
    error as `imu_samples` gives its orientation, in the body frame (a heading error turns about
    the body's own z, whatever its tilt); tilt alone leaves the heading unmeasured."""
    poses = np.array([pose_to_matrix([0.0, 0.0, 0.5, 0.2, -0.1, 1.0])] * 30000)
    config = ImuConfig(orientation_time=10.0)
    readings = attitude_readings(poses, 0.1, config, rng)
    error = Rotation.from_matrix(np.swapaxes(poses[:, :3, :3], 1, 2) @ readings).as_rotvec()
    np.testing.assert_allclose(error.std(axis=0), config.orientation_sigmas(), rtol=0.2)
    assert np.corrcoef(error[:-100, 2], error[100:, 2])[0, 1] == pytest.approx(np.exp(-1), abs=0.12)
    # a reading a second, its error lasting 10 s: each reading weighs as the share of an independent one it is
    full = attitude_sigmas("full", config, every=1.0)
    r = np.exp(-0.1)
    np.testing.assert_allclose(full, config.orientation_sigmas() * np.sqrt((1 + r) / (1 - r)))
    tilt = attitude_sigmas("tilt", config, every=1.0)
    assert np.isinf(tilt[2]) and (tilt[:2] == full[:2]).all()
    # so that the readings over a walk are as sure of the tilt as the error's mean over it is: the spread of
    # that mean over 300 s walks (30 s apart, each reading 1 s apart) against the weighted readings' sigma
    per_second = error[::10, 0]
    means = [per_second[k : k + 300].mean() for k in range(0, len(per_second) - 300, 30)]
    assert np.std(means) == pytest.approx(tilt[0] / np.sqrt(300), rel=0.35)
    # each as if independent: the error's own sigma (the fusion's choice without the ground)
    np.testing.assert_allclose(
        attitude_sigmas("full", config, every=1.0, correlated=False), config.orientation_sigmas()
    )
    assert attitude_sigmas("none") is None
    with pytest.raises(ValueError, match="attitude must be one of"):
        attitude_sigmas("gravity")


def test_too_few_poses_or_unordered_times_are_refused():
    with pytest.raises(ValueError, match="at least two poses"):
        imu_samples(np.array([0.0]), [np.eye(4)])
    with pytest.raises(ValueError, match="increasing times"):
        imu_samples(np.array([0.0, 0.0]), [np.eye(4), np.eye(4)])


def _walk_then_stand(stamps: np.ndarray, speed: float = 1.0, stop: float = 9.0) -> list[np.ndarray]:
    """Walking straight along x at `speed` until `stop`, then standing."""
    return [pose_to_matrix([speed * min(s, stop), 0.0, 0.5, 0.0, 0.0, 0.0]) for s in stamps]


def test_footfalls_jolt_the_walking_body_and_leave_no_velocity_behind():
    stamps = np.arange(0.0, 10.01, 0.1)
    poses = _walk_then_stand(stamps)
    still = ImuConfig(footfall_accel=0.0)
    smooth = imu_samples(stamps, poses, still, np.random.default_rng(3))
    walking = imu_samples(stamps, poses, ImuConfig(), np.random.default_rng(3))
    jolt, turn = walking.accel - smooth.accel, walking.gyro - smooth.gyro
    np.testing.assert_allclose(walking.orientation, smooth.orientation)  # drawn after everything else
    config, dt = ImuConfig(), 1.0 / ImuConfig().rate
    assert 0.7 * config.footfall_accel <= np.abs(jolt[:, 2]).max() <= 1.3 * config.footfall_accel
    assert np.abs(jolt[:, :2]).max() <= 0.3 * 1.3 * config.footfall_accel
    assert 0.7 * config.footfall_gyro <= np.abs(turn[:, :2]).max() <= 1.3 * config.footfall_gyro
    assert np.abs(turn[:, 2]).max() == 0.0
    standing = walking.stamps > 9.6  # the last jolt has died away: the body is exactly as without them
    np.testing.assert_allclose(jolt[standing], 0.0, atol=1e-12)
    velocity = np.cumsum(jolt, axis=0) * dt  # what integrating the samples makes of them
    assert np.abs(velocity[standing]).max() < 1e-9  # no velocity left
    assert np.abs(np.cumsum(velocity, axis=0)[standing] * dt).max() < 1e-9  # nor displacement
    assert np.abs(np.cumsum(turn, axis=0)[standing] * dt).max() < 1e-9  # nor angle
    assert np.abs(np.cumsum(velocity, axis=0) * dt).max() < 1e-3  # a jolt moves the body by under a millimetre
    spectrum = np.abs(np.fft.rfft(jolt[:, 2]))
    assert abs(np.fft.rfftfreq(len(jolt), dt)[spectrum.argmax()] - config.jolt_frequency) < 3.0


def test_one_footfall_every_third_of_a_second_while_walking_and_none_at_rest():
    stamps = np.arange(0.0, 10.01, 0.1)
    short = ImuConfig(jolt_time=0.005, gyro_noise=0.0, accel_noise=0.0, gyro_bias_walk=0.0, accel_bias_walk=0.0)
    vertical = imu_samples(stamps, _walk_then_stand(stamps), short, np.random.default_rng(4)).accel[:, 2] - GRAVITY
    high = np.abs(vertical) > 0.5 * 0.7 * short.footfall_accel
    onsets = np.flatnonzero(high[1:] & ~np.convolve(high, np.ones(20), "full")[: len(high) - 1].astype(bool))
    assert len(onsets) == 27  # 9 s of walking at 3 Hz
    assert np.allclose(np.diff(onsets) / short.rate, 1.0 / short.footfall_rate, atol=0.011)
    at_rest = [pose_to_matrix([1.0, 2.0, 0.5, 0.0, 0.0, 0.3])] * len(stamps)
    np.testing.assert_array_equal(
        imu_samples(stamps, at_rest, ImuConfig(), np.random.default_rng(5)).accel,
        imu_samples(stamps, at_rest, ImuConfig(footfall_accel=0.0), np.random.default_rng(5)).accel,
    )


def test_the_step_gyro_reads_the_step_s_turn_off_by_its_integrated_noise_and_bias():
    """Over 0.1 s steps the white rate noise integrates to gyro_noise sqrt(dt) per axis; the bias
    starts at zero and wanders; without noise the reading is the true turn, in the body frame."""
    before = pose_to_matrix([0, 0, 0, 0.1, -0.2, 1.0])[:3, :3]
    after = pose_to_matrix([0, 0, 0, 0.12, -0.19, 1.3])[:3, :3]
    exact = StepGyro(ImuConfig(gyro_noise=0.0, gyro_bias_walk=0.0))
    np.testing.assert_allclose(exact.measure(before, after, 0.1), before.T @ after, atol=1e-12)
    config = ImuConfig(gyro_bias_walk=0.0)
    gyro = StepGyro(config, np.random.default_rng(3))
    errors = np.array([Rotation.from_matrix(gyro.measure(before, before, 0.1)).as_rotvec() for _ in range(4000)])
    np.testing.assert_allclose(errors.std(axis=0), config.gyro_noise * np.sqrt(0.1), rtol=0.06)
    assert np.abs(errors.mean(axis=0)).max() < 0.1 * config.gyro_noise
    drifting = StepGyro(ImuConfig(gyro_noise=0.0, gyro_bias_walk=1e-3), np.random.default_rng(4))
    for _ in range(1000):  # 100 s
        drifting.measure(before, before, 0.1)
    assert 1e-4 < np.linalg.norm(drifting.bias) < 1e-1  # about 1e-3 sqrt(100) a axis
    drifting.reset(np.random.default_rng(4))
    assert not drifting.bias.any()
