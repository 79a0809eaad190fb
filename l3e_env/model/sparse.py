"""Sparse 3D convolution in pure PyTorch: kernel maps by coordinate keys, gather, matmul.

Written by hand because MinkowskiEngine does not build on current torch, spconv's CPU build
cannot back-propagate and torchsparse is not on the package registry. The scheme is
"gather-GEMM": for every output site a table holds the row of the input feature at each
kernel offset (or a zero row when that neighbour is empty); the features are gathered into
one (N, K * C_in) matrix and multiplied once by the (K * C_in, C_out) weight. Autograd turns
the gather into a scatter-add in the backward pass, so gradients need no extra code.

Coordinates are int64 (N, 4) rows (batch, x, y, z) in voxel units of the current level. The
levels and their kernel maps are index bookkeeping on a few thousand sites, where nothing needs a
gradient: loops compiled with numba, one site at a time, because numpy's and torch's per-operation
overhead on arrays this small costs several times the work (docs/log.md); the sorts stay
in numpy, whose sort is several times faster than numba's. On a GPU the same bookkeeping runs as
whole-array torch operations (sorts, searchsorted, scatters: the `_torch` functions below), where one
site at a time would be the slow way; both give the same tables. voxelize sorts the sites once, by Morton
key (the batch, then the bits of x, y and z interleaved), so that the eight children of every
coarser site are consecutive rows and each coarser level follows from the finer one without
another sort.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import torch
from numba import njit
from torch import nn

_BITS = 16  # per spatial axis: +-32768 voxels, 6.5 km at 0.2 m
_SHIFT = 1 << (_BITS - 1)
OFFSETS_3 = torch.tensor(list(itertools.product((-1, 0, 1), repeat=3)), dtype=torch.int64)  # (27, 3)
OFFSETS_2 = torch.tensor(list(itertools.product((0, 1), repeat=3)), dtype=torch.int64)  # (8, 3)

# the neighbour at OFFSETS_3[k] of a site has the site's search key plus _NEIGHBOUR_DELTAS[k]
_NEIGHBOUR_DELTAS = ((OFFSETS_3[:, 0] << 2 * _BITS) + (OFFSETS_3[:, 1] << _BITS) + OFFSETS_3[:, 2]).numpy()
# A site in child slot s (OFFSETS_2[s]) of its parent has its neighbour at OFFSETS_3[k] in the
# parent's neighbour _PARENT_OFFSET[s, k] (an OFFSETS_3 row), in child slot _CHILD_SLOT[s, k].
_FINE = (OFFSETS_2[:, None, :] + OFFSETS_3[None, :, :]).numpy()  # (8, 27, 3), each in -1..2
_PARENT_OFFSET = (np.floor_divide(_FINE, 2) + 1) @ np.array([9, 3, 1])
_CHILD_SLOT = np.remainder(_FINE, 2) @ np.array([4, 2, 1])
# a byte's bits spread to every third bit, for Morton keys
_SPREAD = np.array([sum(((v >> b) & 1) << 3 * b for b in range(8)) for v in range(256)], dtype=np.int64)


_TOO_FAR = f"voxel coordinates beyond +-{_SHIFT}; the scan extends too far for this voxel size"


def morton_keys(coords: np.ndarray) -> np.ndarray:
    """One int64 key per (batch, x, y, z) row: the batch above the interleaved bits of x, y, z, so
    that sorted keys keep the scans in order and a site's key shifted right by 3 is its parent's."""
    return _interleaved(np.ascontiguousarray(coords, dtype=np.int64))


@njit(cache=True, nogil=True)
def _shifted(v: int) -> int:
    """A voxel coordinate moved into 0 .. 2^16 - 1, or ValueError."""
    v += _SHIFT
    if v < 0 or v >= 1 << _BITS:
        raise ValueError(_TOO_FAR)
    return v


@njit(cache=True, nogil=True)
def _interleaved(coords: np.ndarray) -> np.ndarray:
    """morton_keys of (N, 4) int64 rows."""
    keys = np.empty(len(coords), dtype=np.int64)
    for i in range(len(coords)):
        key = coords[i, 0] << 3 * _BITS
        for a in range(3):
            v = _shifted(coords[i, a + 1])
            key |= (_SPREAD[v & 255] | (_SPREAD[v >> 8] << 24)) << (2 - a)
        keys[i] = key
    return keys


@njit(cache=True, nogil=True)
def _linear_keys(coords: np.ndarray) -> np.ndarray:
    """Keys linear in x, y and z: a neighbour's key is the site's plus a constant (_NEIGHBOUR_DELTAS)."""
    keys = np.empty(len(coords), dtype=np.int64)
    for i in range(len(coords)):
        keys[i] = (
            (coords[i, 0] << 3 * _BITS)
            | (_shifted(coords[i, 1]) << 2 * _BITS)
            | (_shifted(coords[i, 2]) << _BITS)
            | _shifted(coords[i, 3])
        )
    return keys


@njit(cache=True, nogil=True)
def _cells(points: np.ndarray, voxel: np.float32, scan: np.ndarray) -> np.ndarray:
    """(N, 4) rows (scan, floor(p / voxel)), the division in float32 as numpy does it for float32 points."""
    cells = np.empty((len(points), 4), dtype=np.int64)
    for i in range(len(points)):
        cells[i, 0] = scan[i]
        for a in range(3):
            cells[i, a + 1] = math.floor(points[i, a] / voxel)
    return cells


@njit(cache=True, nogil=True)
def _runs(sorted_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first position of each run of equal keys, and the run of every position."""
    run = np.empty(len(sorted_keys), dtype=np.int64)
    first = np.empty(len(sorted_keys), dtype=np.int64)
    count = 0
    for i in range(len(sorted_keys)):
        if i == 0 or sorted_keys[i] != sorted_keys[i - 1]:
            first[count] = i
            count += 1
        run[i] = count - 1
    return first[:count], run


