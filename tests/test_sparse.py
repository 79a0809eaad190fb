"""The pure-PyTorch sparse convolutions against torch's dense Conv3d on a small grid."""
import pytest
import torch

from l3e_env.sparse import (
    OFFSETS_2, OFFSETS_3, DownConv, Level, SubmanifoldConv, UpConv, global_max_pool, hash_coords, voxelize,
)


def _sparse_grid(seed: int, size: int = 6, fill: float = 0.3, batch: int = 2, channels: int = 3):
    g = torch.Generator().manual_seed(seed)
    dense = torch.zeros(batch, channels, size, size, size, dtype=torch.float64)
    active = torch.rand(batch, size, size, size, generator=g) < fill
    coords = active.nonzero()  # (N, 4): batch, x, y, z
    feats = torch.randn(len(coords), channels, generator=g, dtype=torch.float64)
    dense[coords[:, 0], :, coords[:, 1], coords[:, 2], coords[:, 3]] = feats
    return coords, feats, dense


def _at(dense_out: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    return dense_out[coords[:, 0], :, coords[:, 1], coords[:, 2], coords[:, 3]]


def _compare(sparse_out, dense_out, coords, sparse_params, dense_params, inputs):
    """Same values at the active sites, and the same gradients of a random loss on them."""
    assert torch.allclose(sparse_out, _at(dense_out, coords), atol=1e-10)
    w = torch.randn(sparse_out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    grads_s = torch.autograd.grad((sparse_out * w).sum(), [inputs[0], *sparse_params])
    grads_d = torch.autograd.grad((_at(dense_out, coords) * w).sum(), [inputs[1], *dense_params])
    return grads_s, grads_d


@pytest.mark.parametrize("order", ["sorted", "shuffled", "keyed"])
def test_submanifold_conv_matches_dense_conv3d(order: str):
    coords, feats, dense = _sparse_grid(0)
    if order == "shuffled":  # sites in no particular order: the kernel map must map sorted keys back to rows
        order = torch.randperm(len(coords), generator=torch.Generator().manual_seed(3))
        coords, feats = coords[order], feats[order]
    feats.requires_grad_(True)
    dense.requires_grad_(True)
    sconv = SubmanifoldConv(3, 4, bias=True).double()
    conv = torch.nn.Conv3d(3, 4, 3, padding=1).double()
    with torch.no_grad():  # conv weight (out, in, kx, ky, kz) <- ours (k, in, out)
        for k, (dx, dy, dz) in enumerate(OFFSETS_3.tolist()):
            conv.weight[:, :, dx + 1, dy + 1, dz + 1] = sconv.weight[k].T
        conv.bias.copy_(sconv.bias)
    # "keyed": the sorted rows' keys come with them (as from voxelize), so a key's position is its row
    level = Level(coords, 1, hash_coords(coords) if order == "keyed" else None)
    assert level.index.sorted == (order == "keyed")
    out_s, out_d = sconv(feats, level), conv(dense)
    (gx, gw, gb), (gxd, gwd, gbd) = _compare(out_s, out_d, coords, [sconv.weight, sconv.bias],
                                             [conv.weight, conv.bias], (feats, dense))
    assert torch.allclose(gx, _at(gxd, coords), atol=1e-10)
    for k, (dx, dy, dz) in enumerate(OFFSETS_3.tolist()):
        assert torch.allclose(gw[k], gwd[:, :, dx + 1, dy + 1, dz + 1].T, atol=1e-10)
    assert torch.allclose(gb, gbd, atol=1e-10)


def test_strided_down_conv_matches_dense_conv3d():
    coords, feats, dense = _sparse_grid(1)
    feats.requires_grad_(True)
    dense.requires_grad_(True)
    down = DownConv(3, 5).double()
    conv = torch.nn.Conv3d(3, 5, 2, stride=2, bias=False).double()
    with torch.no_grad():
        for k, (dx, dy, dz) in enumerate(OFFSETS_2.tolist()):
            conv.weight[:, :, dx, dy, dz] = down.weight[k].T
    out_s, coarse = down(feats, Level(coords, 1))
    assert coarse.stride == 2 and len(coarse.coords) < len(coords)
    out_d = conv(dense)
    (gx, gw), (gxd, gwd) = _compare(out_s, out_d, coarse.coords, [down.weight], [conv.weight], (feats, dense))
    assert torch.allclose(gx, _at(gxd, coords), atol=1e-10)
    for k, (dx, dy, dz) in enumerate(OFFSETS_2.tolist()):
        assert torch.allclose(gw[k], gwd[:, :, dx, dy, dz].T, atol=1e-10)
    # the coarse sites are exactly the cells with at least one active child
    dense_active = torch.nn.functional.max_pool3d((dense.abs().sum(1, keepdim=True) > 0).double(), 2)
    assert set(map(tuple, coarse.coords.tolist())) == set(map(tuple, dense_active[:, 0].nonzero().tolist()))


def test_transposed_up_conv_matches_dense_conv_transpose3d():
    coords, _, _ = _sparse_grid(2)
    fine = Level(coords, 1)
    coarse, _, _, _ = fine.coarser()
    g = torch.Generator().manual_seed(3)
    x = torch.randn(len(coarse.coords), 4, dtype=torch.float64, generator=g, requires_grad=True)
    dense_x = torch.zeros(2, 4, 3, 3, 3, dtype=torch.float64)
    c = coarse.coords
    dense_x[c[:, 0], :, c[:, 1], c[:, 2], c[:, 3]] = x.detach()
    dense_x.requires_grad_(True)
    up = UpConv(4, 2).double()
    tconv = torch.nn.ConvTranspose3d(4, 2, 2, stride=2, bias=False).double()
    with torch.no_grad():  # weight (in, out, kx, ky, kz)
        for k, (dx, dy, dz) in enumerate(OFFSETS_2.tolist()):
            tconv.weight[:, :, dx, dy, dz] = up.weight[k]
    out_s, out_d = up(x, fine), tconv(dense_x)
    (gx, gw), (gxd, gwd) = _compare(out_s, out_d, coords, [up.weight], [tconv.weight], (x, dense_x))
    assert torch.allclose(gx, _at(gxd, c), atol=1e-10)
    for k, (dx, dy, dz) in enumerate(OFFSETS_2.tolist()):
        assert torch.allclose(gw[k], gwd[:, :, dx, dy, dz], atol=1e-10)


def test_voxelize_and_pool_keep_scans_apart():
    a = torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.1, 0.0], [1.0, 1.0, 1.0]])
    b = torch.tensor([[0.05, 0.05, 0.05]])
    level, means, rows = voxelize([a, b], 0.2)
    assert len(level.coords) == 3  # two voxels in scan 0, one in scan 1
    assert torch.allclose(means[rows[0]], torch.tensor([0.1, 0.075, 0.025]))
    feats = torch.tensor([[1.0], [5.0], [2.0]])
    pooled = global_max_pool(feats, level, 2)
    assert pooled[:, 0].tolist() == [5.0, 2.0]
    alone, _, _ = voxelize([a], 0.2)  # one scan takes a shortcut of its own
    assert global_max_pool(torch.tensor([[1.0, -3.0], [5.0, -4.0]]), alone, 1).tolist() == [[5.0, -3.0]]


def test_far_coordinates_are_refused():
    with pytest.raises(ValueError, match="too far"):
        Level(torch.tensor([[0, 40000, 0, 0]]), 1).neighbours()
