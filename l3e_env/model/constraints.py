"""What the geometry of a scan constrains: its point-to-plane Hessian, and a per-axis logistic
layer that weighs it against the network's logits.

The network learns the scene families it was trained on; the Hessian is what point-to-plane ICP
itself linearises, so it carries over to families never seen. On the mine and caves of the test
split, the marginal variances diag(H^-1) of the model's own 0.2 m voxels rank the labels better than
the network does on every axis, y only just (docs/log.md). A logistic layer per axis over the
network's logit, the six log marginal variances and the six log eigenvalues (13 weights an axis
for one level) is fitted on the training scenes after the network, so it cannot overfit the way a layer trained
with the network would. The same twelve features of the next coarser level (0.4 m voxels, normals of
1.2 m blocks) can be added (ModelConfig.constraint_levels): they see the larger structure that the
registration's coarse first stage locks onto, and they help on scene families never trained on
(docs/log.md).

The normals are those of the 3x3x3 voxel neighbourhood of each voxel, from a closed-form
eigen-decomposition of the 3x3 scatter (torch.linalg.eigh on a few thousand 3x3 matrices costs
4 ms here). The Hessian is summed by a loop compiled with numba, one voxel at a time: numpy's
operations on arrays of a few thousand voxels cost more in overhead than in arithmetic.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import nn

from l3e_env.core.normals import closed_form_normal

from .sparse import Level

FEATURES = 12  # per level: log diag(H^-1) (6), log eigenvalues of H (6)
MIN_NEIGHBOURS = 4  # occupied voxels in the 3x3x3 block, the voxel itself included, for a normal
PLANARITY = 0.1  # smallest scatter eigenvalue under this share of the middle one: a surface


def voxel_hessian(level: Level, means: torch.Tensor, batch_size: int) -> np.ndarray:
    """(B, 6, 6) point-to-plane Hessians sum_v J_v^T J_v, J_v = [n_v, p_v x n_v] (translation first,
    as the labels' axes), over the planar voxels of each scan: each voxel's mean point with the
    normal of its 3x3x3 neighbourhood. The ICP that makes the labels thins its scans to voxels too,
    so every voxel weighs one."""
    hessians = np.zeros((batch_size, 6, 6))
    _add_planar_hessians(
        level.neighbours().numpy(), means.numpy().astype(np.float64), level.coords[:, 0].numpy(), hessians
    )
    return hessians


@njit(cache=True, nogil=True)
def _planar_row(neighbours: np.ndarray, means: np.ndarray, v: int, row: np.ndarray) -> bool:
    """Write voxel v's point-to-plane row J_v = [n_v, p_v x n_v] into `row` (n_v turned to face the
    sensor) and say whether the voxel is planar: the normal is that of the scatter of the mean
    points of its 3x3x3 block (`neighbours`, len(means): empty), in float64 since the moments are
    about the sensor and float32 would cancel the scatter of far voxels."""
    n = len(means)
    count = 0
    sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
    for u in neighbours:
        if u < n:
            x, y, z = means[u, 0], means[u, 1], means[u, 2]
            count += 1
            sx += x
            sy += y
            sz += z
            sxx += x * x
            sxy += x * y
            sxz += x * z
            syy += y * y
            syz += y * z
            szz += z * z
    if count < MIN_NEIGHBOURS:
        return False
    mx, my, mz = sx / count, sy / count, sz / count
    nx, ny, nz, smallest, middle = closed_form_normal(
        sxx / count - mx * mx,
        sxy / count - mx * my,
        sxz / count - mx * mz,
        syy / count - my * my,
        syz / count - my * mz,
        szz / count - mz * mz,
    )
    if not smallest < PLANARITY * middle:
        return False
    px, py, pz = means[v, 0], means[v, 1], means[v, 2]
    if nx * px + ny * py + nz * pz > 0:  # facing the sensor; J J^T does not care
        nx, ny, nz = -nx, -ny, -nz
    row[0], row[1], row[2] = nx, ny, nz
    row[3], row[4], row[5] = py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx  # p x n
    return True


@njit(cache=True, nogil=True)
def _add_planar_hessians(table: np.ndarray, means: np.ndarray, groups: np.ndarray, hessians: np.ndarray) -> None:
    """hessians[groups[v]] += J_v^T J_v over the planar voxels v (`_planar_row`), each voxel with its
    (27,) row of neighbours in `table`.

    A compiled loop, one voxel at a time: in numpy the same work is some sixty passes over a few
    thousand voxels, whose per-operation overhead cost several times the arithmetic
    (docs/log.md)."""
    row = np.empty(6)
    for v in range(len(means)):
        if not _planar_row(table[v], means, v, row):
            continue
        hessian = hessians[groups[v]]
        for i in range(6):
            for j in range(6):
                hessian[i, j] += row[i] * row[j]


@njit(cache=True, nogil=True)
def _planar_rows(table: np.ndarray, means: np.ndarray, rows: np.ndarray) -> None:
    """rows[v] = (J_v, 1) for the planar voxels v; other rows are left as they are (zeros)."""
    row = np.empty(6)
    for v in range(len(means)):
        if _planar_row(table[v], means, v, row):
            rows[v, :6] = row
            rows[v, 6] = 1.0


SURFACE_FEATURES = 7  # a voxel's J = [n, p x n] and whether it is planar


def surface_rows(level: Level, means: torch.Tensor) -> torch.Tensor:
    """(V, 7) float32 per voxel: its point-to-plane row J = [n, p x n] (the normal facing the sensor)
    and 1 where its 3x3x3 block is planar; zeros where it is not. The Hessian is the sum of J J^T;
    a network fed J sees what each voxel constrains, in any scene."""
    rows = np.zeros((len(means), SURFACE_FEATURES))  # compiled loops on the CPU, whatever the device
    _planar_rows(level.neighbours().cpu().numpy(), means.detach().cpu().numpy().astype(np.float64), rows)
    return torch.from_numpy(rows.astype(np.float32)).to(means.device)


def coarser_means(level: Level, means: np.ndarray) -> tuple[Level, np.ndarray]:
    """The next coarser level (the network's own, cached on `level`) and the mean of each coarse
    voxel's finer mean points: every finer voxel weighs one, whatever its point count."""
    coarse, _, parents, _ = level.coarser()
    parent, size = parents.cpu().numpy(), len(coarse.coords)
    summed = np.stack([np.bincount(parent, weights=means[:, k], minlength=size) for k in range(3)], axis=1)
    return coarse, summed / np.bincount(parent, minlength=size)[:, None]  # float64, as the moments


def scan_features(level: Level, means: torch.Tensor, batch_size: int, levels: tuple[int, ...] = (0,)) -> torch.Tensor:
    """(B, FEATURES * len(levels)): the Hessian features of each of `levels` (0: the finest voxels)."""
    hessians = np.zeros((len(levels), batch_size, 6, 6))
    device, points = means.device, means.detach().cpu().numpy().astype(np.float64)
    for k in range(max(levels) + 1):
        if k in levels:  # compiled loops on the CPU, whatever the device
            _add_planar_hessians(
                level.neighbours().cpu().numpy(), points, level.coords[:, 0].cpu().numpy(), hessians[levels.index(k)]
            )
        if k < max(levels):
            level, points = coarser_means(level, points)
    per_level = hessian_features(hessians.reshape(-1, 6, 6)).reshape(len(levels), batch_size, FEATURES)
    return torch.from_numpy(np.ascontiguousarray(per_level.transpose(1, 0, 2).reshape(batch_size, -1))).to(device)


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

    mean: torch.Tensor  # buffers, registered below
    std: torch.Tensor

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