def _searched_neighbours(coords: np.ndarray) -> np.ndarray:
    """(N, 27) rows of the 3x3x3 neighbours of each site (N where empty), from keys that are linear
    in x, y, z (a neighbour's key is the site's plus a constant, see _merged_table)."""
    keys = _linear_keys(coords)
    return _merged_table(keys, np.argsort(keys))  # numpy's sort: several times faster than numba's


@njit(cache=True, nogil=True)
def _merged_table(keys: np.ndarray, order: np.ndarray) -> np.ndarray:
    """The sites' keys sorted once; the keys wanted at one offset are the sorted keys plus a
    constant, sorted as well, so one merge of the two finds them all: O(27 N) after the sort."""
    n = len(keys)
    sorted_keys = keys[order]
    table = np.empty((n, 27), dtype=np.int64)
    for k in range(27):
        j = 0
        for i in range(n):
            wanted = sorted_keys[i] + _NEIGHBOUR_DELTAS[k]
            while j < n and sorted_keys[j] < wanted:
                j += 1
            table[order[i], k] = order[j] if j < n and sorted_keys[j] == wanted else n
    return table


@njit(cache=True, nogil=True)
def _child_table(coarse_table: np.ndarray, children: np.ndarray, parent: np.ndarray, slot: np.ndarray) -> np.ndarray:
    """(N, 27) neighbour rows read off the coarser level's table (see Level.neighbours)."""
    n, m = len(parent), len(coarse_table)
    table = np.empty((n, 27), dtype=np.int64)
    for v in range(n):
        p, s = parent[v], slot[v]
        for k in range(27):
            q = coarse_table[p, _PARENT_OFFSET[s, k]]
            table[v, k] = children[q, _CHILD_SLOT[s, k]] if q < m else n
    return table


