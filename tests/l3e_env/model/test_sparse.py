"""The pure-PyTorch sparse convolutions against torch's dense Conv3d on a small grid."""

import pytest
import torch

from l3e_env.model.sparse import (
    OFFSETS_2,
    OFFSETS_3,
    DownConv,
    Level,
    SubmanifoldConv,
    UpConv,
    _int8_rows,
    global_max_pool,
    int8_products_work,
    voxelize,
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


@pytest.mark.parametrize("order", ["sorted", "shuffled"])
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
    level = Level(coords, 1)
    out_s, out_d = sconv(feats, level), conv(dense)
    (gx, gw, gb), (gxd, gwd, gbd) = _compare(
        out_s, out_d, coords, [sconv.weight, sconv.bias], [conv.weight, conv.bias], (feats, dense)
    )
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


@pytest.mark.skipif(not int8_products_work(), reason="this torch build has no CPU int8 products")
@pytest.mark.parametrize("conv_type", [SubmanifoldConv, DownConv])
def test_int8_convolution_is_close_to_float32_and_scales_each_scan_alone(conv_type):
    coords, feats, _ = _sparse_grid(4, size=8, fill=0.4, channels=16)
    feats = feats.float().relu()  # as after a ReLU, the inputs of the quantised convolutions
    torch.manual_seed(0)
    conv = conv_type(16, 24)
    conv.bias = torch.nn.Parameter(torch.randn(24))  # as after fold_batch_norms
    level = Level(coords, 1)

    def run(x, lv):
        out = conv(x, lv)
        return out[0] if isinstance(out, tuple) else out

    exact = run(feats, level)
    conv.quantize()
    assert conv.int8_weight.dtype == torch.int8
    rounded = run(feats, level)
    assert (rounded - exact).abs().max() < 0.02 * exact.abs().max()  # 8 bits: about 1 % of the range
    assert not torch.equal(rounded, exact)  # the int8 path did run
    # scan 0 a hundred times louder: scan 1 keeps its own scale, so its outputs do not move
    louder = feats.clone()
    louder[coords[:, 0] == 0] *= 100
    out_coords = level.coarser()[0].coords if conv_type is DownConv else coords
    second = out_coords[:, 0] == 1
    assert torch.allclose(run(louder, level)[second], rounded[second], atol=1e-5)
    assert not torch.allclose(run(louder, level)[~second], rounded[~second], atol=1e-3)


def test_int8_rows_are_the_features_rounded_with_the_empty_row_last():
    g = torch.Generator().manual_seed(3)
    after_relu, signed = torch.rand(60, 16, generator=g) * 3, torch.randn(60, 16, generator=g)
    for x in (after_relu, signed):  # the two roundings of one scan
        rows, scale = _int8_rows(x, None)
        assert rows.dtype == torch.int8 and rows.shape == (61, 16) and not rows[-1].any()
        assert scale == pytest.approx(float(x.abs().max()) / 127)
        assert ((rows[:-1] - x / scale).abs() <= 0.5 + 1e-4).all()  # to the nearest step
    batch = torch.tensor([0] * 30 + [1] * 30)
    rows, scales = _int8_rows(signed, batch)
    assert torch.allclose(scales, torch.stack([signed[:30].abs().max(), signed[30:].abs().max()]) / 127)
    assert ((rows[:-1] - signed / scales[batch, None]).abs() <= 0.5 + 1e-4).all() and not rows[-1].any()


def test_kernel_maps_read_off_the_coarser_level_equal_the_searched_ones():
    g = torch.Generator().manual_seed(5)
    coords = torch.unique(
        torch.cat(
            [
                torch.randint(0, 3, (600, 1), generator=g),  # three scans
                torch.randint(-9, 9, (600, 3), generator=g),
            ],
            dim=1,
        ),
        dim=0,
    )
    searched = [Level(coords, 1)]
    derived = [Level(coords, 1)]
    for _ in range(3):
        coarse = Level(searched[-1].coords, 1).coarser()[0].coords  # on a copy: `searched` keeps no coarser level
        searched.append(Level(coarse, searched[-1].stride * 2))
        derived.append(derived[-1].coarser()[0])
    for s, d in zip(searched, derived):  # each derived level but the last comes from its coarser one
        assert torch.equal(s.neighbours(), d.neighbours())
    assert derived[0]._coarser is not None and searched[0]._coarser is None
    # every table entry is a true 3x3x3 neighbour or the empty row, and some of both occur
    table = derived[0].neighbours()
    found = table < len(coords)
    assert 0 < found.float().mean() < 1
    rows, k = found.nonzero(as_tuple=True)
    same_scan_offsets = torch.cat([torch.zeros_like(rows)[:, None], OFFSETS_3[k]], 1)
    assert torch.equal(coords[table[rows, k]] - coords[rows], same_scan_offsets)


def test_voxelize_orders_sites_so_that_coarser_levels_need_no_sort():
    g = torch.Generator().manual_seed(6)
    scans = [torch.randn(400, 3, generator=g) * 2.0 - 1.0 for _ in range(3)]  # negative coordinates too
    level, means, rows = voxelize(scans, 0.2)
    assert torch.equal(level.coords[:, 0], level.coords[:, 0].sort().values)  # scans in order
    point_cells = torch.floor(torch.cat(scans) / 0.2).long()
    assert torch.equal(level.coords[rows, 1:], point_cells)  # every point lies in its voxel
    sizes = [len(level.coords)]
    for _ in range(3):
        generic = Level(level.coords.clone(), level.stride)  # no keys: coarser() sorts for itself
        fast, slow = level.coarser(), generic.coarser()
        for a, b in zip(fast, slow):
            assert torch.equal(a.coords, b.coords) if isinstance(a, Level) else torch.equal(a, b)
        coarse, children, parent, slot = fast
        assert torch.equal(coarse.coords[parent, 1:], torch.div(level.coords[:, 1:], 2, rounding_mode="floor"))
        assert torch.equal(level.coords[:, 1:] - 2 * coarse.coords[parent, 1:], OFFSETS_2[slot])
        assert torch.equal(children[parent, slot], torch.arange(len(level.coords)))
        level = coarse
        sizes.append(len(level.coords))
    assert sizes == sorted(sizes, reverse=True) and sizes[-1] < sizes[0] / 2


def _scans(seed: int, count: int = 3) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [(torch.rand(400 + 150 * k, 3, generator=g) - 0.5) * torch.tensor([30.0, 20.0, 6.0]) for k in range(count)]


def _levels(points: list[torch.Tensor], depth: int = 3) -> list[tuple]:
    """voxelize and the coarser levels' tables, as the network builds them (coarser levels first)."""
    level, mean, inverse = voxelize(points, 0.2)
    levels = [level]
    for _ in range(depth):
        levels.append(levels[-1].coarser()[0])
    parts = [(mean, inverse)]
    for lv in levels:
        parts.append((lv.coords, lv.neighbours(), *(lv.coarser()[1:] if lv is not levels[-1] else ())))
    return parts


def test_the_torch_bookkeeping_gives_the_compiled_loops_tables(monkeypatch):
    """On a GPU the voxels, kernel maps and parent tables are made by whole-array torch operations;
    here both ways run on the CPU and must give the same tables (the means to float rounding)."""
    import l3e_env.model.sparse as sparse

    points = _scans(3)
    compiled = _levels(points)
    monkeypatch.setattr(sparse, "_by_torch", lambda t: True)
    by_torch = _levels(points)
    assert torch.allclose(compiled[0][0], by_torch[0][0], atol=1e-5) and torch.equal(compiled[0][1], by_torch[0][1])
    for ours, theirs in zip(compiled[1:], by_torch[1:]):
        assert all(torch.equal(a, b) for a, b in zip(ours, theirs))
    sparse_level = Level(torch.tensor([[0, 5, 5, 5], [0, 40000, 0, 0]]), 1)
    with pytest.raises(ValueError, match="beyond"):
        sparse_level.neighbours()


def test_the_network_answers_alike_by_either_bookkeeping(monkeypatch):
    """The whole ResUNet (surface rows, information pooling, constraint features) gives the same
    logits and gradients with the torch bookkeeping as with the compiled loops."""
    import l3e_env.model.sparse as sparse
    from l3e_env.model.classifier import LocalizabilityNet, ModelConfig

    torch.manual_seed(0)
    model = LocalizabilityNet(ModelConfig(pooling="information", surface_rows=True, constraints=True)).eval()
    points = _scans(5, count=2)

    def run() -> tuple[torch.Tensor, torch.Tensor]:
        model.zero_grad()
        logits = model(points)
        logits.square().sum().backward()
        return logits.detach(), model.backbone.stem.weight.grad.clone()

    logits, grad = run()
    monkeypatch.setattr(sparse, "_by_torch", lambda t: True)
    logits_t, grad_t = run()
    assert torch.allclose(logits, logits_t, atol=1e-5) and torch.allclose(grad, grad_t, rtol=1e-4, atol=1e-6)
