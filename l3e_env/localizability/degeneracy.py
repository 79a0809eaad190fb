"""Training-free degeneracy tests that read every correspondence of the point-to-plane problem, not
only its Hessian: X-ICP's localizability analysis (Tuna et al., T-RO 2024) and DRPM's probabilistic
test (Hatleskog and Alexis, RA-L 2024). Written from the papers' descriptions (no code of theirs).

Both judge one scan from its own correspondences (`scan_rows`: the scan registered onto itself at
identity, with the thinning, normals and distance of `register`), as `registration.scan_hessian`
does for the eigenvalue test and DCReg, and both answer on the axes (x, y, z, roll, pitch, yaw) as
(scores, mask), a score over 0.5 where the axis is flagged. Rows are in this project's order:
J = [n, p x n], translation first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from .registration import PreparedTarget, RegistrationConfig, aligned_axes, prepare_source


@dataclass(frozen=True)
class PlaneRows:
    """The point-to-plane problem of a scan: each source point matched to a target voxel, that voxel's
    normal, and the covariance of that normal per unit point variance (its neighbourhood's plane fit:
    V diag(0, 1/l_mid, 1/l_max) V^T / k, l the neighbourhood covariance's eigenvalues, k its points,
    kept across the normal read)."""

    points: np.ndarray  # (N, 3) source points
    normals: np.ndarray  # (N, 3) unit normals of the matched target voxels
    normal_spread: np.ndarray  # (N, 3, 3) normal covariance over the point noise variance

    def turned(self, R: np.ndarray) -> PlaneRows:
        """The same problem written in a frame turned by R (points and normals R p, R n) about the
        sensor: a scan's level frame (core.transforms.level_rotation)."""
        R = np.asarray(R, dtype=np.float64)
        spread = np.einsum("ij,njk,lk->nil", R, self.normal_spread, R)
        return PlaneRows(self.points @ R.T, self.normals @ R.T, spread)

    @property
    def jacobian(self) -> np.ndarray:
        """(N, 6) rows [n, p x n]: J^T J is the registration's Hessian at identity."""
        return np.hstack([self.normals, np.cross(self.points, self.normals)])


def scan_rows(points: np.ndarray, config: RegistrationConfig | None = None) -> PlaneRows:
    """The scan's own point-to-plane rows at identity (RegistrationError for a scan too small)."""
    config = config or RegistrationConfig()
    target = PreparedTarget(points, config)
    source = np.asarray(prepare_source(points, config).points())[:, :3]
    idx, sq = target.tree.batch_nearest_neighbor_search(source)
    idx, sq = np.asarray(idx, dtype=np.int64).reshape(-1), np.asarray(sq).reshape(-1)
    keep = (idx >= 0) & (sq < config.max_correspondence_distance[-1] ** 2)
    matched = idx[keep]
    k = min(config.num_neighbors, len(target.points))
    near, _ = target.tree.batch_knn_search(target.points[matched], k)
    hood = target.points[np.asarray(near, dtype=np.int64)]  # (M, k, 3)
    centred = hood - hood.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", centred, centred) / k
    w, V = np.linalg.eigh(cov)  # ascending: the smallest is the normal's
    inverse = np.where(w[:, 1:] > 1e-12, 1.0 / np.maximum(w[:, 1:], 1e-12), 0.0) / k
    spread = np.einsum("mik,mk,mjk->mij", V[:, :, 1:], inverse, V[:, :, 1:])
    normals = target.normals_at(matched)[matched]
    # a ground voxel reads the ground plane's normal, not its neighbourhood's: its spread is kept to the
    # plane of the normal it reads (a unit normal moves only across itself)
    across = np.eye(3) - normals[:, :, None] * normals[:, None, :]
    return PlaneRows(source[keep], normals, across @ spread @ across)


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices [v]x."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return out - np.swapaxes(out, -1, -2)


