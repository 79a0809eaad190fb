"""What the geometry of a scan constrains: its point-to-plane Hessian, and a per-axis logistic
layer that weighs it against the network's logits.

The network learns the scene families it was trained on; the Hessian is what point-to-plane ICP
itself linearises, so it carries over to families never seen. On the mine and caves of the test
split, the marginal variances diag(H^-1) of the model's own 0.2 m voxels rank the labels better than
the network does on every axis, y only just (benchmarks/RESULTS.md). A logistic layer per axis over the
network's logit, the six log marginal variances and the six log eigenvalues (13 weights an axis
for one level) is fitted on the training scenes after the network, so it cannot overfit the way a layer trained
with the network would. The same twelve features of the next coarser level (0.4 m voxels, normals of
1.2 m blocks) can be added (ModelConfig.constraint_levels): they see the larger structure that the
registration's coarse first stage locks onto, and they help on scene families never trained on
(benchmarks/RESULTS.md).

The normals are those of the 3x3x3 voxel neighbourhood of each voxel, from a closed-form
eigen-decomposition of the 3x3 scatter: torch.linalg.eigh on a few thousand 3x3 matrices costs
4 ms here, the closed form a tenth of that.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse
import torch
from torch import nn

from .sparse import Level

FEATURES = 12  # per level: log diag(H^-1) (6), log eigenvalues of H (6)
MIN_NEIGHBOURS = 4  # occupied voxels in the 3x3x3 block, the voxel itself included, for a normal
PLANARITY = 0.1  # smallest scatter eigenvalue under this share of the middle one: a surface


def smallest_eigenvector(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unit eigenvector of the smallest eigenvalue, smallest, middle eigenvalue) of symmetric
    (N, 3, 3) matrices, in closed form (see _smallest_eigenvector)."""
    c = np.asarray(c, dtype=np.float64)
    return _smallest_eigenvector(*(c[:, i, j] for i, j in _UPPER))


_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the six distinct entries, in this order
_ROW, _COLUMN = np.array(_UPPER).T