@njit(cache=True, nogil=True)
def _parents(keys: np.ndarray, coords: np.ndarray) -> tuple[np.ndarray, ...]:
    """For sites in ascending Morton order: the coarser level's keys and coords, its (M, 8) children
    table (N where none), and each site's parent row and child slot."""
    n = len(keys)
    first, parent = _runs(keys >> 3)
    m = len(first)
    coarse_keys, coarse = np.empty(m, dtype=np.int64), np.empty((m, 4), dtype=np.int64)
    children = np.full((m, 8), n, dtype=np.int64)
    slot = keys & 7  # the lowest bits of x, y and z: 4 dx + 2 dy + dz
    for j in range(m):
        i = first[j]
        coarse_keys[j] = keys[i] >> 3
        coarse[j, 0] = coords[i, 0]
        for a in range(1, 4):
            coarse[j, a] = coords[i, a] >> 1  # floor(x / 2)
    for i in range(n):
        children[parent[i], slot[i]] = i
    return coarse_keys, coarse, children, parent, slot


def _by_torch(t: torch.Tensor) -> bool:
    """Whether the index bookkeeping of tensors like `t` runs as torch operations (on a GPU) rather
    than the compiled loops (on the CPU)."""
    return t.device.type != "cpu"


# the same bookkeeping on a torch device (see the module's text): tensors in, tensors out
_SPREAD_T = torch.from_numpy(_SPREAD)
_DELTAS_T = torch.from_numpy(_NEIGHBOUR_DELTAS)
_PARENT_OFFSET_T = torch.from_numpy(_PARENT_OFFSET)
_CHILD_SLOT_T = torch.from_numpy(_CHILD_SLOT)


def _shifted_torch(xyz: torch.Tensor) -> torch.Tensor:
    """Voxel coordinates (N, 3) moved into 0 .. 2^16 - 1, or ValueError (as _shifted)."""
    v = xyz + _SHIFT
    if len(v) and bool(((v < 0) | (v >= 1 << _BITS)).any()):
        raise ValueError(_TOO_FAR)
    return v


def morton_keys_torch(coords: torch.Tensor) -> torch.Tensor:
    """morton_keys of (N, 4) int64 rows on any device."""
    v = _shifted_torch(coords[:, 1:])
    spread = _SPREAD_T.to(coords.device)
    s = spread[v & 255] | (spread[v >> 8] << 24)
    return (coords[:, 0] << 3 * _BITS) | (s[:, 0] << 2) | (s[:, 1] << 1) | s[:, 2]


def _searched_neighbours_torch(coords: torch.Tensor) -> torch.Tensor:
    """_searched_neighbours on any device: every wanted key found by a binary search of the sorted keys."""
    n = len(coords)
    if n == 0:
        return coords.new_zeros((0, 27))
    v = _shifted_torch(coords[:, 1:])
    keys = (coords[:, 0] << 3 * _BITS) | (v[:, 0] << 2 * _BITS) | (v[:, 1] << _BITS) | v[:, 2]
    sorted_keys, order = torch.sort(keys)
    wanted = keys[:, None] + _DELTAS_T.to(keys.device)[None, :]
    at = torch.searchsorted(sorted_keys, wanted).clamp_max(n - 1)
    return torch.where(sorted_keys[at] == wanted, order[at], n)


def _child_table_torch(
    coarse_table: torch.Tensor, children: torch.Tensor, parent: torch.Tensor, slot: torch.Tensor
) -> torch.Tensor:
    """_child_table on any device."""
    n, m = len(parent), len(coarse_table)
    if n == 0 or m == 0:
        return parent.new_full((n, 27), n)
    q = coarse_table[parent[:, None], _PARENT_OFFSET_T.to(slot.device)[slot]]
    child = children[q.clamp_max(m - 1), _CHILD_SLOT_T.to(slot.device)[slot]]
    return torch.where(q < m, child, n)


def _parents_torch(keys: torch.Tensor, coords: torch.Tensor, in_order: bool) -> tuple[torch.Tensor, ...]:
    """_parents on any device; `in_order`: the keys ascend (each parent's children are consecutive)."""
    n = len(keys)
    if in_order:
        coarse_keys, parent = torch.unique_consecutive(keys >> 3, return_inverse=True)
    else:
        coarse_keys, parent = torch.unique(keys >> 3, return_inverse=True)
    m = len(coarse_keys)
    rows = torch.arange(n, device=keys.device)
    first = torch.full((m,), n, device=keys.device, dtype=torch.int64).scatter_reduce_(0, parent, rows, "amin")
    coarse = coords[first].clone()
    coarse[:, 1:] >>= 1  # floor(x / 2)
    slot = keys & 7  # the lowest bits of x, y and z: 4 dx + 2 dy + dz
    children = torch.full((m, 8), n, device=keys.device, dtype=torch.int64)
    children[parent, slot] = rows
    return coarse_keys, coarse, children, parent, slot


