"""A recorded drive fused with each detector's mask, scored against the truth (`fuse_recording`,
`DetectorResult`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields

import numpy as np
from tqdm import tqdm

from fusion import (
    FusionConfig,
    MetricError,
    ate,
    ate_aligned,
    check_backend,
    rpe,
)
from l3e_env.config import FusionSettings, OdometryConfig, RobotConfig
from l3e_env.detection.detectors import (
    Detector,
)
from l3e_env.detection.pipeline import LocalizationPipeline
from l3e_env.sim.imu import attitude_readings, attitude_sigmas
from l3e_env.sim.odometry import odometry_fusion_config

from .drive import DriveRecord


@dataclass
class FusedRun:
    """A trajectory the fusion made (or an odometry gave) and what its detector did at each step."""

    name: str
    trajectory: np.ndarray
    masks: np.ndarray  # (N, 6) bool
    probabilities: np.ndarray  # (N, 6)
    seconds: float = 0.0
    unknown_steps: int = 0
    fallback_steps: int = 0
    detector_errors: int = 0
    # per bias state of the legs (fusion.bias): the share of steps whose ICP observed it (a state never
    # observed kept its prior); and the flagged axes the gate kept (FusionConfig.mode "gate")
    observed: dict[str, float] = field(default_factory=dict)
    gated_axes: int = 0


@dataclass
class DetectorResult(FusedRun):
    """A fused run scored against the ground truth (`scored`)."""

    ate: float = float("nan")
    ate_aligned: float | None = None
    rpe_translation: float = float("nan")
    rpe_rotation: float = float("nan")


def fuse_recording(
    rec: DriveRecord,
    detectors: list[Detector],
    registrations: list,
    fusion: FusionConfig | None = None,
    odometry: OdometryConfig | None = None,
    progress: bool = True,
    settings: FusionSettings = FusionSettings(),
) -> list[DetectorResult]:
    """The recording's odometry and registrations through the localization pipeline with each
    detector, on the settings' backend; with their attitude ("tilt" or "full", see
    `imu.attitude_sigmas`) the IMU's orientation joins every ATTITUDE_EVERY steps, the same readings
    for every detector (drawn from the recording's seed). `fusion`: the estimator's parameters (where
    None, the settings' own: `sim.odometry.odometry_fusion_config`, as `l3e ate` runs them)."""
    backend, attitude = settings.backend, settings.attitude
    check_backend(backend)
    odometry = odometry or OdometryConfig()
    fusion = fusion or odometry_fusion_config(odometry, settings)
    gt = rec.ground_truth
    readings = (
        None
        if attitude_sigmas(attitude) is None
        else attitude_readings(gt, RobotConfig.dt, rng=np.random.default_rng([rec.seed, 5]))
    )
    out = []
    for det in detectors:
        t0 = time.perf_counter()
        ground = (settings.ground or "none") if getattr(det, "reads_scans", True) else "none"
        pipeline = LocalizationPipeline(
            det, backend, fusion, odometry, rec.T_b_s, attitude, settings.detector_every, ground
        )
        pipeline.start(gt[0], getattr(registrations, "start_ground", None))  # drive.RegisteredSteps
        masks, probs, unknown, fallbacks, errors = [], [], 0, 0, 0
        for k, reg in enumerate(tqdm(registrations, desc=f"fusing with {det.name}", unit="step", disable=not progress)):
            step = pipeline.step(
                rec.odometry[k],
                reg,
                rec.detector_input(k + 1),
                gt[k + 1] @ rec.T_b_s,
                None if readings is None else readings[k + 1],
            )
            unknown += not step.prediction.known
            errors += step.detector_failed
            fallbacks += step.fallback
            masks.append(step.prediction.mask)
            probs.append(step.prediction.probabilities)
        counts = (unknown, fallbacks, errors)
        run = fused_run(det.name, pipeline, (np.array(masks), np.array(probs)), time.perf_counter() - t0, counts)
        out.append(scored(run, gt))
    return out


def fused_run(
    name: str,
    pipeline: LocalizationPipeline,
    answers: tuple[np.ndarray, np.ndarray],
    seconds: float,
    counts: tuple[int, int, int],
) -> FusedRun:
    """A drive's pipeline as a FusedRun: its trajectory, the detector's masks and probabilities, the
    unknown, fallback and failed steps, and the share of steps whose ICP observed each leg bias."""
    estimator = pipeline.backend
    steps = max(1, len(answers[0]))
    observed = {a: round(n / steps, 3) for a, n in zip(estimator.bias_axes, estimator.bias_observed.tolist())}
    return FusedRun(name, pipeline.trajectory(), *answers, seconds, *counts, observed, estimator.gated)


def odometry_only(rec: DriveRecord) -> DetectorResult:
    traj = [rec.ground_truth[0]]
    for inc in rec.odometry:
        traj.append(traj[-1] @ inc)
    n = len(rec.odometry)
    return scored(FusedRun("odometry only", np.array(traj), np.ones((n, 6), bool), np.ones((n, 6))), rec.ground_truth)


def scored(run: FusedRun, gt: np.ndarray) -> DetectorResult:
    """A trajectory with its metrics against ground truth (aligned ATE is None for colinear runs)."""
    traj = run.trajectory
    try:
        aligned = ate_aligned(traj, gt)
    except MetricError:
        aligned = None
    rt, rr = rpe(traj, gt, delta=min(10, len(gt) - 1))
    made = {f.name: getattr(run, f.name) for f in fields(run)}
    return DetectorResult(**made, ate=ate(traj, gt), ate_aligned=aligned, rpe_translation=rt, rpe_rotation=rr)