def _smallest_eigenvector(a: np.ndarray, e: np.ndarray, f: np.ndarray, b: np.ndarray, g: np.ndarray,
                          d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """smallest_eigenvector of [[a, e, f], [e, b, g], [f, g, d]], each entry an (N,) vector: the
    trigonometric solution of the characteristic cubic, entry by entry, because reductions and
    argmax over the small 3-wide dimensions cost more than all the arithmetic."""
    q = (a + b + d) / 3
    a0, b0, d0 = a - q, b - q, d - q
    p = np.sqrt((a0 * a0 + b0 * b0 + d0 * d0 + 2 * (e * e + f * f + g * g)) / 6).clip(1e-12)
    det = a0 * (b0 * d0 - g * g) - e * (e * d0 - g * f) + f * (e * g - b0 * f)  # of C - q I
    phi = np.arccos((det / (2 * p**3)).clip(-1.0, 1.0)) / 3
    largest = q + 2 * p * np.cos(phi)
    smallest = q + 2 * p * np.cos(phi + 2 * math.pi / 3)
    middle = 3 * q - largest - smallest
    # the eigenvector is orthogonal to every row of C - lambda I: the longest cross product of two rows
    a1, b1, d1 = a - smallest, b - smallest, d - smallest
    crosses = np.stack([e * g - f * b1, f * e - a1 * g, a1 * b1 - e * e,  # rows 0 x 1
                        e * d1 - f * g, f * f - a1 * d1, a1 * g - e * f,  # rows 0 x 2
                        b1 * d1 - g * g, g * f - e * d1, e * g - b1 * f]).reshape(3, 3, -1)  # rows 1 x 2
    n0, n1, n2 = (crosses * crosses).sum(1)
    first = n0 >= n1
    best, longest = np.where(first, crosses[0], crosses[1]), np.where(first, n0, n1)
    third = n2 > longest
    best, longest = np.where(third, crosses[2], best), np.where(third, n2, longest)
    return (best / np.sqrt(longest).clip(1e-12)).T, smallest, middle


def voxel_hessian(level: Level, means: torch.Tensor, batch_size: int) -> np.ndarray:
    """(B, 6, 6) point-to-plane Hessians sum_v J_v^T J_v, J_v = [n_v, p_v x n_v] (translation first,
    as the labels' axes), over the planar voxels of each scan: each voxel's mean point with the
    normal of its 3x3x3 neighbourhood. The ICP that makes the labels thins its scans to voxels too,
    so every voxel weighs one."""
    return _planar_hessians([level.neighbours().numpy()], [means.numpy()], level.coords[:, 0].numpy(), batch_size)


def _planar_hessians(tables: list[np.ndarray], means: list[np.ndarray], groups: np.ndarray,
                     count: int) -> np.ndarray:
    """(count, 6, 6): voxel_hessian over sets of voxels, each set with its (N, 27) neighbour rows
    (N: empty), and an ascending group index for each voxel of the sets stacked (a scan, or a scan
    at one level). In numpy: a few thousand voxels make small arrays, on which numpy's operations
    cost a fraction of torch's (benchmarks/RESULTS.md), and no gradient flows through the features."""
    counts, scatters = zip(*(_neighbourhood_scatter(t, m) for t, m in zip(tables, means)))
    voxels, scatter = np.concatenate(counts), np.concatenate(scatters, axis=1)
    candidates = np.flatnonzero(voxels >= MIN_NEIGHBOURS)
    normal, smallest, middle = _smallest_eigenvector(*scatter[:, candidates])
    planar = smallest < PLANARITY * middle
    chosen = candidates[planar]
    (px, py, pz), (nx, ny, nz) = np.concatenate(means)[chosen].T.astype(np.float64), normal[planar].T
    # J = [n, p x n], written out: np.cross costs several times more on a few thousand rows
    rows = np.stack([nx, ny, nz, py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx], axis=1)
    bounds = np.searchsorted(groups[chosen], np.arange(count + 1))
    return np.stack([rows[i:j].T @ rows[i:j] for i, j in zip(bounds[:-1], bounds[1:])])


def _neighbourhood_scatter(table: np.ndarray, means: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel, the number of occupied voxels in its 3x3x3 block and the six distinct entries of
    the scatter of their mean points ((6, N), in _UPPER's order), from the block's summed moments
    (1, p, the products of p's coordinates). In float64, as the moments are about the sensor and
    float32 would cancel the scatter of far voxels."""
    n = len(means)
    x, y, z = np.asarray(means, dtype=np.float64).T
    moments = np.stack([x, y, z, x * x, x * y, x * z, y * y, y * z, z * z], axis=1)
    # the block sums as a sparse (N, N) product: about three quarters of the table's entries are empty
    occupied = np.flatnonzero(table < n)  # row-major: grouped by voxel
    voxels = np.bincount(occupied // table.shape[1], minlength=n)
    starts = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(voxels, out=starts[1:])
    pairs = np.take(table, occupied)
    summed = scipy.sparse.csr_array((np.ones(len(pairs)), pairs, starts), shape=(n, n)) @ moments
    mean = summed.T / voxels  # (9, N): the centre, then the second moments in _UPPER's order
    return voxels.astype(np.float64), mean[3:] - mean[_ROW] * mean[_COLUMN]


def coarser_means(level: Level, means: np.ndarray) -> tuple[Level, np.ndarray]:
    """The next coarser level (the network's own, cached on `level`) and the mean of each coarse
    voxel's finer mean points: every finer voxel weighs one, whatever its point count."""
    coarse, _, parent, _ = level.coarser()
    parent, size = parent.numpy(), len(coarse.coords)
    summed = np.stack([np.bincount(parent, weights=means[:, k], minlength=size) for k in range(3)], axis=1)
    return coarse, summed / np.bincount(parent, minlength=size)[:, None]  # float64, as the moments


def scan_features(level: Level, means: torch.Tensor, batch_size: int, levels: tuple[int, ...] = (0,)) -> torch.Tensor:
    """(B, FEATURES * len(levels)): the Hessian features of each of `levels` (0: the finest voxels).
    The levels' voxels, once their neighbourhoods are summed, go through one pass, as if each level
    were more scans of the batch: the work is small and the operations' overhead would otherwise be
    paid once per level."""
    tables, points, groups = [], [], []
    points_here = means.numpy()
    for k in range(max(levels) + 1):
        if k in levels:
            tables.append(level.neighbours().numpy())
            points.append(points_here)
            groups.append(level.coords[:, 0].numpy() + len(groups) * batch_size)
        if k < max(levels):
            level, points_here = coarser_means(level, points_here)
    hessians = _planar_hessians(tables, points, np.concatenate(groups), batch_size * len(levels))
    per_level = hessian_features(hessians).reshape(len(levels), batch_size, FEATURES)
    return torch.from_numpy(np.ascontiguousarray(per_level.transpose(1, 0, 2).reshape(batch_size, -1)))


def hessian_features(hessian: np.ndarray) -> np.ndarray:
    """(B, 12) float32: log diag(H^-1) (how far each axis can move for a unit rise in the cost, the
    other axes free) and log eigenvalues of H. A small ridge keeps a scan with no constraint on an
    axis finite (and large) instead of singular."""
    h = np.asarray(hessian, dtype=np.float64)  # the eigenvalues span several decades
    ridge = 1e-6 * np.trace(h, axis1=1, axis2=2).clip(1e-6)
    h = h + ridge[:, None, None] * np.eye(6)
    variances = np.linalg.inv(h).diagonal(axis1=1, axis2=2)
    eigenvalues = np.linalg.eigvalsh(h).clip(1e-3)
    return np.concatenate([np.log(variances), np.log(eigenvalues)], axis=1).astype(np.float32)


def axis_rows(logits: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """(B, 6, 1 + F): per axis, that axis's logit followed by the scan's F features."""
    return torch.cat([logits[..., None], features[:, None, :].expand(-1, 6, -1)], dim=2)


class AxisStacker(nn.Module):
    """Per axis, a logistic layer over (the network's logit for that axis, the scan's features),
    on features standardised with the statistics of the rows it was fitted on."""

    def __init__(self, features: int = FEATURES) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(1 + features))
        self.register_buffer("std", torch.ones(1 + features))
        self.weight = nn.Parameter(torch.zeros(6, 1 + features))
        self.weight.data[:, 0] = 1.0  # unfitted: the network's logits as they are
        self.bias = nn.Parameter(torch.zeros(6))

    def inputs(self, logits: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """(B, 6, 1 + features) standardised inputs, one row per axis."""
        return (axis_rows(logits, features) - self.mean) / self.std

    def forward(self, logits: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        return (self.inputs(logits, features) * self.weight).sum(2) + self.bias


def fit_stacker(logits: np.ndarray, features: np.ndarray, labels: np.ndarray, l2: float = 1e-2) -> AxisStacker:
    """A stacker fitted by L-BFGS on class-balanced cross-entropy (each axis's positives weigh as
    much as its negatives) with an L2 penalty on the standardised weights."""
    logits_t = torch.as_tensor(logits, dtype=torch.float64)
    features_t = torch.as_tensor(features, dtype=torch.float64)
    targets = torch.as_tensor(np.asarray(labels, dtype=np.float64))
    if logits_t.shape[0] != targets.shape[0] or logits_t.shape[0] < 2:
        raise ValueError(f"a stacker needs at least two labelled rows, got {logits_t.shape[0]}")
    if not (torch.isfinite(logits_t).all() and torch.isfinite(features_t).all()):
        raise ValueError("the stacker's inputs hold NaN or inf")
    stacker = AxisStacker(features_t.shape[1]).double()
    rows = axis_rows(logits_t, features_t).reshape(-1, 1 + features_t.shape[1])
    stacker.mean.copy_(rows.mean(0))
    stacker.std.copy_(rows.std(0).clamp_min(1e-6))
    share = targets.mean(0).clamp(1e-3, 1 - 1e-3)
    positive_weight = (1 - share) / share
    optimiser = torch.optim.LBFGS(list(stacker.parameters()), max_iter=300, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimiser.zero_grad()
        out = stacker(logits_t, features_t)
        loss = nn.functional.binary_cross_entropy_with_logits(out, targets, pos_weight=positive_weight)
        loss = loss + l2 * (stacker.weight**2).sum() / 6
        loss.backward()
        return loss

    optimiser.step(closure)
    return stacker.float()
