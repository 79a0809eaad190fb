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
import warnings

import numpy as np
import torch
from torch import nn

from .sparse import Level

FEATURES = 12  # per level: log diag(H^-1) (6), log eigenvalues of H (6)
MIN_NEIGHBOURS = 4  # occupied voxels in the 3x3x3 block, the voxel itself included, for a normal
PLANARITY = 0.1  # smallest scatter eigenvalue under this share of the middle one: a surface


def smallest_eigenvector(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(unit eigenvector of the smallest eigenvalue, smallest, middle eigenvalue) of symmetric
    (N, 3, 3) matrices, in closed form (the trigonometric solution of the characteristic cubic).
    Written out entry by entry on contiguous (N,) vectors: reductions over the small 3-wide
    dimensions and argmax over three rows cost more here than all the arithmetic."""
    a, e, f, _, b, g, _, _, d = c.reshape(-1, 9).T.contiguous()  # the six distinct entries
    q = (a + b + d) / 3
    a0, b0, d0 = a - q, b - q, d - q
    p = torch.sqrt((a0 * a0 + b0 * b0 + d0 * d0 + 2 * (e * e + f * f + g * g)) / 6).clamp_min(1e-12)
    det = a0 * (b0 * d0 - g * g) - e * (e * d0 - g * f) + f * (e * g - b0 * f)  # of C - q I
    phi = torch.acos((det / (2 * p**3)).clamp(-1.0, 1.0)) / 3
    largest = q + 2 * p * torch.cos(phi)
    smallest = q + 2 * p * torch.cos(phi + 2 * math.pi / 3)
    middle = 3 * q - largest - smallest
    # the eigenvector is orthogonal to every row of C - lambda I: the longest cross product of two rows
    a1, b1, d1 = a - smallest, b - smallest, d - smallest
    crosses = torch.stack([e * g - f * b1, f * e - a1 * g, a1 * b1 - e * e,  # rows 0 x 1
                           e * d1 - f * g, f * f - a1 * d1, a1 * g - e * f,  # rows 0 x 2
                           b1 * d1 - g * g, g * f - e * d1, e * g - b1 * f]).reshape(3, 3, -1)  # rows 1 x 2
    n0, n1, n2 = (crosses * crosses).sum(1)
    first = n0 >= n1
    best, longest = torch.where(first, crosses[0], crosses[1]), torch.where(first, n0, n1)
    third = n2 > longest
    best, longest = torch.where(third, crosses[2], best), torch.where(third, n2, longest)
    return (best / longest.sqrt().clamp_min(1e-12)).T, smallest, middle


def voxel_hessian(level: Level, means: torch.Tensor, batch_size: int) -> torch.Tensor:
    """(B, 6, 6) point-to-plane Hessians sum_v J_v^T J_v, J_v = [n_v, p_v x n_v] (translation first,
    as the labels' axes), over the planar voxels of each scan: each voxel's mean point with the
    normal of its 3x3x3 neighbourhood. The ICP that makes the labels thins its scans to voxels too,
    so every voxel weighs one."""
    return _planar_hessians([level.neighbours()], [means], level.coords[:, 0], batch_size)


def _planar_hessians(tables: list[torch.Tensor], means: list[torch.Tensor], groups: torch.Tensor,
                     count: int) -> torch.Tensor:
    """(count, 6, 6): voxel_hessian over sets of voxels, each set with its (N, 27) neighbour rows
    (N: empty), and an ascending group index for each voxel of the sets stacked (a scan, or a scan
    at one level)."""
    voxels, scatter = map(torch.cat, zip(*(_neighbourhood_scatter(t, m) for t, m in zip(tables, means))))
    means = torch.cat(means).double()
    normal, smallest, middle = smallest_eigenvector(scatter)
    planar = (voxels >= MIN_NEIGHBOURS) & (smallest < PLANARITY * middle)
    rows = torch.cat([normal, torch.linalg.cross(means, normal)], dim=1)[planar]
    sizes = torch.bincount(groups[planar], minlength=count).tolist()
    return torch.stack([r.T @ r for r in torch.split(rows, sizes)])


def _neighbourhood_scatter(table: torch.Tensor, means: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per voxel, the number of occupied voxels in its 3x3x3 block and the scatter of their mean
    points, from the block's summed moments (1, p, p p^T): one sparse product. In float64, as the moments
    are about the sensor and float32 would cancel the scatter of far voxels."""
    n = len(means)
    means = means.double()
    moments = torch.cat([torch.ones(n, 1, dtype=means.dtype), means,
                         (means[:, :, None] * means[:, None, :]).reshape(n, 9)], dim=1)
    # the block sums as a sparse (N, N) product: three quarters of the table's entries are empty,
    # so this moves a third less memory than gathering all 27 rows and summing them
    occupied = table < n
    starts = torch.cat([occupied.new_zeros(1, dtype=torch.int64), occupied.sum(1).cumsum(0)])
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the product is exact here
        warnings.simplefilter("ignore", UserWarning)
        pairs = table[occupied]
        blocks = torch.sparse_csr_tensor(starts, pairs, torch.ones(len(pairs), dtype=moments.dtype), (n, n))
    summed = blocks @ moments
    voxels = summed[:, 0]
    centre = summed[:, 1:4] / voxels[:, None]
    return voxels, summed[:, 4:].reshape(n, 3, 3) / voxels[:, None, None] - centre[:, :, None] * centre[:, None, :]


def coarser_means(level: Level, means: torch.Tensor) -> tuple[Level, torch.Tensor]:
    """The next coarser level (the network's own, cached on `level`) and the mean of each coarse
    voxel's finer mean points: every finer voxel weighs one, whatever its point count."""
    coarse, _, parent, _ = level.coarser()
    count = torch.zeros(len(coarse.coords), dtype=means.dtype).index_add_(0, parent, torch.ones_like(means[:, 0]))
    summed = torch.zeros(len(coarse.coords), 3, dtype=means.dtype).index_add_(0, parent, means)
    return coarse, summed / count[:, None]


def scan_features(level: Level, means: torch.Tensor, batch_size: int, levels: tuple[int, ...] = (0,)) -> torch.Tensor:
    """(B, FEATURES * len(levels)): the Hessian features of each of `levels` (0: the finest voxels).
    The levels' voxels, once their neighbourhoods are summed, go through one pass, as if each level
    were more scans of the batch: the work is small and the operations' overhead would otherwise be
    paid once per level."""
    tables, points, groups = [], [], []
    for k in range(max(levels) + 1):
        if k in levels:
            tables.append(level.neighbours())
            points.append(means)
            groups.append(level.coords[:, 0] + len(groups) * batch_size)
        if k < max(levels):
            level, means = coarser_means(level, means)
    hessians = _planar_hessians(tables, points, torch.cat(groups), batch_size * len(levels))
    per_level = hessian_features(hessians).reshape(len(levels), batch_size, FEATURES)
    return per_level.permute(1, 0, 2).reshape(batch_size, -1)


def hessian_features(hessian: torch.Tensor) -> torch.Tensor:
    """(B, 12): log diag(H^-1) (how far each axis can move for a unit rise in the cost, the other
    axes free) and log eigenvalues of H. A small ridge keeps a scan with no constraint on an axis
    finite (and large) instead of singular."""
    h = hessian.double()  # the eigenvalues span several decades
    ridge = 1e-6 * h.diagonal(dim1=1, dim2=2).sum(1).clamp_min(1e-6)
    h = h + ridge[:, None, None] * torch.eye(6, dtype=h.dtype)
    variances = torch.linalg.inv(h).diagonal(dim1=1, dim2=2)
    eigenvalues = torch.linalg.eigvalsh(h).clamp_min(1e-3)
    return torch.cat([variances.log(), eigenvalues.log()], dim=1).float()


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
