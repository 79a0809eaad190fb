"""What one fusion step uses, decided the same way by every backend (graph and filter)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bias import check_bias_settings
from .ground import GROUND_SIGMAS, check_ground_sigmas

MASK_MODES = ("mask", "full", "drop", "directions", "gate")
# gate: a flagged axis keeps ICP where its step lies within this many sigmas of the legs' prediction
GATE_SIGMAS = 3.0
ICP_COVARIANCES = ("hessian", "fixed")


@dataclass
class FusionConfig:
    """mask: drop only the flagged axes; full: keep the whole ICP factor (no detector);
    drop: drop the whole ICP factor when any axis is flagged; directions: drop, of the information's
    own directions (its eigenvectors on the mask's axes), those that lie mostly along a flagged axis,
    so that a direction a flagged axis shares with a held one (a tilted floor's z) keeps its weight;
    gate: a flagged axis keeps ICP's information where ICP's motion along it agrees with the legs'
    prediction within GATE_SIGMAS of the legs' uncertainty (`gate_mask`), so that a slide is kept
    out and a flagged place whose geometry still holds the step (an open yard) keeps what it holds;
    the axes it still flags leave as in "directions": a slide lies along the information's weak
    direction, which may turn the heading with the length (a gallery at an angle to the heading), and
    removing the length's rows alone would keep the heading's part of the slide at full weight.
    Sigmas in project order (m, m, m, rad, rad, rad).

    icp_covariance "hessian": the ICP factor's information is the registration's point-to-plane
    Hessian over `icp_residual_variance`, so that a weakly held axis weighs little even where no
    axis is flagged, and a well held one more than the legs; the variance is fitted on training
    drives by `studies/icp_step_errors.py`. "fixed": the constant `icp_sigmas` (also where a
    step comes without a finite Hessian).

    odometry_bias: which of the leg odometry's biases ("yaw", "z" per metre, "scale" of the
    stride) are estimated as states of the fusion (see fusion.bias), with their prior spread
    `odometry_bias_sigmas` (rad/m, m/m, 1) and random walk `odometry_bias_walk` (per square-root
    metre), both in BIAS_AXES order; none by default. A bias moves only on the steps whose ICP
    factor observes it (`bias_information_share`, fusion.bias.observed_axes); elsewhere it keeps its
    estimate, so that an axis handed to the legs ends no worse than the legs.

    smoother_lag: None smooths the whole drive (iSAM2), so that `trajectory()` is the smoothed
    trajectory; a number of steps keeps only that many poses (and the bias states they use) in an
    incremental fixed-lag smoother and marginalizes the older ones, which bounds each step's cost
    for a consumer of the newest estimate alone (an environment): with the odometry bias states,
    whose revision moves every later pose, the full smoother's step grows with the drive.
    `marginalize_every`: the window's oldest poses leave it in batches of this many steps (the
    window holds `smoother_lag` to `smoother_lag + marginalize_every` steps), since each
    marginalization costs GTSAM's smoother a re-elimination of the whole window."""

    mode: str = "mask"
    icp_covariance: str = "hessian"
    # m^2: fitted to the registration's steps over the training families (studies/icp_step_errors.py)
    icp_residual_variance: float = 0.0016
    icp_sigmas: tuple[float, ...] = (0.005, 0.005, 0.005, 0.001, 0.001, 0.001)  # scan-to-scan at 10 Hz
    prior_sigmas: tuple[float, ...] = (1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4)
    robust_kernel: str | None = None  # None | "huber" | "cauchy"
    robust_threshold: float = 1.345
    relinearize_threshold: float = 0.01
    odometry_bias: tuple[str, ...] = ()
    odometry_bias_sigmas: tuple[float, ...] = (0.001, 0.005, 0.02)
    odometry_bias_walk: tuple[float, ...] = (0.0003, 0.0005, 0.0001)
    # a bias state moves on a step only where the step's ICP knows the motion it explains with at least
    # this share of the legs' own information (fusion.bias.observed_axes); 0 lets every step move it
    bias_information_share: float = 0.1
    smoother_lag: int | None = None
    marginalize_every: int = 25
    ground_sigmas: tuple[float, ...] = GROUND_SIGMAS


