"""The one per-step localization pipeline: register the new scan to the last (`ScanRegistrar`),
ask the detector which axes to trust, and add the leg odometry and the masked ICP factor to the
fusion backend (`LocalizationPipeline`). The environments (`OnlineFusion`), `l3e ate` and the
policies' evaluation all step through these two classes.

`EnvConfig.fusion` switches it on in an environment; `info` then carries the fused estimate, the
detector's probabilities and mask, and the running ATE against ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from fusion import EKFFusion, FusionConfig, FusionGraph, check_backend, make_fusion, plane_in_frame
from l3e_env.config import GROUND_MODES, FusionSettings, OdometryConfig, from_dict
from l3e_env.core.threads import part_threads
from l3e_env.core.transforms import (
    adjoint,
    inverse,
    level_rotation_of,
    nearest_rigid,
    rotation_angle,
    rotation_pose,
)
from l3e_env.localizability.registration import (
    PreparedTarget,
    RegistrationConfig,
    RegistrationError,
    RegistrationResult,
    register,
)
from l3e_env.localizability.up import ground_plane
from l3e_env.sim.imu import ATTITUDE_EVERY, attitude_sigmas
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.odometry import odometry_fusion_config, odometry_sigmas

from .ahead import DetectorProcess
from .detectors import UNKNOWN, Detector, Prediction, make_detector, registration_of, safe_predict


@dataclass(frozen=True)
class Keyframes:
    """When a registrar's keyframe is renewed: once the scans registered onto it have moved `distance`
    metres (as registered, or as the legs walked, whichever is more) or turned `turn` radians from
    it, or `steps` scans have been registered onto it; or where one failed to register, or moved
    from the guess (the last registration advanced by the legs' step) by more than `gate` metres or
    `gate_turn` radians (about twice the 99th percentile of that move on the bypass's way round).
    In a degenerate place the registration slides back towards the keyframe along the axis it cannot
    hold, and one scan that the detector does not flag would hand the fusion that slide whole: the
    fusion renews the keyframe at every scan its detector flags (`keyframe_here`), and the gate
    catches a slide where no detector is asked. A distance of 0 registers each scan to the one
    before (no keyframes)."""

    distance: float = 0.0
    turn: float = 0.8
    steps: int = 100
    gate: float = 0.05
    gate_turn: float = 0.02

    def __post_init__(self) -> None:
        if not (self.distance >= 0 and self.turn > 0 and self.steps >= 1 and self.gate > 0 and self.gate_turn > 0):
            raise ValueError(
                "keyframes: a distance of at least 0 m, a turn, a gate and a gate's turn above 0 and at least "
                f"1 step, got {self}"
            )

    @property
    def enabled(self) -> bool:
        return self.distance > 0


class ScanRegistrar:
    """Each scan registered to an earlier one: `start` with the first scan, then `next` with each
    new one. None where registration is impossible (too few points). A target scan is prepared
    (normals, k-d tree: the step's largest cost) on `threads` threads, by default as many as the
    ray casting uses (`part_threads()`).

    Without keyframes, scan k onto scan k-1 from identity, as the labels are made. With them
    (`Keyframes`), onto the last keyframe, from the pose since it that the registrations before
    give, advanced by the step's `motion` (the odometry's, in the sensor frame), matched in the
    registration's fine stage alone: its coarse stage's matches, meant for a start from identity,
    pull a weakly held axis away from a good guess. A scan-to-scan step's small bias adds up at
    every scan; onto a keyframe it adds up once a keyframe (studies/keyframe_drift.py)."""

    def __init__(self, config: RegistrationConfig, threads: int | None = None, keyframes: Keyframes | None = None):
        self.config = config
        self.threads = threads if threads is not None else part_threads()
        self.keyframes = keyframes or Keyframes()
        # from a guess: the last stage of the coarse-to-fine schedule only
        self._from_guess = replace(config, max_correspondence_distance=config.max_correspondence_distance[-1:])
        self.target: PreparedTarget | None = None
        self._since = np.eye(4)  # the newest scan's pose in the keyframe's sensor frame
        self._span = 0  # scans registered onto the keyframe
        self._walked = 0.0  # metres the legs' steps have moved the sensor since the keyframe
        self._last: np.ndarray | None = None  # the newest scan

    def _prepare(self, points: np.ndarray) -> PreparedTarget | None:
        try:
            return PreparedTarget(points, self.config, self.threads)
        except RegistrationError:
            return None

    def start(self, points: np.ndarray) -> None:
        self.target = self._prepare(points)
        self._since, self._span, self._walked = np.eye(4), 0, 0.0

    @property
    def ground(self) -> np.ndarray | None:
        """The keyframe's ground plane (n, d in its sensor frame), where one was found."""
        return None if self.target is None else self.target.ground

    def first_ground(self, points: np.ndarray) -> np.ndarray | None:
        """The first scan's ground plane, which ties the fusion's first ground patch to the start pose:
        the keyframe's fit, or where that found none (a floor whose candidates furniture shares), the
        search for the best-held plane that levels a user's scans (`localizability.up`), once a drive."""
        if self.ground is not None:
            return self.ground
        found = ground_plane(points)
        return None if found is None else np.r_[found[0], found[1]]

    def next(self, points: np.ndarray, motion: np.ndarray | None = None) -> RegistrationResult | None:
        """The registration of `points` onto the keyframe (the scan before, without keyframes);
        `motion`: the sensor's motion since the scan before (4x4), the guess's step with keyframes."""
        if not self.keyframes.enabled:
            result = self._register(points, self.config, None)
            self.target = self._prepare(points)
            return self._with_ground(result)
        self._span, self._last = self._span + 1, points
        self._walked += 0.0 if motion is None else float(np.linalg.norm(motion[:3, 3]))
        guess = nearest_rigid(self._since @ motion) if motion is not None else self._since
        result = self._register(points, self._from_guess, guess)
        ok = result is not None and result.converged
        self._since = result.T_target_source if ok and result is not None else guess
        if not ok or self._renew() or self._beyond_gate(guess):
            self.start(points)
            return self._with_ground(result)
        return result

    def keyframe_here(self) -> np.ndarray | None:
        """The newest scan becomes the keyframe (where the detector flagged an axis of it); returns
        its ground plane where it became one and a plane was found (see `RegistrationResult.ground`)."""
        if self.keyframes.enabled and self._span > 0 and self._last is not None:
            self.start(self._last)
            return self.ground
        return None

    def _with_ground(self, result: RegistrationResult | None) -> RegistrationResult | None:
        """The registration of the scan just prepared as the target, with that scan's ground plane."""
        if result is None or self.target is None or self.target.ground is None:
            return result
        return replace(result, ground=self.target.ground)

    def _register(
        self, points: np.ndarray, config: RegistrationConfig, guess: np.ndarray | None
    ) -> RegistrationResult | None:
        if self.target is None:
            return None
        try:
            result = register(points, self.target, config, init_T_target_source=guess)
        except RegistrationError:
            return None
        return replace(result, span=max(self._span, 1))

    def _renew(self) -> bool:
        k = self.keyframes
        moved = max(float(np.linalg.norm(self._since[:3, 3])), self._walked)
        return bool(moved >= k.distance or rotation_angle(self._since) >= k.turn or self._span >= k.steps)

    def _beyond_gate(self, guess: np.ndarray) -> bool:
        off = inverse(guess) @ self._since
        return bool(np.linalg.norm(off[:3, 3]) > self.keyframes.gate or rotation_angle(off) > self.keyframes.gate_turn)


@dataclass
class StepOutcome:
    T_w_b: np.ndarray  # the fused estimate of the body after the step
    prediction: Prediction  # the detector's answer for the new scan
    detector_failed: bool  # the detector raised: its answer is UNKNOWN
    icp_used: bool  # the registration gave an ICP factor (it converged, in the body frame)
    fallback: bool  # the fusion had to fall back (no odometry and every axis masked, or neither)


def level_basis(T_w_b: np.ndarray, T_b_s: np.ndarray) -> np.ndarray:
    """The 6x6 map (project order) from a body-frame step's tangent onto the axes of the sensor's level
    frame at body pose T_w_b (the estimator's; only its tilt counts): where the detector's mask names
    its axes, so that the fusion removes a level tunnel's slide along its length, not along the tilted
    sensor's x and z."""
    return adjoint(rotation_pose(level_rotation_of(T_w_b @ T_b_s)) @ inverse(T_b_s))


class LocalizationPipeline:
    """Detect and fuse, one step at a time, along one drive: `start` at the first pose, then `step`
    with each step's odometry increment and registration (from a `ScanRegistrar`). The detector judges
    the first scan and every `detector_every`-th after it; its answer holds in between."""

    def __init__(
        self,
        detector: Detector,
        backend: str,
        fusion: FusionConfig,
        odometry: OdometryConfig,
        T_b_s: np.ndarray,
        attitude: str = "none",
        detector_every: int = 1,
        ground: str = "none",
    ):
        check_backend(backend)
        if detector_every < 1:
            raise ValueError(f"the detector judges every detector_every >= 1 steps, got {detector_every}")
        if ground not in GROUND_MODES or (ground == "plane" and backend != "graph"):
            raise ValueError(f"ground is one of {GROUND_MODES}, and 'plane' needs the graph backend; got {ground!r}")
        self.ground = ground == "plane"
        self.detector_every = detector_every
        self._held: tuple[Prediction, bool] | None = None
        self.detector, self.backend_name, self.fusion, self.odometry = detector, backend, fusion, odometry
        self.T_b_s = T_b_s
        self.attitude_sigmas = attitude_sigmas(attitude, correlated=False)  # each reading as independent
        self._correlated_sigmas = attitude_sigmas(attitude, correlated=True)
        self.attitude_mode = attitude
        self._backend: FusionGraph | EKFFusion | None = None
        self.steps = 0

    def start(self, T_w_b: np.ndarray, ground: np.ndarray | None = None) -> None:
        """The drive's first pose, and its scan's ground plane (n, d in the sensor frame) where one was found."""
        self._backend = make_fusion(self.backend_name, T_w_b, self.fusion)
        self.steps = 0
        self._held = None
        if ground is not None:
            self.add_ground(ground, T_w_b)

    def judges_next(self) -> bool:
        """Whether the next `step` asks the detector (else its last answer holds)."""
        return self._held is None or self.steps % self.detector_every == 0

    @property
    def backend(self) -> FusionGraph | EKFFusion:
        """The estimator of the drive begun by `start`."""
        if self._backend is None:
            raise RuntimeError("the pipeline has no drive yet: call start(T_w_b) with the first pose before step()")
        return self._backend

    def step(
        self,
        odom_increment: np.ndarray,
        registration: RegistrationResult | None,
        detector_points: np.ndarray,
        T_w_s: np.ndarray | None,
        attitude: np.ndarray | None = None,
        judged: tuple[Prediction, bool] | None = None,
    ) -> StepOutcome:
        """`detector_points`: what the detector judges (the new scan, or the classifier's sample of
        it); `T_w_s`: the sensor's pose where a detector needs one (the oracle, a model reading the
        tilt); `attitude`: the IMU's orientation of the body (3x3), fused every ATTITUDE_EVERY steps
        where the pipeline was built with an attitude mode; `judged`: the detector's answer and
        whether it failed, where it was judged elsewhere (a DetectorProcess). On a step the detector
        does not judge (`judges_next`), its last answer holds and `judged` is not read."""
        if self.judges_next():
            self._held = judged or safe_predict(self.detector, detector_points, registration, T_w_s)
            pred, failed = self._held
        else:
            pred, failed = self._held[0] if self._held is not None else UNKNOWN, False
        self.steps += 1
        icp, hessian = (registration.in_frame(self.T_b_s) if registration is not None else None) or (None, None)
        sigmas = odometry_sigmas(odom_increment, self.odometry)
        span = registration.span if registration is not None else 1
        guess = next((m for m in (odom_increment, icp) if m is not None and np.isfinite(m).all()), np.eye(4))
        basis = level_basis(self.backend.newest @ guess, self.T_b_s)  # the new pose's level frame, as guessed
        T, report = self.backend.add_step(odom_increment, sigmas, icp, pred.mask, hessian, span, basis)
        if self.attitude_sigmas is not None and self.steps % ATTITUDE_EVERY == 0:
            if attitude is None:
                raise ValueError(f"fusion.attitude is {self.attitude_mode!r}: every step needs the IMU's attitude")
            T = self.backend.add_attitude(attitude, self.attitude_weights())
        if registration is not None and registration.ground is not None:
            T = self.add_ground(registration.ground, T)
        return StepOutcome(T, pred, failed, icp is not None, report.fallback is not None)

    def attitude_weights(self) -> np.ndarray:
        """The sigmas the IMU's next reading takes: weighed as the correlated reading it is while a
        ground patch holds the tilt and height (seen within `fusion.ground.HOLDS_STEPS`), else as an
        independent one, over-sure of the readings' mean, which is then what holds the tilt against the
        registrations' chain (docs/decisions.md, "Fusion")."""
        assert self.attitude_sigmas is not None and self._correlated_sigmas is not None  # step(): an attitude mode
        held = self.ground and isinstance(self.backend, FusionGraph) and self.backend.ground.holds(self.backend.k)
        return self._correlated_sigmas if held else self.attitude_sigmas

    def add_ground(self, plane_s: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
        """The newest scan's ground plane (n, d in the sensor frame) as a measurement of the ground
        patch under the robot (fusion.ground), where the pipeline takes the ground; returns the
        newest pose's estimate (`T_w_b` where it does not)."""
        if not self.ground:
            return T_w_b
        assert isinstance(self.backend, FusionGraph)  # __init__: the ground needs the graph
        return self.backend.add_ground(plane_in_frame(plane_s, self.T_b_s))

    def trajectory(self) -> np.ndarray:
        return self.backend.trajectory()


# steps (20 s at 10 Hz) the environment's graph keeps before marginalizing: twice a keyframe's longest
# run (Keyframes.steps), as an ICP factor must reach its keyframe within half the window
ONLINE_LAG = 200
# the window relinearizes a state once its estimate has moved 0.1 (rad or m) from its linearization
# point, GTSAM's default; FusionConfig's 0.01 is the whole drive's, whose smoothed trajectory is scored,
# and relinearizes the window far more often (docs/fusion.md)
ONLINE_RELINEARIZE = 0.1


class OnlineFusion:
    """The pipeline inside an environment: one run along an episode; `reset` at every episode start."""

    def __init__(
        self,
        config: FusionSettings,
        lidar: Lidar,
        odometry: OdometryConfig,
        T_b_s: np.ndarray,
        seed: int = 0,
        registration: RegistrationConfig | dict | None = None,
    ):
        self.config, self.T_b_s = config, T_b_s
        detector = make_detector(config.detector, lidar, seed)
        if isinstance(registration, dict):
            registration = from_dict(RegistrationConfig, registration)
        # with the classifier in a process of its own, the target is prepared on one thread: the other core is its
        self.registrar = ScanRegistrar(
            registration or registration_of([detector]),
            threads=1 if config.detector_process else None,
            keyframes=Keyframes(distance=config.keyframe_distance or 0.0),  # set by its __post_init__
        )
        # an environment reports the newest estimate only: the graph keeps a window (bounded cost per step)
        self.pipeline = LocalizationPipeline(
            detector,
            config.backend,
            odometry_fusion_config(odometry, config, smoother_lag=ONLINE_LAG, relinearize_threshold=ONLINE_RELINEARIZE),
            odometry,
            T_b_s,
            config.attitude,
            config.detector_every,
            config.ground or "none",  # set by its __post_init__
        )
        # the classifier beside the registration, in a process of its own (detection.ahead)
        self.ahead = DetectorProcess(config.detector, lidar.config, seed) if config.detector_process else None

    @property
    def detector(self) -> Detector:
        return self.pipeline.detector

    @property
    def registration(self) -> RegistrationConfig:
        return self.registrar.config

    @property
    def fusion_config(self) -> FusionConfig:
        """The estimator's settings, made from `FusionSettings` and the odometry's noise model."""
        return self.pipeline.fusion

    @property
    def backend(self) -> Any:
        """The fusion backend of the current episode (a FusionGraph or an EKFFusion)."""
        return self.pipeline.backend

    def reset(self, T_w_b: np.ndarray, points: np.ndarray) -> dict[str, Any]:
        self.registrar.start(points)
        self.pipeline.start(T_w_b, self.registrar.first_ground(points) if self.pipeline.ground else None)
        self.squared_errors: list[float] = [0.0]
        self.counts = {"icp_failed": 0, "unknown": 0, "detector_errors": 0, "fallbacks": 0}
        return self._info(T_w_b, UNKNOWN)

    def step(
        self, odom_increment: np.ndarray, points: np.ndarray, T_w_b_true: np.ndarray, attitude: np.ndarray | None = None
    ) -> dict[str, Any]:
        """`attitude`: the IMU's orientation of the body (3x3), fused every ATTITUDE_EVERY steps
        where `FusionSettings.attitude` asks for it."""
        T_w_s = T_w_b_true @ self.T_b_s
        ahead = self.ahead if self.pipeline.judges_next() else None  # a held answer asks no process
        if ahead is not None:
            ahead.submit(points, T_w_s)
        motion = inverse(self.T_b_s) @ odom_increment @ self.T_b_s  # the sensor's, the keyframe guess's step
        registration = self.registrar.next(points, motion)
        judged = ahead.result() if ahead is not None else None
        out = self.pipeline.step(odom_increment, registration, points, T_w_s, attitude, judged)
        if out.prediction.mask.any() or not out.prediction.known:  # a degenerate place: no keyframe behind it
            ground = self.registrar.keyframe_here()
            if ground is not None:
                out = replace(out, T_w_b=self.pipeline.add_ground(ground, out.T_w_b))
        self.counts["icp_failed"] += not out.icp_used
        self.counts["detector_errors"] += out.detector_failed
        self.counts["unknown"] += not out.prediction.known
        self.counts["fallbacks"] += out.fallback
        self.squared_errors.append(float(np.sum((out.T_w_b[:3, 3] - T_w_b_true[:3, 3]) ** 2)))
        return self._info(out.T_w_b, out.prediction)

    def close(self) -> None:
        if self.ahead is not None:
            self.ahead.close()

    def _info(self, T: np.ndarray, pred: Prediction) -> dict[str, Any]:
        return {
            "fused_T_w_b": T.copy(),
            "localizability_probabilities": pred.probabilities.copy(),
            "localizability_mask": pred.mask.copy(),
            "localizability_known": pred.known,
            "running_ate": float(np.sqrt(np.mean(self.squared_errors))),
            "fusion_counts": dict(self.counts),
        }