def _voxels_torch(points: torch.Tensor, lengths: list[int], voxel: float) -> tuple[torch.Tensor, ...]:
    """voxelize's cells, mean points, voxel of every point and keys, on the points' device."""
    device = points.device
    batch = torch.repeat_interleave(torch.arange(len(lengths), device=device), torch.tensor(lengths, device=device))
    # float32 division, as numpy (and _cells) divide float32 points
    cells = torch.floor(points / torch.tensor(voxel, dtype=torch.float32, device=device)).to(torch.int64)
    cells = torch.cat([batch[:, None], cells], dim=1)
    keys, inverse, counts = torch.unique(morton_keys_torch(cells), return_inverse=True, return_counts=True)
    summed = torch.zeros((len(keys), 3), dtype=torch.float64, device=device).index_add_(0, inverse, points.double())
    coords = torch.empty((len(keys), 4), dtype=torch.int64, device=device)
    coords[inverse] = cells  # every point of a voxel has its cell
    return coords, (summed / counts[:, None]).float(), inverse, keys


@dataclass
class Level:
    """The active sites of one resolution level and the kernel maps built on them (cached,
    because every convolution at a level shares them)."""

    coords: torch.Tensor  # (N, 4) int64
    stride: int  # in units of the finest voxel
    # the rows' Morton keys when the rows come in ascending Morton order (as from voxelize and coarser);
    # a tensor on the coords' device where that is not the CPU
    morton: np.ndarray | torch.Tensor | None = field(default=None, repr=False)
    _neighbours: torch.Tensor | None = field(default=None, repr=False)
    _one_scan: bool | None = field(default=None, repr=False)
    _coarser: tuple[Level, torch.Tensor, torch.Tensor, torch.Tensor] | None = field(default=None, repr=False)

    def batch_index(self) -> torch.Tensor | None:
        """The scan of each site, or None when all are of one scan (rows are in scan order)."""
        if self._one_scan is None:
            self._one_scan = len(self.coords) == 0 or int(self.coords[-1, 0]) == 0
        return None if self._one_scan else self.coords[:, 0]

    def neighbours(self) -> torch.Tensor:
        """(N, 27) rows of the 3x3x3 neighbours of each site (N where empty). Once the coarser level
        exists (ResUNet.encode builds them all first), the table is read off that level's own:
        every neighbour of a site is a child of a neighbour of the site's parent, so two table
        lookups per neighbour replace a search of the keys (exact, and several times faster); the
        coarsest level's table comes from _searched_neighbours."""
        if self._neighbours is None and _by_torch(self.coords):
            if self._coarser is not None:
                coarse, children, parent, slot = self._coarser
                self._neighbours = _child_table_torch(coarse.neighbours(), children, parent, slot)
            else:
                self._neighbours = _searched_neighbours_torch(self.coords)
        if self._neighbours is None:
            if self._coarser is not None:
                coarse, children, parent, slot = self._coarser
                table = _child_table(coarse.neighbours().numpy(), children.numpy(), parent.numpy(), slot.numpy())
            else:
                table = _searched_neighbours(self.coords.numpy())
            self._neighbours = torch.from_numpy(table)
        return self._neighbours

    def coarser(self) -> tuple[Level, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The level at twice the voxel size (in Morton order), plus (children table (M, 8) of this
        level's rows (N where none), parent row of each site here (N,), child slot of each site here
        (N,), an OFFSETS_2 row)."""
        if self._coarser is None and _by_torch(self.coords):
            keys = self.morton if isinstance(self.morton, torch.Tensor) else morton_keys_torch(self.coords)
            coarse_keys, coarse, children, parent, slot = _parents_torch(keys, self.coords, self.morton is not None)
            self._coarser = (Level(coarse, self.stride * 2, coarse_keys), children, parent, slot)
        if self._coarser is None:
            tables = _coarser_tables(self.coords.numpy(), self.morton)
            self._coarser = (
                Level(torch.from_numpy(tables[1]), self.stride * 2, tables[0]),
                torch.from_numpy(tables[2]),
                torch.from_numpy(tables[3]),
                torch.from_numpy(tables[4]),
            )
        return self._coarser


def _coarser_tables(
    coords: np.ndarray, morton: np.ndarray | torch.Tensor | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Level.coarser's tables on the CPU: the coarse keys, coarse coordinates, children table,
    parent row and child slot of each site."""
    if isinstance(morton, np.ndarray):  # each parent's children are consecutive rows: no sort
        coarse_keys, coarse, children, parent, slot = _parents(morton, coords)
        return coarse_keys, coarse, children, parent, slot
    keys = morton_keys(coords)
    coarse_keys, first, parent = np.unique(keys >> 3, return_index=True, return_inverse=True)
    coarse = np.take(coords, first, axis=0)
    coarse[:, 1:] >>= 1  # floor(x / 2)
    slot = keys & 7  # the lowest bits of x, y and z: 4 dx + 2 dy + dz
    children = np.full((len(first), 8), len(coords), dtype=np.int64)
    children[parent, slot] = np.arange(len(coords))
    return coarse_keys, coarse, children, parent, slot


def _gather_matmul(
    x: torch.Tensor, table: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None
) -> torch.Tensor:
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


_TINY = float(np.finfo(np.float32).tiny)


def _int8_rows(x: torch.Tensor, batch: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | float]:
    """x rounded to int8 with one scale per scan (so that a scan's answer does not depend on the
    other scans of its batch), a zero row appended for the empty neighbour; and the scales, one
    per scan ((B,); a float for one scan, which saves the tensor operations on a scalar)."""
    out = torch.empty(len(x) + 1, x.shape[1], dtype=torch.int8)
    out[-1] = 0
    if batch is None:
        rows, scale = _scan_rows(x.detach().contiguous().numpy())
        if scale > 0:
            return torch.from_numpy(rows), scale
        scale = max(float(x.abs().max()), 127 * _TINY) / 127  # a negative entry: not after a ReLU
        out[:-1] = torch.round(x * (1 / scale))
        return out, scale
    scales = x.new_zeros(int(batch[-1]) + 1).scatter_reduce_(0, batch, x.abs().amax(1), "amax") / 127
    scales = scales.clamp_min(_TINY)
    out[:-1] = torch.round(x / scales[batch, None])
    return out, scales


@njit(cache=True, nogil=True)
def _scan_rows(x: np.ndarray) -> tuple[np.ndarray, float]:
    """One scan's features (N, C) rounded to int8 with one scale, the empty row last, and the
    scale; scale -1 when x has a negative entry (the rounding below holds for x >= 0 only)."""
    n, c = x.shape
    high, low = np.zeros(c, dtype=x.dtype), np.zeros(c, dtype=x.dtype)  # per column, so that the loop vectorises
    for i in range(n):
        for j in range(c):
            high[j] = max(high[j], x[i, j])
            low[j] = min(low[j], x[i, j])
    if _column_extreme(low, False) < 0:
        return np.zeros((0, c), dtype=np.int8), -1.0
    return _rounded_rows(x, _column_extreme(high, True))


@njit(cache=True, nogil=True)
def _column_extreme(values: np.ndarray, largest: bool) -> float:
    """The largest (or smallest) of values and 0, in their own dtype: a loop, which numba compiles far
    faster than an array's own max() and min()."""
    found = values.dtype.type(0)
    for v in values:
        found = max(found, v) if largest else min(found, v)
    return found


@njit(cache=True, nogil=True)
def _rounded_rows(y: np.ndarray, high: float) -> tuple[np.ndarray, float]:
    """y >= 0 (N, C) over the scale high / 127, rounded to int8 (y / scale + 0.5 truncated by the
    conversion: rounding half up), with a zero row appended; and the scale."""
    n, c = y.shape
    scale = max(high, 127 * _TINY) / 127
    inverse = np.float32(1 / scale)
    rows = np.empty((n + 1, c), dtype=np.int8)
    for i in range(n):
        for j in range(c):
            rows[i, j] = np.int8(y[i, j] * inverse + np.float32(0.5))
    rows[n] = 0
    return rows, scale


@njit(cache=True, nogil=True)
def _relu_rows(
    products: np.ndarray, weight_scale: np.ndarray, scale: float, bias: np.ndarray
) -> tuple[np.ndarray, float]:
    """relu(products * weight_scale * scale + bias) of one scan as int8 rows (see _rounded_rows)."""
    n, c = products.shape
    factor = weight_scale * np.float32(scale)
    y, high = np.empty((n, c), dtype=np.float32), np.zeros(c, dtype=np.float32)
    for i in range(n):
        for j in range(c):
            y[i, j] = max(np.float32(products[i, j]) * factor[j] + bias[j], np.float32(0))
            high[j] = max(high[j], y[i, j])
    return _rounded_rows(y, _column_extreme(high, True))


@njit(cache=True, nogil=True)
def _residual_relu(
    products: np.ndarray, weight_scale: np.ndarray, scale: float, bias: np.ndarray, residual: np.ndarray
) -> np.ndarray:
    """relu(products * weight_scale * scale + bias + residual), float32."""
    n, c = products.shape
    factor = weight_scale * np.float32(scale)
    out = np.empty((n, c), dtype=np.float32)
    for i in range(n):
        for j in range(c):
            out[i, j] = max(np.float32(products[i, j]) * factor[j] + bias[j] + residual[i, j], np.float32(0))
    return out


class GatherConv(nn.Module):
    """A sparse convolution computed as one gather and one product (see the module's docstring).

    `quantize()` switches an inference copy to int8 gathers and products: the features are
    rounded to 8 bits with one scale per scan, the weight with one scale per output channel, and
    the int32 products scaled back. The gathered matrix is a quarter of the bytes and the CPU's
    int8 matrix units multiply several times faster than float32 (docs/log.md); the
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

    def int8_products(self, rows: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        """(len(table), C_out) int32: the int8 rows (the empty row last) gathered by `table` and
        multiplied by the int8 weight."""
        if rows.shape[1] == 16:  # a 16-byte row as one complex128: index_select copies elements, not rows
            rows = rows.view(torch.complex128).reshape(-1)
        gathered = rows.index_select(0, table.reshape(-1)).view(torch.int8).reshape(len(table), -1)
        if self.int8_weight is None:
            raise RuntimeError("int8_products needs quantize() first")
        return torch._int_mm(gathered, self.int8_weight)

    def product(self, x: torch.Tensor, table: torch.Tensor, rows_in: Level, rows_out: Level) -> torch.Tensor:
        """sum_k x[table[:, k]] @ weight[k] (+ bias): one output row per row of `table`, whose
        entries index `x` (len(x): no neighbour); the levels say which scan each row is of."""
        if self.int8_weight is None or self.int8_scale is None:
            return _gather_matmul(x, table, self.weight, self.bias)
        batch_in, batch_out = rows_in.batch_index(), rows_out.batch_index()
        rows, scale = _int8_rows(x, batch_in)
        products = self.int8_products(rows, table)  # int32, scaled to float below
        if not isinstance(scale, torch.Tensor):  # one scan: its scale as addcmul's value saves a product
            if self.bias is None:
                return products * (self.int8_scale * scale)
            return torch.addcmul(self.bias, products, self.int8_scale, value=scale)
        scales = self.int8_scale * scale[batch_out, None]
        return products * scales if self.bias is None else torch.addcmul(self.bias, products, scales)


def int8_residual_block(conv1: GatherConv, conv2: GatherConv, x: torch.Tensor, level: Level) -> torch.Tensor | None:
    """relu(conv2(relu(conv1(x))) + x) of one scan, for int8 submanifold convolutions whose batch
    norms are folded into their biases: three compiled passes and two gather-products, where the
    modules take some twenty torch operations, and the middle features never exist in float32.
    None where it does not apply: a batch, convolutions not quantised or without biases, or a
    negative entry in x."""
    if level.batch_index() is not None or any(c.int8_weight is None or c.bias is None for c in (conv1, conv2)):
        return None
    assert conv1.int8_scale is not None and conv2.int8_scale is not None  # quantised, as checked above
    assert conv1.bias is not None and conv2.bias is not None
    features = x.detach().contiguous().numpy()
    rows, scale = _scan_rows(features)
    if scale < 0:
        return None
    table = level.neighbours()
    products = conv1.int8_products(torch.from_numpy(rows), table).numpy()
    rows, scale = _relu_rows(products, conv1.int8_scale.numpy(), scale, conv1.bias.detach().numpy())
    products = conv2.int8_products(torch.from_numpy(rows), table).numpy()
    return torch.from_numpy(
        _residual_relu(products, conv2.int8_scale.numpy(), scale, conv2.bias.detach().numpy(), features)
    )


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
        out = (x @ weight).reshape(-1, self.c_out).index_select(0, parent * 8 + slot)
        return (
            out if self.bias is None else out.add_(cast(torch.Tensor, self.bias))
        )  # after the gather: bias.repeat(8) costs more


def voxelize(points: list[torch.Tensor], voxel: float) -> tuple[Level, torch.Tensor, torch.Tensor]:
    """Quantize a batch of point sets: the finest level (rows in Morton order, scans in order), each
    voxel's mean point (float, (N, 3)), and the voxel row of every input point (for per-point
    features). The bookkeeping runs on the points' device."""
    if points and _by_torch(points[0]):
        coords, mean, inverse, keys = _voxels_torch(torch.cat(points), [len(q) for q in points], voxel)
        return Level(coords, 1, keys), mean, inverse
    p = torch.cat(points).numpy()
    batch = np.repeat(np.arange(len(points)), [len(q) for q in points])
    cells = _cells(p, np.float32(voxel), batch)
    cell_keys = _interleaved(cells)
    found = _voxels(cell_keys, np.argsort(cell_keys), cells, p)  # numpy's sort: faster than numba's
    level = Level(torch.from_numpy(found[0]), 1, found[3])
    return level, torch.from_numpy(found[1]), torch.from_numpy(found[2])


