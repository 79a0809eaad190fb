"""Sparse 3D convolution in pure PyTorch: kernel maps by coordinate hashing, gather, matmul.

Written by hand because MinkowskiEngine does not build on current torch, spconv's CPU build
cannot back-propagate and torchsparse is not on the package registry. The scheme is
"gather-GEMM": for every output site a table holds the row of the input feature at each
kernel offset (or a zero row when that neighbour is empty); the features are gathered into
one (N, K * C_in) matrix and multiplied once by the (K * C_in, C_out) weight. Autograd turns
the gather into a scatter-add in the backward pass, so gradients need no extra code.

Coordinates are int64 (N, 4) rows (batch, x, y, z) in voxel units of the current level.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import torch
from torch import nn

_BITS = 16  # per spatial axis: +-32768 voxels, 6.5 km at 0.2 m
_SHIFT = 1 << (_BITS - 1)
OFFSETS_3 = torch.tensor(list(itertools.product((-1, 0, 1), repeat=3)), dtype=torch.int64)  # (27, 3)
OFFSETS_2 = torch.tensor(list(itertools.product((0, 1), repeat=3)), dtype=torch.int64)  # (8, 3)


def hash_coords(coords: torch.Tensor, check: bool = True) -> torch.Tensor:
    """One int64 key per (batch, x, y, z) row; order-preserving in batch, then x, y, z."""
    xyz = coords[:, 1:] + _SHIFT
    if check and bool((xyz < 0).any() | (xyz >= 1 << _BITS).any()):
        raise ValueError(f"voxel coordinates beyond +-{_SHIFT}; the scan extends too far for this voxel size")
    return (coords[:, 0] << 3 * _BITS) | (xyz[:, 0] << 2 * _BITS) | (xyz[:, 1] << _BITS) | xyz[:, 2]


def unhash_coords(keys: torch.Tensor) -> torch.Tensor:
    mask = (1 << _BITS) - 1
    xyz = [((keys >> s) & mask) - _SHIFT for s in (2 * _BITS, _BITS, 0)]
    return torch.stack([keys >> 3 * _BITS, *xyz], dim=1)


def unique_coords(coords: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sorted unique rows, the inverse map and the rows' (sorted) keys, through the 1-D keys
    (torch.unique(dim=0) is an order of magnitude slower on CPU)."""
    keys, inverse = torch.unique(hash_coords(coords), return_inverse=True)
    return unhash_coords(keys), inverse, keys


class CoordinateIndex:
    """Sorted hash keys of a set of sites, for vectorised lookup of any list of sites.
    `row_keys` are the sites' keys in row order; given and sorted, they are used as they are."""

    def __init__(self, coords: torch.Tensor, row_keys: torch.Tensor | None = None):
        self.n = len(coords)
        self.row_keys = hash_coords(coords) if row_keys is None else row_keys
        # the row of each sorted key; None when the rows come in key order: a key's position is its row
        self.order: torch.Tensor | None = None
        if row_keys is not None and bool((row_keys[1:] > row_keys[:-1]).all()):
            self.keys = row_keys
        else:
            self.keys, self.order = torch.sort(self.row_keys)

    @property
    def sorted(self) -> bool:
        return self.order is None

    def lookup(self, keys: torch.Tensor) -> torch.Tensor:
        """Row of each queried key, or n (the zero row) where the site is empty."""
        if self.n == 0:
            return torch.zeros_like(keys)
        pos = torch.searchsorted(self.keys, keys).clamp_(max=self.n - 1)
        found = self.keys[pos] == keys
        rows = pos if self.order is None else self.order[pos]
        return torch.where(found, rows, torch.full_like(pos, self.n))


# the key of a neighbour is the site's key plus a constant, because the key is linear in x, y, z
_NEIGHBOUR_DELTAS = (OFFSETS_3[:, 0] << 2 * _BITS) + (OFFSETS_3[:, 1] << _BITS) + OFFSETS_3[:, 2]

# A site in child slot s (OFFSETS_2[s]) of its parent has its neighbour at OFFSETS_3[k] in the
# parent's neighbour _PARENT_OFFSET[s, k] (an OFFSETS_3 row), in child slot _CHILD_SLOT[s, k].
_FINE = OFFSETS_2[:, None, :] + OFFSETS_3[None, :, :]  # (8, 27, 3), each in -1..2
_PARENT_OFFSET = (torch.div(_FINE, 2, rounding_mode="floor") + 1) @ torch.tensor([9, 3, 1])
_CHILD_SLOT = torch.remainder(_FINE, 2) @ torch.tensor([4, 2, 1])


