"""Leg odometry: the true relative motion between steps, with the drift legged robots show."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from l3e_env.config import FusionSettings, OdometryConfig
from l3e_env.core.transforms import adjoint, inverse, matrix_to_pose, pose_to_matrix

if TYPE_CHECKING:
    from fusion import FusionConfig


class LegOdometry:
    """Noisy body-frame increments T_prev_cur.

    Per step, with d the distance moved and a the angle turned: white noise with sigmas
    proportional to d (and a, for yaw), a constant stride-scale error, and yaw and z biases
    (per metre) that wander as random walks. So standing still gives no drift and long
    straight walks drift in heading and height, as on a real quadruped.
    """

    def __init__(self, config: OdometryConfig | None = None, rng: np.random.Generator | None = None):
        self.config = config or OdometryConfig()
        self.reset(rng or np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        c = self.config
        self.rng = rng
        self.scale = 1.0 + rng.normal(0.0, c.scale_error_std)
        self.yaw_bias = rng.normal(0.0, c.yaw_bias_std)
        self.z_bias = rng.normal(0.0, c.z_bias_std)

    def measure(self, T_w_prev: np.ndarray, T_w_cur: np.ndarray) -> np.ndarray:
        """Noisy increment (4x4) for the true motion from T_w_prev to T_w_cur."""
        c, rng = self.config, self.rng
        v = matrix_to_pose(inverse(T_w_prev) @ T_w_cur)
        d, a = float(np.linalg.norm(v[:3])), abs(float(v[5]))
        self.yaw_bias += rng.normal(0.0, c.yaw_bias_walk * np.sqrt(d))
        self.z_bias += rng.normal(0.0, c.z_bias_walk * np.sqrt(d))
        sigma = np.array(
            [
                c.trans_noise_per_m * d,
                c.trans_noise_per_m * d,
                c.z_noise_per_m * d,
                c.rp_noise_per_m * d,
                c.rp_noise_per_m * d,
                c.yaw_noise_per_m * d + c.yaw_noise_per_rad * a,
            ]
        )
        noisy = v + rng.normal(0.0, 1.0, 6) * sigma
        noisy[:3] *= self.scale
        noisy[2] += self.z_bias * d
        noisy[5] += self.yaw_bias * d
        return pose_to_matrix(noisy)


# the stride's scale error is constant over an episode here; the fusion's state for it still
# wanders a little, as a real robot's does with its load and its ground (and a zero walk would make
# the graph's tie between its states singular)
SCALE_WALK = 1e-4  # per square-root metre


def odometry_fusion_config(
    odometry: OdometryConfig, settings: FusionSettings = FusionSettings(), **overrides
) -> FusionConfig:
    """The estimator's checked FusionConfig for `settings` (and any other FusionConfig fields), its
    odometry bias states, if any, starting from this noise model's bias spread and wandering by its
    random walk."""
    from fusion import FusionConfig, check_config  # GTSAM loads slowly

    return check_config(
        FusionConfig(
            odometry_bias_sigmas=(odometry.yaw_bias_std, odometry.z_bias_std, odometry.scale_error_std),
            odometry_bias_walk=(odometry.yaw_bias_walk, odometry.z_bias_walk, SCALE_WALK),
            mode=settings.mode,
            odometry_bias=tuple(settings.odometry_bias),
            **overrides,
        )
    )


def _white_sigmas(v: np.ndarray, cfg: OdometryConfig) -> np.ndarray:
    """The sigmas of one step's white noise, for the increment v = (x, y, z, roll, pitch, yaw)."""
    d, a = float(np.linalg.norm(v[:3])), abs(float(v[5]))
    yaw = cfg.yaw_noise_per_m * d + cfg.yaw_noise_per_rad * a
    return np.array(
        [cfg.trans_noise_per_m, cfg.trans_noise_per_m, cfg.z_noise_per_m, cfg.rp_noise_per_m, cfg.rp_noise_per_m, 0.0]
    ) * d + np.array([0, 0, 0, 0, 0, yaw])


def odometry_sigmas(increment: np.ndarray, cfg: OdometryConfig) -> np.ndarray:
    """Per-step standard deviations of the leg odometry from its own noise model (plus a floor)."""
    v = matrix_to_pose(increment)
    d = float(np.linalg.norm(v[:3]))
    bias = d * np.array([0, 0, cfg.z_bias_std, 0, 0, cfg.yaw_bias_std])
    scale = cfg.scale_error_std * np.abs(v) * np.array([1, 1, 1, 0, 0, 0])
    return np.sqrt(_white_sigmas(v, cfg) ** 2 + bias**2 + scale**2) + np.array([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4])


class DeadReckoningCovariance:
    """The covariances that the leg odometry's own noise model gives its dead-reckoned pose and
    its twist, step by step, ordered (x, y, z, rot x, rot y, rot z) as nav_msgs/Odometry carries
    them: the pose's in the odometry frame, the twist's in the body frame. The pose's error is
    propagated jointly with the stride scale and the yaw and z biases, which persist and wander, so
    the covariance grows with the distance walked as the drift does (a per-step white model
    under-states a 100 m walk's yaw error ten times)."""

    def __init__(self, config: OdometryConfig | None = None):
        c = self.config = config or OdometryConfig()
        # the pose's error in its own frame (6), then the scale error, the yaw bias and the z bias
        self.P = np.diag([0.0] * 6 + [c.scale_error_std**2, c.yaw_bias_std**2, c.z_bias_std**2])

    def step(self, increment: np.ndarray, T_odom_b: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The pose covariance after `increment` (4x4, body frame) brought the body to T_odom_b,
        and the covariance of the twist over `dt` seconds (odometry_sigmas, floor included, so
        that it is never singular)."""
        c, v = self.config, matrix_to_pose(increment)
        d = float(np.linalg.norm(v[:3]))
        self.P[7, 7] += c.yaw_bias_walk**2 * d  # the biases wander before the step reads them
        self.P[8, 8] += c.z_bias_walk**2 * d
        F = np.eye(9)
        F[:6, :6] = adjoint(inverse(increment))  # the previous body frame's error seen from the new one
        F[:3, 6] = v[:3]  # the stride scale stretches the step
        F[5, 7] = F[2, 8] = d  # the biases are per metre
        self.P = F @ self.P @ F.T
        self.P[:6, :6] += np.diag(_white_sigmas(v, c) ** 2)  # none standing still: the model does not drift there
        rotate = np.kron(np.eye(2), T_odom_b[:3, :3])
        return rotate @ self.P[:6, :6] @ rotate.T, np.diag(odometry_sigmas(increment, c) ** 2) / dt**2
