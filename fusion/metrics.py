"""Trajectory metrics (pure numpy): ATE without and with SE(3) alignment, RPE."""
from __future__ import annotations

import numpy as np


class MetricError(ValueError):
    """Trajectories that cannot be compared (shape, length, NaN, degenerate alignment)."""


def _positions(traj: np.ndarray) -> np.ndarray:
    t = np.asarray(traj, dtype=np.float64)
    if t.ndim == 3 and t.shape[1:] == (4, 4):
        t = t[:, :3, 3]
    if t.ndim != 2 or t.shape[1] != 3:
        raise MetricError(f"expected (N, 4, 4) poses or (N, 3) positions, got shape {t.shape}")
    if not np.isfinite(t).all():
        raise MetricError("trajectory contains NaN or infinite values")
    return t


def ate(estimate: np.ndarray, ground_truth: np.ndarray) -> float:
    """Absolute trajectory error: RMSE of translation, no alignment (simulation shares the world frame)."""
    e, g = _positions(estimate), _positions(ground_truth)
    if e.shape != g.shape:
        raise MetricError(f"trajectories differ in length: {len(e)} vs {len(g)}")
    return float(np.sqrt(np.mean(np.sum((e - g) ** 2, axis=1))))


def umeyama(source: np.ndarray, target: np.ndarray, min_spread_ratio: float = 1e-3) -> np.ndarray:
    """The rigid 4x4 transform minimising |target - T source|^2 (Umeyama 1991, no scale).

    Refuses near-colinear trajectories (second singular value of the centred points below
    `min_spread_ratio` of the first): the rotation about their line is not determined.
    """
    s, t = _positions(source), _positions(target)
    if len(s) < 3:
        raise MetricError("alignment needs at least 3 poses")
    ms, mt = s.mean(0), t.mean(0)
    sv = np.linalg.svd(s - ms, compute_uv=False)
    if sv[1] < min_spread_ratio * max(sv[0], 1e-12):
        raise MetricError("trajectory is (nearly) colinear: SE(3) alignment is not determined; use the unaligned ATE")
    U, _, Vt = np.linalg.svd((t - mt).T @ (s - ms))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, mt - R @ ms
    return T


def ate_aligned(estimate: np.ndarray, ground_truth: np.ndarray) -> float:
    e, g = _positions(estimate), _positions(ground_truth)
    T = umeyama(e, g)
    return ate(e @ T[:3, :3].T + T[:3, 3], g)


def rpe(estimate: np.ndarray, ground_truth: np.ndarray, delta: int = 10) -> tuple[float, float]:
    """Relative pose error over `delta` frames: (translation RMSE m, rotation RMSE rad)."""
    E, G = np.asarray(estimate, dtype=np.float64), np.asarray(ground_truth, dtype=np.float64)
    if E.shape != G.shape or E.ndim != 3 or E.shape[1:] != (4, 4):
        raise MetricError(f"rpe needs two (N, 4, 4) pose arrays of equal length, got {E.shape} and {G.shape}")
    if len(E) <= delta:
        raise MetricError(f"trajectory of {len(E)} poses is too short for delta = {delta}")
    inv = np.linalg.inv
    errs_t, errs_r = [], []
    for i in range(len(E) - delta):
        dE, dG = inv(E[i]) @ E[i + delta], inv(G[i]) @ G[i + delta]
        err = inv(dG) @ dE
        errs_t.append(np.linalg.norm(err[:3, 3]))
        errs_r.append(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.sqrt(np.mean(np.square(errs_t)))), float(np.sqrt(np.mean(np.square(errs_r))))
