"""Fusion in the loop: per environment step, register the new scan to the last, ask the
detector for a mask, and add odometry and masked ICP to the fusion backend.

`EnvConfig.fusion` switches it on; `info` then carries the fused estimate, the detector's
probabilities and mask, and the running ATE against ground truth.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from fusion import check_backend, make_fusion

from l3e_env.config import LoopFusionConfig, OdometryConfig
from .detectors import UNKNOWN, Detector, Prediction, make_detector, safe_predict
from l3e_env.sim.imu import ATTITUDE_EVERY, attitude_sigmas
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.odometry import odometry_fusion_config, odometry_sigmas
from l3e_env.localizability.registration import PreparedTarget, RegistrationConfig, RegistrationError, register


class OnlineFusion:
    """One run of fusion along an episode; `reset` at every episode start."""

    def __init__(self, config: LoopFusionConfig, lidar: Lidar, odometry: OdometryConfig, T_b_s: np.ndarray,
                 seed: int = 0):
        check_backend(config.backend)
        self.config, self.odometry, self.T_b_s = config, odometry, T_b_s
        self.registration = RegistrationConfig()
        self.fusion_config = odometry_fusion_config(odometry, config.options(), mode=config.mode)
        self.detector: Detector = make_detector(config.detector, lidar, seed)
        self.attitude_sigmas = attitude_sigmas(config.attitude)

    def reset(self, T_w_b: np.ndarray, points: np.ndarray) -> dict[str, Any]:
        self.backend = make_fusion(self.config.backend, T_w_b, self.fusion_config)
        self.target = self._target(points)
        self.squared_errors: list[float] = [0.0]
        self.counts = {"icp_failed": 0, "unknown": 0, "detector_errors": 0, "fallbacks": 0}
        return self._info(T_w_b, UNKNOWN)

    def _target(self, points: np.ndarray) -> PreparedTarget | None:
        try:
            return PreparedTarget(points, self.registration)
        except RegistrationError:
            return None

    def step(self, odom_increment: np.ndarray, points: np.ndarray, T_w_b_true: np.ndarray,
             attitude: np.ndarray | None = None) -> dict[str, Any]:
        """`attitude`: the IMU's orientation of the body (3x3), fused every ATTITUDE_EVERY steps
        where `LoopFusionConfig.attitude` asks for it."""
        reg = None
        if self.target is not None:
            try:
                reg = register(points, self.target, self.registration)
            except RegistrationError:
                reg = None
        icp, hessian = (reg.in_frame(self.T_b_s) if reg is not None else None) or (None, None)
        self.counts["icp_failed"] += icp is None
        pred, failed = safe_predict(self.detector, points, reg, T_w_b_true @ self.T_b_s)
        self.counts["detector_errors"] += failed
        self.counts["unknown"] += not pred.known
        sigmas = odometry_sigmas(odom_increment, self.odometry)
        T, report = self.backend.add_step(odom_increment, sigmas, icp, pred.mask, hessian)
        self.counts["fallbacks"] += report.fallback is not None
        if self.attitude_sigmas is not None and len(self.squared_errors) % ATTITUDE_EVERY == 0:
            if attitude is None:
                raise ValueError(f"fusion.attitude is {self.config.attitude!r}: every step needs the IMU's attitude")
            T = self.backend.add_attitude(attitude, self.attitude_sigmas)
        self.target = self._target(points)
        self.squared_errors.append(float(np.sum((T[:3, 3] - T_w_b_true[:3, 3]) ** 2)))
        return self._info(T, pred)

    def _info(self, T: np.ndarray, pred: Prediction) -> dict[str, Any]:
        return {"fused_T_w_b": T.copy(), "localizability_probabilities": pred.probabilities.copy(),
                "localizability_mask": pred.mask.copy(), "localizability_known": pred.known,
                "running_ate": float(np.sqrt(np.mean(self.squared_errors))), "fusion_counts": dict(self.counts)}
