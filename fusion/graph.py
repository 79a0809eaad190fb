"""iSAM2 fusion of leg odometry with scan-to-scan ICP factors whose non-localizable axes are masked.

A masked axis gets zero information in the ICP factor's noise model (its rows and columns of the
registration's Hessian, or of the fixed diagonal), so the factor says nothing along it and the
odometry alone decides there. This is the L3E use of the mask.
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np

from .bias import BIAS_KNOT_METRES, bias_prior, corrected_increment, observed_axes, odometry_bias_factor
from .ground import GroundPatches, check_ground_sigmas, check_plane, ground_key
from .steps import (
    FusionConfig,
    StepInputs,
    StepReport,
    check_attitude,
    check_config,
    check_mask_basis,
    check_odometry_sigmas,
    gate_mask,
    icp_information,
    legs_covariance,
    resolve_step,
)
from .tangent import to_gtsam_order, to_project_order


class FusionError(RuntimeError):
    """GTSAM could not solve a step (an under-determined or degenerate system): the message names the step."""


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


def bias_key(n: int) -> int:
    """The key of the n-th odometry bias state (poses are keyed by their index)."""
    return gtsam.symbol("b", n)


class FusionGraph:
    """One Pose3 per scan; `add_step` adds odometry and (masked) ICP between-factors. With
    `FusionConfig.odometry_bias`, a bias vector per metre walked too (fusion.bias), each tied to the
    last by its random walk; `odometry_bias` is the newest one's estimate, in the config's axis order."""

    def __init__(self, T_w_0: np.ndarray, config: FusionConfig | None = None):
        self.config = check_config(config or FusionConfig())
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        # QR, not GTSAM's default Cholesky: a long drive's newest pose is known far less well than each
        # step (its marginal grows with the drive while the factors stay sharp), and Cholesky, which
        # squares that condition number, meets an indeterminate system after a few thousand steps.
        params.setFactorization("QR")
        self.lag = self.config.smoother_lag
        # with a lag, the poses that left the window keep the estimate they had when they left
        self.isam: Any = (  # ISAM2 or the fixed-lag smoother: the same update and estimate calls
            gtsam.ISAM2(params) if self.lag is None else gtsam.IncrementalFixedLagSmoother(float(self.lag), params)
        )
        self._left: list[np.ndarray] = []
        self.k = 0
        self.estimate = _pose3(T_w_0)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        prior = gtsam.noiseModel.Diagonal.Sigmas(to_gtsam_order(np.asarray(self.config.prior_sigmas)))
        graph.add(gtsam.PriorFactorPose3(0, self.estimate, prior))
        values.insert(0, self.estimate)
        self.bias_axes = self.config.odometry_bias
        spread, self._walk = bias_prior(
            self.bias_axes, self.config.odometry_bias_sigmas, self.config.odometry_bias_walk
        )
        self.odometry_bias = np.zeros(len(self.bias_axes))
        self.bias_observed = np.zeros(len(self.bias_axes), dtype=int)  # steps whose ICP observed each bias
        self.gated = 0  # flagged axes kept by the gate (mode "gate")
        self._scale_known = (-1, 0.0)  # (bias state, the scale's sigma there): see _scale_sigma
        self._knot, self._walked = 0, 0.0
        # a ground patch unseen for half the window may be marginalized before it is seen again
        self.ground = GroundPatches(None if self.lag is None else self.lag // 2)
        if self.bias_axes:
            spread_noise = gtsam.noiseModel.Diagonal.Sigmas(spread)
            graph.add(gtsam.PriorFactorVector(bias_key(0), self.odometry_bias, spread_noise))
            values.insert(bias_key(0), self.odometry_bias)
        self._update(graph, values, 0)

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, k: int) -> None:
        try:
            if self.lag is None:
                self.isam.update(graph, values)
            else:  # every state the new factors touch is stamped with this step: the bias state in use stays
                stamp = self._stamp(k)
                self._keep_leaving(stamp)
                self.isam.update(graph, values, {key: stamp for key in graph.keyVector()})
        except RuntimeError as exc:  # GTSAM's C++ exceptions (IndeterminantLinearSystem, ...) arrive as this
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise FusionError(
                f"fusion step {k}: GTSAM could not solve the graph ({first}); this graph cannot take more steps"
            ) from exc

    def _stamp(self, k: int) -> float:
        """The smoother's time of step k: the step rounded down to a multiple of `marginalize_every`,
        so that the poses leave the window in batches. GTSAM's smoother re-eliminates its whole window
        whenever it marginalizes (its ordering puts the leaving states first): once a step, that
        re-elimination dominated the step's cost (docs/fusion.md)."""
        return float(k - k % self.config.marginalize_every)

    def _keep_leaving(self, stamp: float) -> None:
        """Before an update stamped `stamp`: the estimates of the poses it marginalizes (GTSAM's
        smoother drops the states stamped before stamp - lag; pose m was last stamped by step m + 1
        at the latest)."""
        assert self.lag is not None  # only the windowed smoother marginalizes
        while self._stamp(len(self._left) + 1) < stamp - self.lag:
            self._left.append(self.isam.calculateEstimatePose3(len(self._left)).matrix())

    def _noise(self, information_project: np.ndarray) -> gtsam.noiseModel.Base:
        """Precisions (6) or an information matrix (6x6), project order; zeros say nothing."""
        information = to_gtsam_order(information_project)
        base: gtsam.noiseModel.Base
        if information.ndim == 1 or not (information - np.diag(np.diag(information))).any():
            precisions = information if information.ndim == 1 else np.diag(information)
            base = gtsam.noiseModel.Diagonal.Precisions(np.where(precisions > 0.0, precisions, 0.0))  # no -0.0
        else:  # a square root of the information; its zero eigenvalues (masked axes) say nothing
            w, V = np.linalg.eigh(information)
            root = np.sqrt(np.where(w > 0.0, w, 0.0))[:, None] * V.T
            base = gtsam.noiseModel.Gaussian.SqrtInformation(root, False)  # GTSAM's "smart" test refuses zero rows
        kernel = self.config.robust_kernel
        if kernel is None:
            return base
        est: Any = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[kernel]
        return gtsam.noiseModel.Robust.Create(est.Create(self.config.robust_threshold), base)

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
        """Add pose k+1 with its factors; returns (estimate of pose k+1, report). `icp_hessian`:
        the registration's point-to-plane Hessian in the body frame, project order (see
        FusionConfig.icp_covariance). `mask_basis`: the axes `non_localizable` names (see
        `icp_information`; the body frame's own where None). `icp_span`: the ICP factor ties pose
        k+1 to pose k+1-icp_span (a keyframe's; 1: pose k), which must still be in the smoother's
        window.

        Missing odometry with every ICP axis masked leaves the new pose unconstrained: then the
        ICP factor is kept whole (documented fallback), and with no ICP either the pose is tied to
        the previous one by a weak constant-position factor; with some axes masked, those axes are.
        Every pose is held on every axis, so a step never fails for that.
        """
        step = resolve_step(self.config.mode, odom_T_prev_cur, icp_T_prev_cur, non_localizable)
        has_odom, has_icp, icp_T_prev_cur = step.has_odom, step.has_icp, step.icp_T_prev_cur
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        i, j = self.k, self.k + 1
        key = self._icp_key(j, icp_span)
        observing, information = self._icp_informations(
            step, odom_T_prev_cur, (icp_hessian, odom_sigmas), key, mask_basis
        )
        odometry = (
            self._add_odometry(graph, values, odom_T_prev_cur, odom_sigmas, (i, j), (observing, icp_span))
            if has_odom
            else None
        )
        if information is not None:
            assert icp_T_prev_cur is not None
            graph.add(gtsam.BetweenFactorPose3(key, j, _pose3(icp_T_prev_cur), self._noise(information)))
        if step.still.any():  # the axes nothing else holds stay where they were, weakly (sigma 1 m and 1 rad)
            graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(), self._noise(step.still.astype(np.float64))))
        guess = (
            self.estimate.compose(odometry)
            if odometry is not None
            else (
                (self.estimate if key == i else self.isam.calculateEstimatePose3(key)).compose(_pose3(icp_T_prev_cur))
                if has_icp and icp_T_prev_cur is not None
                else self.estimate
            )
        )
        values.insert(j, guess)
        self.ground.moved(self.estimate.between(guess))
        self._update(graph, values, j)
        self.k = j
        self.estimate = self.isam.calculateEstimatePose3(j)
        if self.bias_axes:
            self.odometry_bias = np.asarray(self.isam.calculateEstimateVector(bias_key(self._knot)), dtype=np.float64)
        return self.estimate.matrix(), step.report()

    def _icp_informations(
        self,
        step: StepInputs,
        odom_T_prev_cur: np.ndarray | None,
        weights: tuple[np.ndarray | None, np.ndarray | None],
        key: int,
        basis: np.ndarray | None,
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The ICP factor's information as the detector masks it, which the biases learn from, and as
        it is fused (the mode "gate": with the flagged axes it keeps, `_gate`); None without ICP.
        `weights`: ICP's Hessian and the legs' sigmas. An axis the gate keeps teaches no bias: it
        agrees with the legs' prediction, which their biases make, and its small slides would teach
        them a wrong one."""
        if not step.has_icp:
            return None, None
        hessian, sigmas = weights
        masked = icp_information(self.config, hessian, step.mask, basis)
        if self.config.mode != "gate" or not step.has_odom or not step.mask.any():
            return masked, masked
        assert step.icp_T_prev_cur is not None and odom_T_prev_cur is not None  # resolve_step: has_icp, has_odom
        legs = self._legs_step(odom_T_prev_cur)
        kept = self._gate(step.mask, (legs, _pose3(step.icp_T_prev_cur)), sigmas, key, basis)
        return masked, masked if (kept == step.mask).all() else icp_information(self.config, hessian, kept, basis)

    def _legs_step(self, odom_T_prev_cur: np.ndarray) -> gtsam.Pose3:
        """The legs' increment as their present bias estimate corrects it."""
        if not self.bias_axes:
            return _pose3(odom_T_prev_cur)
        return corrected_increment(odom_T_prev_cur, self.odometry_bias, self.bias_axes)[0]

    def _gate(
        self,
        mask: np.ndarray,
        steps: tuple[gtsam.Pose3, gtsam.Pose3],
        sigmas: np.ndarray | None,
        key: int,
        basis: np.ndarray | None,
    ) -> np.ndarray:
        """The mode "gate": of the flagged axes, those along which ICP's motion from pose `key` disagrees
        with the legs' prediction, the estimate advanced by their step (`steps.gate_mask`). `steps`: the
        legs' and ICP's; `sigmas`: the legs' of this step, their covariance over the factor's span
        `steps.legs_covariance`, the scale as the graph knows it now (`_scale_sigma`)."""
        legs, icp = steps
        start = self.estimate if key == self.k else self.isam.calculateEstimatePose3(key)
        predicted = start.between(self.estimate.compose(legs))
        innovation = to_project_order(gtsam.Pose3.Logmap(predicted.between(icp)))
        across = predicted.inverse().translation()  # the span's length, seen from the new pose
        spread = float(self.config.odometry_bias_sigmas[2])
        covariance = legs_covariance(
            check_odometry_sigmas(sigmas), legs.translation(), across, self.k + 1 - key, spread, self._scale_sigma()
        )
        kept = gate_mask(mask, check_mask_basis(basis), innovation, covariance)
        self.gated += int(mask.sum() - kept.sum())
        return kept

    def _scale_sigma(self) -> float:
        """How well the fusion knows the stride's scale now: the marginal of the bias state in use
        (computed once a state), or the legs' prior spread where the scale is not a state. A scale learnt
        where ICP held the length narrows the gate where it no longer does."""
        if "scale" not in self.bias_axes:
            return float(self.config.odometry_bias_sigmas[2])
        if self._scale_known[0] != self._knot:
            covariance = self.isam.marginalCovariance(bias_key(self._knot))
            n = self.bias_axes.index("scale")
            self._scale_known = (self._knot, float(np.sqrt(max(covariance[n, n], 0.0))))
        return self._scale_known[1]

    def _add_odometry(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        odom_T_prev_cur: np.ndarray | None,
        odom_sigmas: np.ndarray | None,
        poses: tuple[int, int],
        icp: tuple[np.ndarray | None, int],
    ) -> gtsam.Pose3:
        """The legs' factor from pose i to j (through the bias state in use, with its knot where one
        is due; only the biases that the step's ICP factor, its information and span `icp`, observes
        are variables of it: fusion.bias.observed_axes); returns the increment as the factor reads it,
        the new pose's guess."""
        assert odom_T_prev_cur is not None  # resolve_step: has_odom says it is given
        i, j = poses
        sigmas = check_odometry_sigmas(odom_sigmas)
        noise = self._noise(1.0 / np.maximum(sigmas, 1e-9) ** 2)
        if not self.bias_axes:
            odometry = _pose3(odom_T_prev_cur)
            graph.add(gtsam.BetweenFactorPose3(i, j, odometry, noise))
            return odometry
        self._next_bias_knot(float(np.linalg.norm(odom_T_prev_cur[:3, 3])), graph, values)
        corrected, G = corrected_increment(odom_T_prev_cur, self.odometry_bias, self.bias_axes)
        observed = observed_axes(G, icp[0], sigmas, icp[1], self.config.bias_information_share)
        self.bias_observed += observed
        if observed.any():
            key = bias_key(self._knot)
            held = self.odometry_bias
            graph.add(odometry_bias_factor(odom_T_prev_cur, i, j, key, noise, self.bias_axes, observed, held))
        else:  # nothing here observes the biases: the legs' step as their present estimate corrects it
            graph.add(gtsam.BetweenFactorPose3(i, j, corrected, noise))
        return corrected

    def _icp_key(self, j: int, span: int) -> int:
        """The pose an ICP factor of `span` steps ties pose j to, or a ValueError where there is none
        (before the first pose, or outside the smoother's window)."""
        if not isinstance(span, (int, np.integer)) or span < 1 or span > j:
            raise ValueError(f"an ICP factor spans 1 to {j} steps back from pose {j}, not {span}")
        if self.lag is not None and span > self.lag // 2:
            raise ValueError(
                f"an ICP factor of {span} steps reaches beyond half the smoother's window of {self.lag} steps: "
                "renew keyframes sooner, or widen FusionConfig.smoother_lag"
            )
        return j - int(span)

    def _next_bias_knot(self, walked: float, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Count the metres walked on the present bias state; past BIAS_KNOT_METRES start the next,
        tied to it by the random walk over those metres (standing still starts none)."""
        self._walked += walked
        if self._walked < BIAS_KNOT_METRES:
            return
        walk = gtsam.noiseModel.Diagonal.Sigmas(self._walk * np.sqrt(self._walked))
        graph.add(
            gtsam.BetweenFactorVector(
                bias_key(self._knot), bias_key(self._knot + 1), np.zeros(len(self.bias_axes)), walk
            )
        )
        self._knot, self._walked = self._knot + 1, 0.0
        values.insert(bias_key(self._knot), self.odometry_bias)

    def add_attitude(self, R_w_b: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
        """An absolute orientation of the newest pose, as an IMU gives it (roll and pitch from
        gravity; the heading from a magnetometer, or inf where there is none): a prior on the
        pose's rotation only, its translation left free. Returns the new estimate of that pose."""
        R, precisions = check_attitude(R_w_b, sigmas)
        T = self.estimate.matrix()
        T[:3, :3] = R
        noise = gtsam.noiseModel.Diagonal.Precisions(to_gtsam_order(np.concatenate([np.zeros(3), precisions])))
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(self.k, _pose3(T), noise))
        self._update(graph, gtsam.Values(), self.k)
        self.estimate = self.isam.calculateEstimatePose3(self.k)
        return self.estimate.matrix()

    def add_ground(self, plane_b: np.ndarray) -> np.ndarray:
        """The ground plane (n, d; n . p = d, body frame) that the newest pose's scan fitted under it,
        as a measurement of the ground patch it stands on (fusion.ground), with the config's
        `ground_sigmas`. Returns the new estimate of that pose."""
        measured = check_plane(plane_b)
        normal_sigma, distance_sigma = check_ground_sigmas(self.config.ground_sigmas)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if self.ground.patch(self.estimate, measured, self.k):  # a new patch, where this pose sees it
            assert self.ground.plane is not None  # patch(): a new patch's plane is set
            values.insert(ground_key(self.ground.index), self.ground.plane)
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([normal_sigma, normal_sigma, distance_sigma]))
        coefficients = np.r_[measured[:3], -measured[3]]  # GTSAM's n . p + d = 0
        graph.add(gtsam.OrientedPlane3Factor(coefficients, noise, self.k, ground_key(self.ground.index)))
        self._update(graph, values, self.k)
        self.estimate = self.isam.calculateEstimatePose3(self.k)
        return self.estimate.matrix()

    @property
    def newest(self) -> np.ndarray:
        """The newest pose's estimate (4x4)."""
        return np.asarray(self.estimate.matrix())

    def trajectory(self) -> np.ndarray:
        """All smoothed poses (k+1, 4, 4); with a lag, those that left the window as they left it."""
        values = self.isam.calculateEstimate()
        return np.array(self._left + [values.atPose3(k).matrix() for k in range(len(self._left), self.k + 1)])
