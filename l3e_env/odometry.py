"""Leg odometry: the true relative motion between steps, with the drift legged robots show."""
from __future__ import annotations

import numpy as np

from .config import OdometryConfig
from .transforms import inverse, matrix_to_pose, pose_to_matrix


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
        sigma = np.array([c.trans_noise_per_m * d, c.trans_noise_per_m * d, c.z_noise_per_m * d,
                          c.rp_noise_per_m * d, c.rp_noise_per_m * d, c.yaw_noise_per_m * d + c.yaw_noise_per_rad * a])
        noisy = v + rng.normal(0.0, 1.0, 6) * sigma
        noisy[:3] *= self.scale
        noisy[2] += self.z_bias * d
        noisy[5] += self.yaw_bias * d
        return pose_to_matrix(noisy)


def odometry_sigmas(increment: np.ndarray, cfg: OdometryConfig) -> np.ndarray:
    """Per-step standard deviations of the leg odometry from its own noise model (plus a floor)."""
    v = matrix_to_pose(increment)
    d, a = float(np.linalg.norm(v[:3])), abs(float(v[5]))
    bias = d * np.array([0, 0, cfg.z_bias_std, 0, 0, cfg.yaw_bias_std])
    s = np.array([cfg.trans_noise_per_m * d, cfg.trans_noise_per_m * d, cfg.z_noise_per_m * d, cfg.rp_noise_per_m * d,
                  cfg.rp_noise_per_m * d, cfg.yaw_noise_per_m * d + cfg.yaw_noise_per_rad * a])
    scale = cfg.scale_error_std * np.abs(v) * np.array([1, 1, 1, 0, 0, 0])
    return np.sqrt(s**2 + bias**2 + scale**2) + np.array([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4])
