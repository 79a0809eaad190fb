"""Information pooling: the scan's point-to-plane information matrix, each voxel weighed by the network.

A max pool keeps, per channel, the one voxel that answers most; whether registration can localize an
axis is a sum over every voxel of what it constrains (ICP's Hessian H = sum of J J^T, J = [n, p x n]).
A network that pools by max has to learn to count; one that pools by that sum has the physics built in
and learns only what the closed-form Hessian gets wrong: which surfaces the registration actually
holds on to (thinned, far, grazing, cluttered), read from each voxel's neighbourhood 10-30 m wide.

Each of `heads` weightings w_k(v) >= 0 of the finest voxels (a linear map of the decoder's feature,
softplus) gives one matrix H_k = sum_v w_k(v) J_v J_v^T per scan; its features are those of the
constraint layer (log diag(H_k^-1), log eigenvalues), normalised by a batch norm, and they join the
max-pooled feature before the head. Everything is differentiable: the 6x6 inverse and eigenvalues in
float64. With w = 1 a head is the constraint layer's Hessian of the same voxels.
"""

from __future__ import annotations

import torch
from torch import nn

from .constraints import FEATURES

ROW = 6  # J = [n, p x n]: translation first, as the labels' axes


class InformationPool(nn.Module):
    """(B, heads * FEATURES) features of the learned-weight information matrices of a batch of scans."""

    def __init__(self, channels: int, heads: int):
        super().__init__()
        if heads < 1:
            raise ValueError(f"information pooling needs at least one weighting, not {heads}")
        self.heads = heads
        self.weight = nn.Linear(channels, heads)
        self.norm = nn.BatchNorm1d(heads * FEATURES)

    def forward(self, x: torch.Tensor, rows: torch.Tensor, scan: torch.Tensor, batch_size: int) -> torch.Tensor:
        """x (V, C): the finest voxels' features; rows (V, 7): their surface rows (J and whether
        planar, l3e_env.model.constraints.surface_rows; J is zero where not planar); scan (V,): the
        scan of each voxel, the scans' voxels one after another (as l3e_env.model.sparse.voxelize
        orders them)."""
        weights = nn.functional.softplus(self.weight(x))  # (V, K)
        counts = torch.bincount(scan, minlength=batch_size).tolist()
        j = rows[:, :ROW]
        # sums of a few thousand rows in float32 (relative error 1e-6); inverted in float64
        summed = [torch.einsum("vk,vi,vj->kij", w, a, a) for w, a in zip(weights.split(counts), j.split(counts))]
        features = information_features(torch.stack(summed).double().reshape(-1, ROW, ROW))
        return self.norm(features.reshape(batch_size, -1).float())


def information_features(h: torch.Tensor) -> torch.Tensor:
    """(N, FEATURES) of (N, 6, 6) information matrices: log diag(H^-1) and log eigenvalues, a small
    ridge keeping an unconstrained axis finite, as l3e_env.model.constraints.hessian_features."""
    eye = torch.eye(ROW, dtype=h.dtype, device=h.device)
    ridge = 1e-6 * torch.diagonal(h, dim1=1, dim2=2).sum(1).clamp_min(1e-6)
    h = h + ridge[:, None, None] * eye
    variances = torch.diagonal(torch.linalg.inv(h), dim1=1, dim2=2).clamp_min(1e-12)
    eigenvalues = torch.linalg.eigvalsh(h).clamp_min(1e-3)
    return torch.cat([variances.log(), eigenvalues.log()], dim=1)
