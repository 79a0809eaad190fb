"""Trajectory metrics (pure numpy): ATE without and with SE(3) alignment, RPE, drift over stretches."""

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


def rpe_pairs(ground_truth: np.ndarray, delta: float, unit: str = "frames") -> list[tuple[int, int]]:
    """Index pairs of the RPE: 'frames': every (i, i + delta); 'meters': consecutive stretches
    of at least `delta` metres of ground-truth path (evo's default pairing for metres)."""
    if unit == "frames":
        d = int(delta)
        return [(i, i + d) for i in range(len(ground_truth) - d)]
    if unit != "meters":
        raise MetricError(f"rpe unit must be 'frames' or 'meters', got '{unit}'")
    steps = np.linalg.norm(np.diff(_positions(ground_truth), axis=0), axis=1)
    ids, travelled = [0], 0.0
    for i, step in enumerate(steps, start=1):
        travelled += float(step)
        if travelled >= delta:
            ids.append(i)
            travelled = 0.0
    return list(zip(ids[:-1], ids[1:]))


def rpe(estimate: np.ndarray, ground_truth: np.ndarray, delta: float = 10, unit: str = "frames") -> tuple[float, float]:
    """Relative pose error over a window of `delta` frames or metres (see `rpe_pairs`):
    (translation RMSE m, rotation RMSE rad)."""
    E, G = np.asarray(estimate, dtype=np.float64), np.asarray(ground_truth, dtype=np.float64)
    if E.shape != G.shape or E.ndim != 3 or E.shape[1:] != (4, 4):
        raise MetricError(f"rpe needs two (N, 4, 4) pose arrays of equal length, got {E.shape} and {G.shape}")
    pairs = rpe_pairs(G, delta, unit)
    if not pairs:
        raise MetricError(f"trajectory of {len(E)} poses is too short for a window of {delta} {unit}")
    i, j = np.array(pairs).T
    inv = np.linalg.inv
    err = inv(inv(G[i]) @ G[j]) @ (inv(E[i]) @ E[j])
    errs_t = np.linalg.norm(err[:, :3, 3], axis=1)
    errs_r = np.arccos(np.clip((np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    return float(np.sqrt(np.mean(errs_t**2))), float(np.sqrt(np.mean(errs_r**2)))


def stretch_drift(estimate: np.ndarray, ground_truth: np.ndarray, inside: np.ndarray) -> tuple[float, float]:
    """The error accumulated over the stretches of a drive where `inside` (N,) holds, whatever the error
    on entering them: (drift m, true distance travelled m). Over each maximal run of poses i..j inside,
    the translation of the relative pose error (G_i^-1 G_j)^-1 (E_i^-1 E_j); the runs' norms are summed,
    as are their true path lengths. (0, 0) where no two consecutive poses are inside."""
    E, G = np.asarray(estimate, dtype=np.float64), np.asarray(ground_truth, dtype=np.float64)
    inside = np.asarray(inside, dtype=bool)
    if E.shape != G.shape or E.ndim != 3 or E.shape[1:] != (4, 4) or inside.shape != (len(G),):
        raise MetricError(
            f"stretch_drift needs two (N, 4, 4) pose arrays and an (N,) mask, got {E.shape}, "
            f"{G.shape} and {inside.shape}"
        )
    edges = np.diff(np.concatenate([[0], inside.astype(np.int8), [0]]))
    drift = distance = 0.0
    inv = np.linalg.inv
    for i, j in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1):
        if j <= i:
            continue
        err = inv(inv(G[i]) @ G[j]) @ (inv(E[i]) @ E[j])
        drift += float(np.linalg.norm(err[:3, 3]))
        distance += float(np.linalg.norm(np.diff(G[i : j + 1, :3, 3], axis=0), axis=1).sum())
    return drift, distance


def write_tum(path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """A trajectory in the TUM format ('t x y z qx qy qz qw' per line), for evo and other tools."""
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, dtype=np.float64)
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w
    rows = np.column_stack([np.asarray(stamps, dtype=np.float64), poses[:, :3, 3], q])
    np.savetxt(path, rows, fmt="%.9f")


def write_kitti(path, poses: np.ndarray) -> None:
    """A trajectory in the KITTI odometry format (the first three rows of each 4x4 pose, 12 numbers a
    line, no times), for evo and the KITTI tools."""
    poses = np.asarray(poses, dtype=np.float64)
    np.savetxt(path, poses[:, :3, :].reshape(len(poses), 12), fmt="%.9f")
