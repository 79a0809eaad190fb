"""Localizability detectors behind one interface: none, eigenvalue (Zhang et al.), oracle,
the scan's own Monte-Carlo estimate, learned, and the learned one checked by the estimate where
it is unsure.

Every detector maps one scan (and, where it needs it, the registration of that scan against
the previous one, or the true pose) to six probabilities of non-localizability and a mask,
in (x, y, z, roll, pitch, yaw) order of the scan's level frame (z along gravity, x the sensor's
heading levelled: core.transforms.level_rotation), 1/True = not localizable. The pose `T_w_s`
(world z up) gives the tilt; a detector given none takes the sensor as level.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, cast

import numpy as np

from l3e_env.config import LidarConfig, from_dict
from l3e_env.config.detector_spec import parse_detector
from l3e_env.core.transforms import level_rotation_of
from l3e_env.localizability.degeneracy import drpm_mask, scan_rows, xicp_mask
from l3e_env.localizability.labels import LabelConfig, label_parent
from l3e_env.localizability.registration import (
    RegistrationConfig,
    RegistrationError,
    RegistrationResult,
    dcreg_mask,
    eigen_mask,
    hessian_in_level,
)
from l3e_env.localizability.scan_mc import ScanMCConfig, ScanPatternError, scan_errors
from l3e_env.sim.lidar import Lidar


@dataclass
class Prediction:
    probabilities: np.ndarray  # (6,) float
    mask: np.ndarray  # (6,) bool, True = not localizable
    known: bool = True  # False: the detector could not judge this scan (mask is all False then)
    reason: str | None = None  # why it could not, where it said


class Detector(Protocol):
    name: str

    def predict(
        self, points: np.ndarray, registration: RegistrationResult | None = None, T_w_s: np.ndarray | None = None
    ) -> Prediction: ...


UNKNOWN = Prediction(np.full(6, np.nan), np.zeros(6, dtype=bool), known=False)


def unknown(reason: str) -> Prediction:
    """UNKNOWN, with why the scan could not be judged."""
    return dataclasses.replace(UNKNOWN, reason=reason)


def level_of(T_w_s: np.ndarray | None) -> np.ndarray:
    """R_l_s of a scan posed at T_w_s; the identity for a scan given without a pose (taken as level)."""
    return np.eye(3) if T_w_s is None else level_rotation_of(T_w_s)


def pose_or_level(T_w_s: np.ndarray | None) -> np.ndarray:
    """T_w_s, or the identity for a scan given without a pose (taken as level)."""
    return np.eye(4) if T_w_s is None else np.asarray(T_w_s, dtype=np.float64)


class NoDetector:
    """Trust ICP on every axis (the 'full ICP' baseline)."""

    name = "none"

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        return Prediction(np.zeros(6), np.zeros(6, dtype=bool))


class HessianDetector:
    """A classical test on the registration's Hessian: `mask_of(hessian, threshold)` -> (scores, mask),
    named '<kind>:<threshold>'; UNKNOWN where there is no finite Hessian."""

    kind = ""
    mask_of: Callable[[np.ndarray, float], tuple[np.ndarray, np.ndarray]] = staticmethod(eigen_mask)

    def __init__(self, threshold: float):
        self.threshold = float(threshold)
        self.name = f"{self.kind}:{threshold:g}"

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        if registration is None or not np.isfinite(registration.hessian).all():
            return UNKNOWN
        return Prediction(*self.mask_of(hessian_in_level(registration.hessian, level_of(T_w_s)), self.threshold))


class EigenvalueDetector(HessianDetector):
    """Zhang et al. (2016) on the registration's Hessian; `probabilities` are the per-axis shares
    of the degenerate subspace (not calibrated probabilities)."""

    kind, mask_of = "eigen", staticmethod(eigen_mask)

    def __init__(self, tau: float):
        if not tau > 0:
            raise ValueError(f"eigenvalue threshold must be positive, got {tau}")
        super().__init__(tau)
        self.tau = self.threshold


class DCRegDetector(HessianDetector):
    """DCReg's detection (Hu et al., 2025) on the registration's Hessian: rotation and translation
    decoupled by Schur complements, an axis flagged when its subspace's condition ratio exceeds kappa
    (registration.dcreg_mask); `probabilities` are log-ratio scores, not calibrated probabilities."""

    kind, mask_of = "dcreg", staticmethod(dcreg_mask)

    def __init__(self, kappa: float):
        if not kappa > 1:
            raise ValueError(f"DCReg's condition ratio threshold must exceed 1, got {kappa}")
        super().__init__(kappa)
        self.kappa = self.threshold


class CorrespondenceDetector:
    """A training-free test that reads each correspondence of the scan's own point-to-plane problem
    (localizability.degeneracy: the scan registered onto itself), named '<kind>:<threshold>'; UNKNOWN
    where the scan is too small to register."""

    kind = ""

    def __init__(self, threshold: float, registration: RegistrationConfig | None = None):
        if not threshold > 0:
            raise ValueError(f"{self.kind}'s threshold must be positive, got {threshold}")
        self.threshold = float(threshold)
        self.name = f"{self.kind}:{threshold:g}"
        self.registration = registration or RegistrationConfig()

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        try:
            rows = scan_rows(points, self.registration)
        except RegistrationError:
            return UNKNOWN
        if len(rows.points) < 6:
            return UNKNOWN
        return Prediction(*self.judge(rows.turned(level_of(T_w_s))))

    def judge(self, rows) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


class XICPDetector(CorrespondenceDetector):
    """X-ICP's localizability analysis (Tuna et al., T-RO 2024; degeneracy.xicp_mask): an axis is flagged
    where fewer correspondences than the threshold constrain it squarely; `probabilities` are
    L / (L + threshold) scores, not calibrated probabilities."""

    kind = "xicp"

    def judge(self, rows) -> tuple[np.ndarray, np.ndarray]:
        return xicp_mask(rows, self.threshold)


class DRPMDetector(CorrespondenceDetector):
    """DRPM's probabilistic degeneracy test (Hatleskog and Alexis, RA-L 2024; degeneracy.drpm_mask) with
    signal-to-noise factor s and the sensor's range noise; `probabilities` are shares of the degenerate
    subspace, not calibrated probabilities."""

    kind = "drpm"

    def __init__(self, threshold: float, registration: RegistrationConfig | None = None, point_sigma: float = 0.03):
        super().__init__(threshold, registration)
        self.point_sigma = point_sigma

    def judge(self, rows) -> tuple[np.ndarray, np.ndarray]:
        return drpm_mask(rows, self.threshold, self.point_sigma)


class OracleDetector:
    """Monte-Carlo labels computed at the true sensor pose with M children (fewer than the
    paper's 200 to keep a route affordable), re-evaluated every `stride` calls and held between."""

    def __init__(
        self,
        lidar: Lidar,
        children: int = 20,
        stride: int = 5,
        seed: int = 0,
        registration: RegistrationConfig | None = None,
    ):
        self.lidar, self.stride, self.seed = lidar, stride, seed
        self.labels = LabelConfig(children=children)
        self.registration = registration or RegistrationConfig()
        self.name = f"oracle:{children}"
        self._calls, self._last = 0, UNKNOWN

    def judge(self, T_w_s: np.ndarray, rng: np.random.Generator) -> Prediction:
        """The labels at one pose, from `rng`'s children (a map seeds each pose by itself)."""
        try:
            res = label_parent(self.lidar, T_w_s, rng, self.labels, self.registration)
        except RegistrationError:
            return UNKNOWN
        return Prediction(res.labels.astype(np.float64), res.labels.astype(bool))

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        if T_w_s is None:
            raise ValueError("the oracle detector needs the true sensor pose")
        if self._calls % self.stride == 0:
            self._last = self.judge(T_w_s, np.random.default_rng([self.seed, self._calls]))
        self._calls += 1
        return self._last


class ScanMCDetector:
    """The Monte-Carlo labels estimated from the scan alone (scan_mc.py): no scene, no true pose
    and no training, at the cost of up to M registrations a scan. `probabilities` are r / (1 + r)
    of the ratio r of each estimated error to its label threshold (0.5 at the threshold), not
    calibrated probabilities."""

    def __init__(
        self,
        lidar: LidarConfig,
        children: int = ScanMCConfig.children,
        seed: int = 0,
        registration: RegistrationConfig | None = None,
        labels: LabelConfig | None = None,
    ):
        self.lidar, self.seed = lidar, seed
        self.config = ScanMCConfig(children=children)
        self.registration = registration or RegistrationConfig()
        self.labels = labels or LabelConfig()
        self.name = f"scanmc:{children}"
        self._calls = 0

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        rng = np.random.default_rng([self.seed, self._calls])
        self._calls += 1
        return self.judge(points, rng, T_w_s)

    def judge(self, points: np.ndarray, rng: np.random.Generator, T_w_s: np.ndarray | None = None) -> Prediction:
        """One scan judged with `rng`'s children (a map seeds each pose by itself), in the level frame
        of its pose's tilt."""
        try:
            errors = scan_errors(
                points, self.lidar, self.registration, self.labels, self.config, rng, level_of(T_w_s)
            ).errors
        except (RegistrationError, ScanPatternError) as exc:
            return unknown(str(exc))
        ratio = errors / self.labels.threshold_vector()
        return Prediction(ratio / (1 + ratio), ratio > 1)


class LearnedDetector:
    """The trained classifier (by default the checkpoint shipped with the package). A scan it
    cannot judge (empty, fewer than 50 points, NaN) gives the UNKNOWN prediction: nothing is
    masked, and `known` is False so that the caller can count it."""

    name = "learned"

    def __init__(
        self,
        checkpoint: str | None = None,
        lidar_model: str | None = None,
        registration: RegistrationConfig | None = None,
        symmetric: bool = False,
        device: str = "cpu",
    ):
        from l3e_env.model.classifier import Classifier  # torch is imported only when a learned detector is made

        self.classifier = Classifier.load(checkpoint, symmetric=symmetric, device=device)
        self.name = ("learned-sym" if symmetric else "learned") + (f":{checkpoint}" if checkpoint else "")
        stored = self.classifier.meta.get("registration")
        # the registration its labels were made with: the pipeline runs the same (pipeline.registration_of)
        self.labelled_with = from_dict(RegistrationConfig, stored) if stored is not None else None
        self.classifier.check_settings(
            lidar_model, dataclasses.asdict(registration or self.labelled_with or RegistrationConfig())
        )

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        from l3e_env.model.classifier import ScanError

        try:
            p, mask = self.classifier.predict(points, pose_or_level(T_w_s))
        except ScanError as exc:
            return unknown(str(exc))
        if not np.isfinite(p).all():  # a broken model answers "unknown", never "localizable"
            return UNKNOWN
        return Prediction(p, mask)


CASCADE_MARGIN = 1.0  # chosen on the validation scenes (docs/decisions.md)


def log_odds_over_threshold(probabilities: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """logit(p) - logit(threshold), per axis: positive where the axis is flagged."""
    p = np.clip(probabilities, 1e-6, 1 - 1e-6)
    t = np.clip(thresholds, 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p)) - np.log(t / (1 - t))


def near_threshold(probabilities: np.ndarray, thresholds: np.ndarray, margin: float) -> np.ndarray:
    """Whether any axis's probability lies within `margin` of its threshold in log-odds, per scan
    ((..., 6) -> (...)): where the classifier is unsure, and where most of its errors on scene
    families it never saw lie."""
    return (np.abs(log_odds_over_threshold(probabilities, thresholds)) < margin).any(axis=-1)


class CascadeDetector:
    """The classifier where it is sure; where any axis lies within `margin` (log-odds) of its
    threshold, the scan's own Monte-Carlo estimate judges the scan instead, all six axes. The
    classifier's misses and false flags on unseen families sit mostly in that band, so checking a
    third of the scans there recovers most of the estimate's accuracy at a third of its cost.
    `probabilities` are the classifier's or the estimate's r / (1 + r), whichever judged; `checked`
    counts the scans the estimate judged."""

    def __init__(self, learned: LearnedDetector, scan_mc: ScanMCDetector, margin: float = CASCADE_MARGIN):
        if not margin >= 0:
            raise ValueError(f"the cascade's margin is a log-odds distance >= 0, got {margin}")
        self.learned, self.scan_mc, self.margin = learned, scan_mc, float(margin)
        self.labelled_with = learned.labelled_with
        self.name = f"learned+scanmc:{self.margin:g}"
        self.calls = self.checked = 0

    def predict(self, points, registration=None, T_w_s=None) -> Prediction:
        rng = np.random.default_rng([self.scan_mc.seed, self.calls])
        return self.judge(points, rng, T_w_s)

    def classify(self, points: np.ndarray, T_w_s: np.ndarray | None = None) -> tuple[Prediction, bool]:
        """The classifier's prediction, and whether it is unsure (a scan it cannot judge is not checked:
        the estimate could not judge it either)."""
        first = self.learned.predict(points, None, T_w_s)
        thresholds = self.learned.classifier.thresholds
        return first, first.known and bool(near_threshold(first.probabilities, thresholds, self.margin))

    def judge(self, points: np.ndarray, rng: np.random.Generator, T_w_s: np.ndarray | None = None) -> Prediction:
        """One scan; the estimate, where it is asked, draws its children from `rng`."""
        return self._judged(points, rng, T_w_s)[0]

    def scores_at_half(
        self, points: np.ndarray, rng: np.random.Generator, T_w_s: np.ndarray | None = None
    ) -> tuple[np.ndarray, bool]:
        """`judge`'s six scores on one scale, flagged above 0.5 whichever judge judged: the classifier's
        probabilities moved so that its thresholds sit at 0.5 (sigmoid of the log-odds over them), the
        estimate's r / (1 + r) as they are; NaN for a scan neither can judge. And whether the estimate
        judged. A map holds these."""
        pred, by_estimate = self._judged(points, rng, T_w_s)
        if not pred.known:
            return np.full(6, np.nan), by_estimate
        if by_estimate:
            return pred.probabilities, True
        return 1 / (1 + np.exp(-log_odds_over_threshold(pred.probabilities, self.learned.classifier.thresholds))), False

    def _judged(
        self, points: np.ndarray, rng: np.random.Generator, T_w_s: np.ndarray | None
    ) -> tuple[Prediction, bool]:
        """The prediction, and whether the estimate made it."""
        self.calls += 1
        first, unsure = self.classify(points, T_w_s)
        if not unsure:
            return first, False
        self.checked += 1
        return self.scan_mc.judge(points, rng, T_w_s), True


def safe_predict(det: Detector, points: np.ndarray, reg, T_w_s: np.ndarray | None) -> tuple[Prediction, bool]:
    """The detector's prediction, or UNKNOWN (nothing masked) if it raises: one bad scan or a
    detector bug must not end a run; the caller counts these."""
    try:
        return det.predict(points, reg, T_w_s), False
    except Exception:  # noqa: BLE001 - any detector failure becomes a counted UNKNOWN step
        return UNKNOWN, True


def make_detector(
    spec: str, lidar: Lidar | None = None, seed: int = 0, sensor: LidarConfig | None = None, device: str = "cpu"
) -> Detector:
    """The detector of `spec` (DETECTOR_GRAMMAR): 'learned' is the shipped model, 'learned-sym' averages
    it over the eight mirror/swap views of each scan, 'learned+scanmc' is the shipped model checked by
    scanmc where it is unsure (CascadeDetector). `sensor`: the LiDAR's settings where there is no scene
    LiDAR (scans read from files): scanmc needs its beams, and the learned detector warns if it differs
    from training. `device`: where a learned detector's network runs (classifier.torch_device)."""
    sensor = lidar.config if lidar is not None else sensor
    parsed = parse_detector(spec)
    if parsed.kind == "learned+scanmc":
        margin = CASCADE_MARGIN if parsed.margin is None else parsed.margin
        return CascadeDetector(
            cast(LearnedDetector, make_detector("learned", lidar, seed, sensor, device)),
            cast(ScanMCDetector, make_detector("scanmc", lidar, seed, sensor)),
            margin,
        )
    if parsed.kind == "none":
        return NoDetector()
    tau = float("nan") if parsed.tau is None else parsed.tau  # parse_detector gives these kinds theirs
    if parsed.kind == "eigen":
        return EigenvalueDetector(tau)
    if parsed.kind == "dcreg":
        return DCRegDetector(tau)
    if parsed.kind == "xicp":
        return XICPDetector(tau)
    if parsed.kind == "drpm":
        return DRPMDetector(tau, point_sigma=(sensor or LidarConfig()).range_noise_std or 0.03)
    if parsed.kind == "oracle":
        if lidar is None:
            raise ValueError("the oracle detector needs the scene's LiDAR")
        return OracleDetector(lidar, children=parsed.children or 20, seed=seed)
    if parsed.kind == "scanmc":
        return ScanMCDetector(sensor or LidarConfig(), children=parsed.children or ScanMCConfig.children, seed=seed)
    return LearnedDetector(
        parsed.checkpoint,
        lidar_model=sensor.model if sensor is not None else None,
        symmetric=parsed.kind == "learned-sym",
        device=device,
    )


def registration_of(detectors: list[Detector]) -> RegistrationConfig:
    """The registration the pipeline runs: the one the learned detectors' labels were made with (their
    checkpoints store it), else the defaults. Detectors whose checkpoints disagree get the defaults and
    a warning, as a checkpoint made with other settings than the ones in use does."""
    stored = [found for d in detectors if (found := getattr(d, "labelled_with", None)) is not None]
    if not stored:
        return RegistrationConfig()
    if any(s != stored[0] for s in stored[1:]):
        warnings.warn(
            "the detectors' checkpoints were labelled with different registration settings; the "
            "pipeline runs the defaults",
            stacklevel=2,
        )
        return RegistrationConfig()
    return stored[0]