@dataclass
class Level:
    """The active sites of one resolution level and the kernel maps built on them (cached,
    because every convolution at a level shares them)."""

    coords: torch.Tensor  # (N, 4) int64
    stride: int  # in units of the finest voxel
    keys: torch.Tensor | None = field(default=None, repr=False)  # the rows' keys, if already known
    _index: CoordinateIndex | None = field(default=None, repr=False)
    _neighbours: torch.Tensor | None = field(default=None, repr=False)
    _one_scan: bool | None = field(default=None, repr=False)
    _coarser: tuple[Level, torch.Tensor, torch.Tensor, torch.Tensor] | None = field(default=None, repr=False)

    def batch_index(self) -> torch.Tensor | None:
        """The scan of each site, or None when all are of one scan (rows are in scan order)."""
        if self._one_scan is None:
            self._one_scan = len(self.coords) == 0 or int(self.coords[-1, 0]) == 0
        return None if self._one_scan else self.coords[:, 0]

    @property
    def index(self) -> CoordinateIndex:
        if self._index is None:
            self._index = CoordinateIndex(self.coords, self.keys)
        return self._index

    def neighbours(self) -> torch.Tensor:
        """(N, 27) rows of the 3x3x3 neighbours of each site (N where empty). Once the coarser level
        exists (ResUNet.encode builds them all first), the table is read off that level's own:
        every neighbour of a site is a child of a neighbour of the site's parent, so four table
        lookups replace 27 searches of the keys (exact, and 3-4x faster)."""
        if self._neighbours is None:
            if self._coarser is not None:
                coarse, children, parent, slot = self._coarser
                parents = coarse.neighbours().index_select(0, parent).gather(1, _PARENT_OFFSET.index_select(0, slot))
                no_child = children.new_full((8,), len(self.coords))  # the children of "no neighbour"
                rows = torch.cat([children.reshape(-1), no_child])
                self._neighbours = rows.take(parents * 8 + _CHILD_SLOT.index_select(0, slot))
            else:
                index = self.index
                self._neighbours = index.lookup(index.row_keys[:, None] + _NEIGHBOUR_DELTAS)
        return self._neighbours

    def coarser(self) -> tuple[Level, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The level at twice the voxel size, plus (children table (M, 8) of this level's rows,
        parent row of each site here (N,), child slot of each site here (N,))."""
        if self._coarser is None:
            parent = self.coords.clone()
            parent[:, 1:] = torch.div(parent[:, 1:], 2, rounding_mode="floor")
            unique, inverse, keys = unique_coords(parent)
            slot_xyz = self.coords[:, 1:] - 2 * parent[:, 1:]
            slot = slot_xyz[:, 0] * 4 + slot_xyz[:, 1] * 2 + slot_xyz[:, 2]
            children = torch.full((len(unique), 8), len(self.coords), dtype=torch.int64)
            children[inverse, slot] = torch.arange(len(self.coords))
            self._coarser = (Level(unique, self.stride * 2, keys), children, inverse, slot)
        return self._coarser


def _gather_matmul(x: torch.Tensor, table: torch.Tensor, weight: torch.Tensor,
                   bias: torch.Tensor | None = None) -> torch.Tensor:
    """sum_k x[table[:, k]] @ weight[k] (+ bias), with row len(x) of the table meaning 'no neighbour'."""
    padded = torch.cat([x, x.new_zeros(1, x.shape[1])])
    gathered = padded.index_select(0, table.reshape(-1)).reshape(len(table), -1)  # 2x faster than padded[table]
    weight = weight.reshape(-1, weight.shape[-1])
    return gathered @ weight if bias is None else torch.addmm(bias, gathered, weight)


def _init_weight(k: int, c_in: int, c_out: int) -> nn.Parameter:
    w = torch.empty(k, c_in, c_out)
    bound = math.sqrt(6.0 / (k * c_in))  # He-uniform for ReLU networks
    nn.init.uniform_(w, -bound, bound)
    return nn.Parameter(w)


def int8_products_work() -> bool:
    """Whether this torch build multiplies int8 matrices (torch._int_mm) on the CPU."""
    try:
        a = torch.ones(3, 5, dtype=torch.int8)
        return bool(torch._int_mm(a, a.T.contiguous()).eq(5).all())
    except (AttributeError, RuntimeError, NotImplementedError):
        return False


def _int8_rows(x: torch.Tensor, batch: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """x rounded to int8 with one scale per scan (so that a scan's answer does not depend on the
    other scans of its batch), a zero row appended for the empty neighbour; and the scales, one
    per scan ((B,), a scalar tensor for one scan)."""
    if batch is None:
        low, high = torch.aminmax(x)  # one pass, and no |x| copy
        scale = torch.maximum(-low, high) / 127
    else:
        scale = x.new_zeros(int(batch[-1]) + 1).scatter_reduce_(0, batch, x.abs().amax(1), "amax") / 127
    scale = scale.clamp_min(torch.finfo(x.dtype).tiny)
    rows = torch.round(x / (scale if batch is None else scale[batch, None])).to(torch.int8)
    return torch.cat([rows, rows.new_zeros(1, x.shape[1])]), scale


class GatherConv(nn.Module):
    """A sparse convolution computed as one gather and one product (see the module's docstring).

    `quantize()` switches an inference copy to int8 gathers and products: the features are
    rounded to 8 bits with one scale per scan, the weight with one scale per output channel, and
    the int32 products scaled back. The gathered matrix is a quarter of the bytes and the CPU's
    int8 matrix units multiply several times faster than float32 (benchmarks/RESULTS.md); the
    shipped model's probabilities move by at most 0.006 on the test families."""

    weight: nn.Parameter
    bias: nn.Parameter | None

    def __init__(self) -> None:
        super().__init__()
        self.int8_weight: torch.Tensor | None = None
        self.int8_scale: torch.Tensor | None = None

    @torch.no_grad()
    def quantize(self) -> None:
        w = self.weight.reshape(-1, self.weight.shape[-1])
        self.int8_scale = w.abs().amax(0).clamp_min(torch.finfo(w.dtype).tiny) / 127
        self.int8_weight = torch.round(w / self.int8_scale).to(torch.int8)

    def product(self, x: torch.Tensor, table: torch.Tensor, rows_in: Level, rows_out: Level) -> torch.Tensor:
        """sum_k x[table[:, k]] @ weight[k] (+ bias): one output row per row of `table`, whose
        entries index `x` (len(x): no neighbour); the levels say which scan each row is of."""
        if self.int8_weight is None:
            return _gather_matmul(x, table, self.weight, self.bias)
        batch_in, batch_out = rows_in.batch_index(), rows_out.batch_index()
        rows, scale = _int8_rows(x, batch_in)
        if rows.shape[1] == 16:  # a 16-byte row as one complex128: index_select copies elements, not rows
            rows = rows.view(torch.complex128).reshape(-1)
        gathered = rows.index_select(0, table.reshape(-1)).view(torch.int8).reshape(len(table), -1)
        products = torch._int_mm(gathered, self.int8_weight)  # int32, scaled to float below
        scale = self.int8_scale * (scale if batch_out is None else scale[batch_out, None])
        return products * scale if self.bias is None else torch.addcmul(self.bias, products, scale)


class SubmanifoldConv(GatherConv):
    """3x3x3 convolution evaluated only at the active sites (output sites = input sites)."""

    def __init__(self, c_in: int, c_out: int, bias: bool = False):
        super().__init__()
        self.weight = _init_weight(27, c_in, c_out)  # weight[k] for offset OFFSETS_3[k]
        self.bias = nn.Parameter(torch.zeros(c_out)) if bias else None

    def forward(self, x: torch.Tensor, level: Level) -> torch.Tensor:
        return self.product(x, level.neighbours(), level, level)


class DownConv(GatherConv):
    """2x2x2 convolution with stride 2: each coarse site sums its up to eight children."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.weight = _init_weight(8, c_in, c_out)  # weight[k] for child offset OFFSETS_2[k]
        self.register_parameter("bias", None)  # none in training; see classifier.fold_batch_norms

    def forward(self, x: torch.Tensor, level: Level) -> tuple[torch.Tensor, Level]:
        coarse, children, _, _ = level.coarser()
        return self.product(x, children, level, coarse), coarse


class UpConv(nn.Module):
    """Transposed 2x2x2 stride-2 convolution onto the finer level's sites (those of the encoder),
    so the decoder never invents sites that the scan did not have."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.weight = _init_weight(8, c_in, c_out)
        self.register_parameter("bias", None)  # none in training; see classifier.fold_batch_norms
        self.c_out = c_out

    def forward(self, x: torch.Tensor, fine: Level) -> torch.Tensor:
        _, _, parent, slot = fine.coarser()
        weight = self.weight.permute(1, 0, 2).reshape(x.shape[1], -1)  # (C_in, 8 C_out): every slot at once
        every_slot = x @ weight if self.bias is None else torch.addmm(self.bias.repeat(8), x, weight)
        return every_slot.reshape(-1, self.c_out).index_select(0, parent * 8 + slot)


def voxelize(points: list[torch.Tensor], voxel: float) -> tuple[Level, torch.Tensor, torch.Tensor]:
    """Quantize a batch of point sets: the finest level, each voxel's mean point (float, (N, 3)),
    and the voxel row of every input point (for per-point features)."""
    p = torch.cat(points)
    batch = torch.repeat_interleave(torch.arange(len(points)), torch.tensor([len(q) for q in points]))
    q = torch.cat([batch[:, None], torch.floor(p / voxel).to(torch.int64)], dim=1)
    unique, inverse, keys = unique_coords(q)  # the batch index leads the key: scans stay in order
    count = torch.zeros(len(unique)).index_add_(0, inverse, torch.ones(len(p)))
    mean = torch.zeros(len(unique), 3).index_add_(0, inverse, p) / count[:, None]
    return Level(unique, 1, keys), mean, inverse


def global_max_pool(x: torch.Tensor, level: Level, batch_size: int) -> torch.Tensor:
    """(B, C) maximum over the sites of each scan of the batch."""
    if batch_size == 1 and len(x):  # one scan, as in online use: a plain reduction, several times faster
        return x.amax(0, keepdim=True)
    out = x.new_full((batch_size, x.shape[1]), -torch.inf)
    index = level.coords[:, 0:1].expand_as(x)
    return out.scatter_reduce(0, index, x, reduce="amax", include_self=True)