def drpm_probabilities(rows: PlaneRows, snr: float, point_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Per eigen-direction u_k of the Hessian (columns of U, ascending eigenvalues): the probability
    that the information measured along u_k exceeds (1 + snr) times the noise's share of it, DRPM's
    signal-to-noise test. Point noise eps ~ N(0, point_sigma^2 I) and normal noise d ~ N(0,
    point_sigma^2 normal_spread) perturb each row by [d, -[n]x eps + [p]x d]; the noise's part of
    u^T H u then has mean sum a_i and variance sum 2 a_i^2 + 4 a_i b_i^2 (a_i = u^T C_i u, C_i the
    row perturbation's covariance, b_i = u^T J_i). Returns (probabilities (6,), U)."""
    J = rows.jacobian
    w, U = np.linalg.eigh(J.T @ J)
    var = point_sigma**2
    normal_cov = var * rows.normal_spread
    n_x, p_x = _skew(rows.normals), _skew(rows.points)
    C = np.zeros((len(J), 6, 6))
    C[:, :3, :3] = normal_cov
    C[:, :3, 3:] = normal_cov @ np.swapaxes(p_x, 1, 2)
    C[:, 3:, :3] = np.swapaxes(C[:, :3, 3:], 1, 2)
    C[:, 3:, 3:] = var * n_x @ np.swapaxes(n_x, 1, 2) + p_x @ normal_cov @ np.swapaxes(p_x, 1, 2)
    a = np.einsum("ik,nij,jk->nk", U, C, U)  # (N, 6)
    b = J @ U
    mean, spread = a.sum(axis=0), np.sqrt((2 * a**2 + 4 * a * b**2).sum(axis=0))
    measured = np.einsum("ik,ij,jk->k", U, J.T @ J, U)
    probability = ndtr((measured / (1 + snr) - mean) / np.maximum(spread, 1e-300))
    return probability, U


def drpm_mask(rows: PlaneRows, snr: float = 10.0, point_sigma: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """DRPM's detection projected to axes: an eigen-direction is degenerate where its signal-to-noise
    probability (drpm_probabilities) is under 0.5; axis i's score is its share of the degenerate
    subspace, sum_k U_ik^2 [p_k < 0.5], flagged over 0.5 (as the eigenvalue test's). `snr`: the paper's
    factor s; `point_sigma`: the points' noise (m), the sensor's range noise by default. The paper
    scales each direction's update by p_k instead of thresholding; a detector needs the threshold."""
    if not snr > 0 or not point_sigma > 0:
        raise ValueError(f"DRPM needs a positive signal-to-noise factor and point noise, got {snr} and {point_sigma}")
    if len(rows.points) < 6:
        raise ValueError(f"DRPM needs at least 6 correspondences, got {len(rows.points)}")
    probability, U = drpm_probabilities(rows, snr, point_sigma)
    scores = (U**2) @ (probability < 0.5).astype(np.float64)
    return scores, scores > 0.5


# X-ICP's contribution filter: a correspondence adds to a direction's localizability only where its
# vector lies within this angle of that direction (the published configuration's 80 deg)
XICP_ALIGNMENT_DEG = 80.0


def xicp_localizability(rows: PlaneRows) -> np.ndarray:
    """X-ICP's localizability per physical axis (x, y, z, roll, pitch, yaw): the translation and the
    rotation blocks of the Hessian are eigen-decomposed apart, each eigenvector assigned one-to-one to
    an axis (as DCReg's basis alignment), and a direction's localizability is the sum of |v . n_i|
    (translation) or |v . c_i| (rotation, c_i = p_i x n_i, scaled to unit length where longer, so
    that far points count as near ones) over the correspondences whose vector lies within
    XICP_ALIGNMENT_DEG of it: how many correspondences constrain that direction, and how squarely."""
    n = rows.normals
    c = np.cross(rows.points, n)
    length = np.linalg.norm(c, axis=1, keepdims=True)
    c = np.where(length > 1.0, c / np.maximum(length, 1e-12), c)
    floor = np.cos(np.radians(XICP_ALIGNMENT_DEG))
    out = np.zeros(6)
    for block, vectors in ((slice(0, 3), n), (slice(3, 6), c)):
        _, V = np.linalg.eigh(vectors.T @ vectors)
        contribution = np.abs(vectors @ V)  # (N, 3): the unit-normal rows' cosines to each direction
        unit = np.linalg.norm(vectors, axis=1, keepdims=True)
        cosine = contribution / np.maximum(unit, 1e-12)
        values = (contribution * (cosine >= floor)).sum(axis=0)
        out[block] = values[aligned_axes(V)]
    return out


def xicp_mask(rows: PlaneRows, enough: float = 300.0) -> tuple[np.ndarray, np.ndarray]:
    """X-ICP's detection projected to axes: an axis whose localizability (xicp_localizability) is under
    `enough` is flagged (the paper's partial and non-localizable categories together: in both, ICP's
    own estimate along it is not taken as it comes). The published configuration's 300 is for its own
    point densities; this registration thins a scan to 1000 points, so the value is swept here as the
    eigenvalue test's tau is. scores: enough / (enough + L), over 0.5 where flagged."""
    if not enough > 0:
        raise ValueError(f"X-ICP's localizability threshold must be positive, got {enough}")
    values = xicp_localizability(rows)
    scores = enough / (enough + values)
    return scores, values < enough
