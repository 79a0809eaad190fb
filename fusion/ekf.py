"""The same fusion as `FusionGraph`, as a filterpy extended Kalman filter with partial updates.

The state is the error of the last two poses (stochastic cloning, 12-d, GTSAM tangent order,
right perturbation T <- T Exp(d)): odometry propagates the clone, the scan-to-scan ICP is a
relative measurement between the two, and only its localizable rows enter the update (the
filter's partial update). A filter cannot revise old poses: `trajectory()` is the sequence of
filtered estimates, which is what a robot has online. With `FusionConfig.odometry_bias` the
legs' biases (fusion.bias) join the state after the two poses.
"""

from __future__ import annotations

import gtsam
import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from .bias import bias_prior, corrected_increment, observed_axes
from .steps import (
    FusionConfig,
    StepInputs,
    StepReport,
    check_attitude,
    check_config,
    check_mask_basis,
    check_odometry_sigmas,
    gate_mask,
    legs_covariance,
    masked_information,
    resolve_step,
)
from .tangent import to_gtsam_order, to_project_order


class EKFFusion:
    """Drop-in for `FusionGraph`: `add_step` takes the same inputs and returns the same report."""

    def __init__(self, T_w_0: np.ndarray, config: FusionConfig | None = None):
        self.config = check_config(config or FusionConfig())
        if self.config.robust_kernel is not None:
            raise ValueError("the EKF backend has no robust kernel; use the graph backend for that")
        self.T = gtsam.Pose3(np.asarray(T_w_0, dtype=np.float64))
        self.bias_axes = self.config.odometry_bias
        spread, self._walk = bias_prior(
            self.bias_axes, self.config.odometry_bias_sigmas, self.config.odometry_bias_walk
        )
        self.odometry_bias = np.zeros(len(self.bias_axes))
        self.bias_observed = np.zeros(len(self.bias_axes), dtype=int)  # steps whose ICP observed each bias
        self.gated = 0  # flagged axes kept by the gate (mode "gate")
        # the newest pose's error (GTSAM order), then the biases'
        self.P = np.diag(np.concatenate([to_gtsam_order(np.asarray(self.config.prior_sigmas)), spread]) ** 2)
        self.poses = [self.T.matrix()]
        self.k = 0

    def add_step(
        self,
        odom_T_prev_cur: np.ndarray | None,
        odom_sigmas: np.ndarray | None,
        icp_T_prev_cur: np.ndarray | None = None,
        non_localizable: np.ndarray | None = None,
        icp_hessian: np.ndarray | None = None,
        icp_span: int = 1,
        mask_basis: np.ndarray | None = None,
    ) -> tuple[np.ndarray, StepReport]:
        """`FusionGraph.add_step` as a filter step: the ICP factor updates the axes the mask keeps, on
        the mask's own axes (`mask_basis`)."""
        if icp_span != 1:
            raise ValueError(
                "the EKF keeps the newest pose only: its ICP factor ties consecutive poses (icp_span 1); "
                "registrations onto keyframes need the graph backend"
            )
        step = resolve_step(self.config.mode, odom_T_prev_cur, icp_T_prev_cur, non_localizable)
        nb = len(self.bias_axes)
        G = np.zeros((6, nb))  # how the motion moves with the biases
        basis = check_mask_basis(mask_basis)
        information = None
        observed = np.zeros(nb, dtype=bool)
        if step.has_odom:
            assert odom_T_prev_cur is not None  # resolve_step: has_odom says it is given
            sigmas = check_odometry_sigmas(odom_sigmas)
            motion, G = corrected_increment(odom_T_prev_cur, self.odometry_bias, self.bias_axes)
            observing, information = self._informations(step, (motion, sigmas), icp_hessian, basis)
            observed = observed_axes(G, observing, sigmas, 1, self.config.bias_information_share)
            self.bias_observed += observed
            walked = float(np.linalg.norm(np.asarray(odom_T_prev_cur)[:3, 3]))
        elif step.has_icp:  # no odometry: ICP carries the motion, its masked axes stand still, as in the graph
            held = to_project_order(gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(step.icp_T_prev_cur))))
            motion = gtsam.Pose3.Expmap(to_gtsam_order(np.where(step.still, 0.0, held)))
            sigmas, walked = np.where(step.still, 1.0, np.asarray(self.config.icp_sigmas)), 0.0
        else:
            motion, sigmas, walked = gtsam.Pose3(), np.ones(6), 0.0  # the graph's weak constant-position tie
        P = self.P.copy()
        P[6:, 6:] += np.diag(self._walk**2 * walked)  # the biases wander with the metres walked, as they are read
        Q = np.diag(to_gtsam_order(np.maximum(sigmas, 1e-9)) ** 2)
        # (previous pose, biases) -> (previous pose, current pose, biases)
        M = np.zeros((12 + nb, 6 + nb))
        M[:6, :6] = np.eye(6)
        M[6:12, :6] = motion.inverse().AdjointMap()
        M[6:12, 6:] = G * observed  # a bias this step does not observe is a constant of it, as in the graph
        M[12:, 6:] = np.eye(nb)
        prev, pred = self.T, self.T.compose(motion)
        ekf = ExtendedKalmanFilter(dim_x=12 + nb, dim_z=6)
        ekf.x = np.zeros(12 + nb)
        ekf.P = M @ P @ M.T
        ekf.P[6:12, 6:12] += Q
        if information is not None:
            icp = gtsam.Pose3(np.asarray(step.icp_T_prev_cur))
            self._partial_update(ekf, prev, pred, icp, information, basis, np.r_[np.zeros(12, bool), ~observed])
        self.T = pred.retract(ekf.x[6:12])  # the previous pose is marginalised: a filter does not revise the past
        self.odometry_bias = self.odometry_bias + ekf.x[12:]
        self.P = 0.5 * (ekf.P[6:, 6:] + ekf.P[6:, 6:].T)
        self.k += 1
        self.poses.append(self.T.matrix())
        return self.T.matrix(), step.report()

    def _informations(
        self,
        step: StepInputs,
        legs: tuple[gtsam.Pose3, np.ndarray],
        hessian: np.ndarray | None,
        basis: np.ndarray,
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """As the graph's: the ICP information as the detector masks it, in the body frame, which the
        biases learn from; and as the update takes it, on the mask's axes (with the mode "gate", the
        flagged axes it keeps); None without ICP. `legs`: their step and its sigmas."""
        if not step.has_icp:
            return None, None
        masked = masked_information(self.config, hessian, step.mask, basis)
        kept = self._gated(step, legs[0], legs[1], basis)
        used = masked if (kept == step.mask).all() else masked_information(self.config, hessian, kept, basis)
        return basis.T @ masked @ basis, used

    def _gated(self, step: StepInputs, motion: gtsam.Pose3, sigmas: np.ndarray, basis: np.ndarray) -> np.ndarray:
        """The step's mask; with the mode "gate", of its flagged axes those along which ICP disagrees
        with the legs' step (`steps.gate_mask`, as the graph's over one step)."""
        if self.config.mode != "gate" or not step.mask.any():
            return step.mask
        spread = float(self.config.odometry_bias_sigmas[2])
        scale_sigma = spread  # the legs' spread, or the state's as known now
        if "scale" in self.bias_axes:
            n = 6 + self.bias_axes.index("scale")
            scale_sigma = float(np.sqrt(max(self.P[n, n], 0.0)))
        t = motion.translation()
        covariance = legs_covariance(sigmas, t, t, 1, spread, scale_sigma)
        innovation = to_project_order(gtsam.Pose3.Logmap(motion.between(gtsam.Pose3(np.asarray(step.icp_T_prev_cur)))))
        kept = gate_mask(step.mask, basis, innovation, covariance)
        self.gated += int(step.mask.sum() - kept.sum())
        return kept

    def _partial_update(
        self,
        ekf: ExtendedKalmanFilter,
        prev: gtsam.Pose3,
        pred: gtsam.Pose3,
        icp: gtsam.Pose3,
        information_project: np.ndarray,
        basis_project: np.ndarray,
        frozen: np.ndarray,
    ) -> None:
        """ICP measures T_prev^-1 T_cur; residual Log(rel_pred^-1 icp) ~ d_cur - Ad(rel^-1) d_prev,
        read on the mask's axes (B d, `basis_project`), where `information_project` is written with
        its masked part removed. The update runs along the information's held directions (its
        eigenvectors there), each with its own precision; a direction it does not hold (a masked
        axis, or one the scan leaves free) is left out. The states `frozen` marks (the biases this step
        does not observe) keep their estimate (`consider_update`)."""
        rel = prev.between(pred)
        w, V = np.linalg.eigh(to_gtsam_order(information_project))
        held = w > 1e-12 * max(float(w.max(initial=0.0)), 1e-300)
        rows = V[:, held].T @ to_gtsam_order(basis_project)  # held directions, on the body's tangent
        H = rows @ np.hstack([-rel.inverse().AdjointMap(), np.eye(6), np.zeros((6, ekf.dim_x - 12))])
        z = rows @ gtsam.Pose3.Logmap(rel.between(icp))
        consider_update(ekf, z, H, np.diag(1.0 / w[held]), frozen)

    def add_attitude(self, R_w_b: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
        """`FusionGraph.add_attitude` as a filter update of the newest pose: the residual
        Log(R^-1 R_w_b) is the state's rotation error plus the measurement's, on the measured axes."""
        R, precisions = check_attitude(R_w_b, sigmas)
        keep = precisions > 0
        if keep.any():
            n = len(self.P)
            H = np.hstack([np.eye(3), np.zeros((3, n - 3))])[keep]
            ekf = ExtendedKalmanFilter(dim_x=n, dim_z=int(keep.sum()))
            ekf.x, ekf.P = np.zeros(n), self.P.copy()
            z = gtsam.Rot3.Logmap(self.T.rotation().between(gtsam.Rot3(R)))[keep]
            # an attitude observes no bias: they keep their estimate
            consider_update(ekf, z, H, np.diag(1.0 / precisions[keep]), np.arange(n) >= 6)
            self.T = self.T.retract(ekf.x[:6])
            self.odometry_bias = self.odometry_bias + ekf.x[6:]
            self.P = 0.5 * (ekf.P + ekf.P.T)
            self.poses[-1] = self.T.matrix()
        return self.T.matrix()

    @property
    def newest(self) -> np.ndarray:
        """The newest pose's estimate (4x4)."""
        return np.asarray(self.T.matrix())

    def trajectory(self) -> np.ndarray:
        """The filtered poses (k+1, 4, 4)."""
        return np.array(self.poses)


def consider_update(ekf: ExtendedKalmanFilter, z: np.ndarray, H: np.ndarray, R: np.ndarray, frozen: np.ndarray) -> None:
    """The filter's update of its error state by the linear measurement z = H x + v (v ~ R), the
    states `frozen` marks left where they are (a Schmidt-Kalman "consider" update: their gain is zero,
    their covariance and their correlation with the others still count). Written here because
    filterpy's filters have no consider states; where none is frozen it is filterpy's own update."""
    ekf.dim_z = len(z)
    if not frozen.any():
        ekf.update(z, lambda x: H, lambda x: H @ x, R=R)
        return
    P = ekf.P
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    K[frozen] = 0.0
    ekf.x = ekf.x + K @ (z - H @ ekf.x)
    I_KH = np.eye(len(P)) - K @ H
    ekf.P = I_KH @ P @ I_KH.T + K @ R @ K.T  # Joseph's form: right for any gain
