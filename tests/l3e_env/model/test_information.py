"""Information pooling: learned-weight point-to-plane information matrices summed over the scan."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from l3e_env.model.classifier import LocalizabilityNet, ModelConfig, fold_batch_norms
from l3e_env.model.constraints import hessian_features, scan_features, surface_rows
from l3e_env.model.information import InformationPool, information_features
from l3e_env.model.sparse import voxelize

SMALL = ModelConfig(points=600, channels=(8, 8, 16, 16), head=(16, 16, 16, 16), pooling="information")


def _corridor(rng, length: float = 30.0, n: int = 3000, ends: bool = False) -> torch.Tensor:
    """Points on the walls, floor and ceiling of a 4 m wide corridor along x (a room with its ends)."""
    faces = [(1, -2.0), (1, 2.0), (2, -1.0), (2, 2.0)] + ([(0, -length / 2), (0, length / 2)] if ends else [])
    points = []
    for axis, value in faces:
        p = np.array([0.0, 0.0, 0.5]) + rng.uniform(-1, 1, (n // len(faces), 3)) * [length / 2, 2.0, 1.5]
        p[:, axis] = value
        points.append(p)
    return torch.from_numpy(np.concatenate(points).astype(np.float32))


def test_the_features_of_an_information_matrix_are_the_constraint_layers(rng):
    a = rng.standard_normal((5, 20, 6))
    h = a.transpose(0, 2, 1) @ a
    h[0] = np.diag([1e-9, 1.0, 2.0, 3.0, 4.0, 5.0])  # an unconstrained axis stays finite
    ours = information_features(torch.from_numpy(h)).numpy()
    assert np.isfinite(ours).all()
    np.testing.assert_allclose(ours, hessian_features(h), rtol=1e-4, atol=1e-4)


def test_with_unit_weights_a_head_is_the_scans_hessian_and_the_sum_keeps_scans_apart(rng):
    """One weighting forced to 1 everywhere and an identity norm: the pooled features are those of the
    constraint layer's Hessian of the same voxels, scan by scan."""
    scans = [_corridor(rng), _corridor(rng, ends=True) * 0.5]
    level, means, _ = voxelize(scans, 0.2)
    x = torch.randn(len(means), 8)
    pool = InformationPool(8, 1).eval()
    with torch.no_grad():
        pool.weight.weight.zero_()
        pool.weight.bias.fill_(math.log(math.e - 1))  # softplus(b) = 1
    pooled = pool(x, surface_rows(level, means), level.coords[:, 0], 2)
    np.testing.assert_allclose(pooled.detach().numpy(), scan_features(level, means, 2).numpy(), rtol=1e-3, atol=1e-3)
    variances = pooled[:, :6].detach().numpy()
    assert variances[0, 0] > variances[1, 0] + 2  # the open corridor leaves x free, the closed room holds it


def test_the_weights_learn_and_the_model_stays_mirror_invariant_and_foldable(rng):
    torch.manual_seed(0)
    net = LocalizabilityNet(dataclasses.replace(SMALL, frame="canonical"))
    scan = _corridor(rng) + torch.tensor([3.0, -0.5, 0.0])
    out = net([scan, scan * 1.3])
    out.sum().backward()
    assert out.shape == (2, 6) and net.backbone.information.weight.weight.grad.abs().sum() > 0
    net.eval()
    with torch.no_grad():
        own = net([scan])
        mirrored = net([scan * torch.tensor([-1.0, 1.0, 1.0])])
        assert torch.allclose(own, mirrored, atol=1e-4)
        folded = fold_batch_norms(net)([scan])
    assert torch.allclose(own, folded, atol=1e-3)


def test_bad_pooling_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="unknown pooling"):
        LocalizabilityNet(dataclasses.replace(SMALL, pooling="mean"))
    with pytest.raises(ValueError, match="PointNet"):
        LocalizabilityNet(dataclasses.replace(SMALL, architecture="pointnet"))
    with pytest.raises(ValueError, match="at least one weighting"):
        LocalizabilityNet(dataclasses.replace(SMALL, information_heads=0))