def check_config(config: FusionConfig) -> FusionConfig:
    if config.mode not in MASK_MODES:
        raise ValueError(f"fusion mode must be one of {MASK_MODES}, got '{config.mode}'")
    if config.icp_covariance not in ICP_COVARIANCES:
        raise ValueError(f"icp_covariance must be one of {ICP_COVARIANCES}, got '{config.icp_covariance}'")
    if not (np.isfinite(config.icp_residual_variance) and config.icp_residual_variance > 0):
        raise ValueError(f"icp_residual_variance must be a positive number, got {config.icp_residual_variance!r}")
    share = config.bias_information_share
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not (np.isfinite(share) and share >= 0):
        raise ValueError(f"bias_information_share must be a number of at least 0, got {share!r}")
    lag = config.smoother_lag
    if lag is not None and (isinstance(lag, bool) or not isinstance(lag, int) or lag < 1):
        raise ValueError(f"smoother_lag must be None (the whole drive) or a number of steps >= 1, got {lag!r}")
    every = config.marginalize_every
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"marginalize_every must be a number of steps >= 1, got {every!r}")
    config.odometry_bias = tuple(config.odometry_bias)
    check_ground_sigmas(config.ground_sigmas)
    check_bias_settings(config.odometry_bias, config.odometry_bias_sigmas, config.odometry_bias_walk)
    return config


def check_mask_basis(basis: np.ndarray | None) -> np.ndarray:
    """The 6x6 map from the factor's tangent (project order) onto the axes the mask names, checked;
    the identity where None (the mask names the factor's own axes)."""
    if basis is None:
        return np.eye(6)
    B = np.asarray(basis, dtype=np.float64)
    if B.shape != (6, 6) or not np.isfinite(B).all() or abs(np.linalg.det(B)) < 1e-9:
        raise ValueError(f"a mask basis is an invertible, finite 6x6 matrix, got {np.asarray(basis).tolist()!r}")
    return B


def icp_information(
    config: FusionConfig, hessian: np.ndarray | None, mask: np.ndarray, basis: np.ndarray | None = None
) -> np.ndarray:
    """The ICP factor's 6x6 information in project order (the body frame), its masked axes zero: the
    Hessian (project order, the body frame) over the residual variance, or diag(1 / icp_sigmas^2).
    `basis` (B, 6x6): the mask names the axes of d' = B d (a scan's level frame), so the information
    is written on those axes, their masked rows and columns zeroed there, and turned back."""
    B = check_mask_basis(basis)
    information = masked_information(config, hessian, mask, B)
    return B.T @ information @ B


def whole_information(config: FusionConfig, hessian: np.ndarray | None) -> np.ndarray:
    """The ICP factor's 6x6 information before any mask (project order, the body frame): the Hessian
    over the residual variance, or diag(1 / icp_sigmas^2) (see FusionConfig.icp_covariance)."""
    H = None if hessian is None else np.asarray(hessian, dtype=np.float64)
    if config.icp_covariance == "hessian" and H is not None and H.shape == (6, 6) and np.isfinite(H).all():
        w, V = np.linalg.eigh(0.5 * (H + H.T))  # rounding can leave a free direction a little below zero
        return (V * np.maximum(w, 0.0)) @ V.T / config.icp_residual_variance
    return np.diag(1.0 / np.asarray(config.icp_sigmas, dtype=np.float64) ** 2)


def masked_information(
    config: FusionConfig, hessian: np.ndarray | None, mask: np.ndarray, basis: np.ndarray
) -> np.ndarray:
    """`icp_information` on the mask's axes (d' = basis d), before it is turned back."""
    information = whole_information(config, hessian)
    inverse = np.linalg.inv(basis)
    information = inverse.T @ information @ inverse
    information = 0.5 * (information + information.T)
    if config.mode in ("directions", "gate") and mask.any():
        w, V = np.linalg.eigh(information)
        along = np.argmax(V**2, axis=0)  # the axis each direction lies mostly along
        return (V * np.where(mask[along], 0.0, w)) @ V.T
    information[mask, :] = 0.0
    information[:, mask] = 0.0
    return information


def gate_mask(mask: np.ndarray, basis: np.ndarray, innovation: np.ndarray, legs_covariance: np.ndarray) -> np.ndarray:
    """The flagged axes (`mask`, on the axes d' = basis d) along which ICP disagrees with the legs:
    its step's difference from the legs' prediction (`innovation`, project order, the body frame),
    read on those axes, beyond GATE_SIGMAS of the legs' uncertainty there (`legs_covariance` over the
    factor's span, 6x6, body frame). The others of `mask` are kept: a flag says ICP cannot correct the
    labels' offsets, not that it is wrong about the small ones a fusion meets between keyframes.
    ICP's own variance does not widen the gate: where a scan slides (a tunnel's identical rings
    register as standing still) its Hessian still claims centimetres, and a slide within them
    would be taken at that weight on every step."""
    B = check_mask_basis(basis)
    legs_variance = np.diag(B @ np.asarray(legs_covariance, dtype=np.float64) @ B.T)
    r = B @ np.asarray(innovation, dtype=np.float64)
    return np.asarray(mask, dtype=bool) & (r**2 > GATE_SIGMAS**2 * legs_variance)