@njit(cache=True, nogil=True)
def _voxels(keys: np.ndarray, order: np.ndarray, cells: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, ...]:
    """The occupied voxels in key order (`order` sorts the keys): their cells, mean points
    (float32), the voxel of every point, and their keys. Loops, not arrays indexed by arrays, which
    numba compiles far more slowly."""
    n = len(keys)
    sorted_keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        sorted_keys[i] = keys[order[i]]
    first, run = _runs(sorted_keys)
    m = len(first)
    inverse = np.empty(n, dtype=np.int64)
    for i in range(n):
        inverse[order[i]] = run[i]
    count, summed = np.zeros(m), np.zeros((m, 3))
    for i in range(n):  # in the points' order, as np.bincount sums
        v = inverse[i]
        count[v] += 1
        for a in range(3):
            summed[v, a] += points[i, a]
    mean = np.empty((m, 3), dtype=np.float32)
    head_cells = np.empty((m, cells.shape[1]), dtype=np.int64)
    head_keys = np.empty(m, dtype=np.int64)
    for v in range(m):
        for a in range(3):
            mean[v, a] = summed[v, a] / count[v]
        head = order[first[v]]
        for a in range(cells.shape[1]):
            head_cells[v, a] = cells[head, a]
        head_keys[v] = sorted_keys[first[v]]
    return head_cells, mean, inverse, head_keys


def global_max_pool(x: torch.Tensor, level: Level, batch_size: int) -> torch.Tensor:
    """(B, C) maximum over the sites of each scan of the batch."""
    if batch_size == 1 and len(x):  # one scan, as in online use: a plain reduction, several times faster
        return x.amax(0, keepdim=True)
    out = x.new_full((batch_size, x.shape[1]), -torch.inf)
    index = level.coords[:, 0:1].expand_as(x)
    return out.scatter_reduce(0, index, x, reduce="amax", include_self=True)