def legs_covariance(
    sigmas: np.ndarray, step: np.ndarray, across: np.ndarray, span: int, spread: float, scale_sigma: float
) -> np.ndarray:
    """The legs' covariance (6x6, project order, the body frame) over `span` steps like this one, which
    the gate reads ICP against: each step's (`sigmas`, its translation `step`) without the stride's
    `spread`, which the legs' sigmas hold as a step's own noise, and the scale as the fusion knows it
    now (`scale_sigma`) over the span's translation `across`: else the gate would stay as wide once
    the scale is learnt as before."""
    variance = np.asarray(sigmas, dtype=np.float64) ** 2
    variance[:3] = np.maximum(variance[:3] - (spread * np.asarray(step)) ** 2, 0.25 * variance[:3])
    covariance = span * np.diag(variance)
    covariance[:3, :3] += scale_sigma**2 * np.outer(across, across)
    return covariance


@dataclass
class StepReport:
    icp_used: bool
    masked_axes: int
    fallback: str | None  # why the step ran on a reduced set of factors


@dataclass
class StepInputs:
    has_odom: bool
    has_icp: bool
    mask: np.ndarray  # (6,) bool in project order, True = no information on that axis
    icp_T_prev_cur: np.ndarray | None
    fallback: str | None
    # (6,) bool in project order: the axes nothing else holds without odometry, which a weak
    # constant-position factor keeps where they were
    still: np.ndarray

    def report(self) -> StepReport:
        return StepReport(self.has_icp, int(self.mask.sum()) if self.has_icp else 6, self.fallback)


def check_odometry_sigmas(sigmas: np.ndarray | None) -> np.ndarray:
    """The odometry's per-axis sigmas as 6 finite non-negative floats, or a ValueError that says so:
    an infinite or NaN sigma would leave the new pose without information and the solve would fail
    far from the cause."""
    out = np.asarray(sigmas if sigmas is not None else np.full(6, np.nan), dtype=np.float64)
    if out.shape != (6,) or not (np.isfinite(out).all() and (out >= 0).all()):
        raise ValueError(f"odometry sigmas must be 6 finite non-negative numbers, got {sigmas!r}")
    return out


def check_attitude(R_w_b: np.ndarray, sigmas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An absolute orientation (3x3 rotation) and its sigmas (3, rad, about the body's x, y and z;
    inf where an axis is not measured, as the heading of an IMU without a trusted magnetometer),
    checked, as (rotation, precisions): a NaN or a matrix that is not a rotation would be fused
    as if it were one."""
    R = np.asarray(R_w_b, dtype=np.float64)
    s = np.asarray(sigmas, dtype=np.float64)
    if (
        R.shape != (3, 3)
        or not np.isfinite(R).all()
        or not np.allclose(R.T @ R, np.eye(3), atol=1e-6)
        or np.linalg.det(R) < 0
    ):
        raise ValueError(f"an attitude must be a finite 3x3 rotation matrix, got {R_w_b!r}")
    if s.shape != (3,) or np.isnan(s).any() or not (s > 0).all():
        raise ValueError(f"attitude sigmas must be 3 positive numbers (inf: not measured), got {sigmas!r}")
    return R, 1.0 / s**2


def resolve_step(
    mode: str, odom_T_prev_cur: np.ndarray | None, icp_T_prev_cur: np.ndarray | None, non_localizable: np.ndarray | None
) -> StepInputs:
    """Apply the mode (mask: drop the flagged axes; full: keep every axis; drop: drop the ICP
    factor when any axis is flagged) and the documented fallbacks: missing odometry with every
    ICP axis masked keeps the ICP factor whole; with neither, the caller adds a weak
    constant-position tie, and without odometry it ties the masked axes so (else nothing would hold
    them). Non-finite inputs count as missing."""
    if mode not in MASK_MODES:
        raise ValueError(f"fusion mode must be one of {MASK_MODES}, got '{mode}'")
    mask = np.zeros(6, dtype=bool) if non_localizable is None else np.asarray(non_localizable, dtype=bool).copy()
    fallback = None
    if mode == "full":
        mask[:] = False
    elif mode == "drop" and mask.any():
        icp_T_prev_cur, mask = None, np.ones(6, dtype=bool)
    has_odom = odom_T_prev_cur is not None and bool(np.isfinite(odom_T_prev_cur).all())
    icp_ok = icp_T_prev_cur is not None and bool(np.isfinite(icp_T_prev_cur).all())
    has_icp = icp_ok and not mask.all()
    if not has_odom and icp_ok and mask.all():
        mask[:], has_icp, fallback = False, True, "all axes masked and no odometry: full ICP factor"
    still = np.zeros(6, dtype=bool) if has_odom else (mask.copy() if has_icp else np.ones(6, dtype=bool))
    if not has_odom and not has_icp:
        fallback = "no odometry and no ICP: constant-position factor"
    elif still.any():
        fallback = "masked axes and no odometry: constant-position factor on the masked axes"
    return StepInputs(has_odom, has_icp, mask, icp_T_prev_cur if icp_ok else None, fallback, still)
