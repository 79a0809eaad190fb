"""The localizability classifier: one scan in, six probabilities of non-localizability out.

Two backbones share the input sampling and the head: a sparse-convolutional ResUNet after
FCGF (the L3E model) and a PointNet (the paper's ablation baseline). Checkpoints carry the
architecture, its config, the per-axis thresholds and the sensor and registration settings
the labels were made with, and are refused when they do not match this code.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from l3e_env.config import from_dict, plain, with_defaults
from l3e_env.config.labelling import LABEL_PROTOCOL, RegistrationConfig, protocol_name
from l3e_env.core.files import write_atomic
from l3e_env.core.points import out_of_reach
from l3e_env.core.transforms import level_rotation_of

from .constraints import FEATURES, SURFACE_FEATURES, AxisStacker, scan_features, surface_rows
from .information import InformationPool
from .sparse import (
    DownConv,
    GatherConv,
    Level,
    SubmanifoldConv,
    UpConv,
    global_max_pool,
    int8_products_work,
    int8_residual_block,
    voxelize,
)

CHECKPOINT_FORMAT = "l3e-classifier"
CHECKPOINT_VERSION = 1
MIN_POINTS = 50
DEFAULT_CHECKPOINT = Path(__file__).parent / "shipped" / "resunet_vlp16.pt"
# Mirroring a scan in x or y, or swapping x and y, gives a scan whose labels are the same up to the
# order of the axes (a degenerate direction stays degenerate whatever its sign): swapping x and y
# swaps the x/y and the roll/pitch labels. Training draws from these views; symmetric inference
# averages over all eight.
SWAP_LABELS = np.array([1, 0, 2, 4, 3, 5])
SYMMETRIES: list[tuple[float, float, bool]] = [
    (sx, sy, swap) for sx in (1.0, -1.0) for sy in (1.0, -1.0) for swap in (False, True)
]


class CheckpointError(RuntimeError):
    """A checkpoint that is missing, unreadable, or of another architecture or version."""


class ScanError(ValueError):
    """A scan the classifier cannot judge (empty, too few points, NaN)."""


@dataclass
class ModelConfig:
    architecture: str = "resunet"  # or "pointnet"
    points: int = 4000  # sampled from the scan (all of them if it has fewer)
    # "points": drawn from the scan's points, so the dense ground next to the sensor dominates;
    # "voxels": the scan is first thinned to one random point per voxel, so every voxel counts once
    # whatever its range, as in the voxel-thinned registration that makes the labels
    sampling: str = "points"
    voxel: float = 0.2  # m, sparse quantization
    # ResUNet widths at 0.2, 0.4, 0.8 and 1.6 m. FCGF's 32-64-128-256 costs 47-70 ms a scan here;
    # half of it at the fine levels and a quarter at the coarsest takes about 0.3 of that on two
    # cores (benchmarks/bench_classifier.py), and the labels depend on coarse geometry
    channels: tuple[int, ...] = (16, 32, 48, 64)
    pointnet_channels: tuple[int, ...] = (64, 64, 128, 256)
    feature: int = 32  # global feature after max pooling
    head: tuple[int, ...] = (64, 64, 32, 16)  # hidden widths: five linear layers with the output
    dropout: float = 0.1  # 0.3 on the 16-wide last hidden layer slowed learning markedly
    coordinate_scale: float = 10.0  # m; point coordinates enter as features divided by this
    # the world's up direction in the sensor frame (what an IMU gives a legged robot) enters the
    # head beside the pooled feature: on uneven ground the scan alone does not show the tilt
    gravity: bool = False
    # each scan is turned into its level frame (z along gravity, x the sensor's heading levelled:
    # core.transforms.level_rotation) before the network, which answers in that frame, as the labels
    # of protocol 3 are written; the scan's pose (its tilt, from an IMU) then comes with every scan
    level: bool = True
    # a per-axis logistic layer over the network's logit and the scan's point-to-plane Hessian
    # (l3e_env.model.constraints), fitted after the network on its training scenes (l3e fit-constraints)
    constraints: bool = False
    # the ResUNet levels whose Hessian features the layer reads (0: 0.2 m voxels, 1: 0.4 m)
    constraint_levels: tuple[int, ...] = (0,)
    # each voxel also enters the ResUNet with its point-to-plane row [n, p x n] (normal facing the
    # sensor) and whether its neighbourhood is planar: what each voxel constrains, in any scene
    surface_rows: bool = False
    # "canonical": every scan is first turned into its own canonical view among the eight mirror and
    # x/y-swap views (canonical_view), and the answer turned back: a scan and its mirror images or
    # its turns by 90 and 180 deg about z get the same answer on their own axes, by construction.
    # "sensor": the scan as the sensor gives it
    frame: str = "sensor"
    # "max": the decoder's features max-pooled over the scan; "information": beside them, the features
    # of `information_heads` point-to-plane information matrices whose voxels the network weighs
    # (l3e_env.model.information): a sum over the scan, as ICP's Hessian, instead of a maximum
    pooling: str = "max"
    information_heads: int = 4


def _bn_relu(c: int) -> nn.Sequential:
    return nn.Sequential(nn.BatchNorm1d(c), nn.ReLU(inplace=True))


class ResBlock(nn.Module):
    """Two submanifold convolutions plus a skip (a linear map when the width changes)."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv1, self.norm1 = SubmanifoldConv(c_in, c_out), _bn_relu(c_out)
        self.conv2, self.norm2 = SubmanifoldConv(c_out, c_out), nn.BatchNorm1d(c_out)
        self.skip = nn.Identity() if c_in == c_out else nn.Linear(c_in, c_out, bias=False)

    def forward(self, x: torch.Tensor, level: Level) -> torch.Tensor:
        if isinstance(self.skip, nn.Identity) and isinstance(self.norm2, nn.Identity):  # norms folded
            fused = int8_residual_block(self.conv1, self.conv2, x, level)
            if fused is not None:
                return fused
        y = self.norm1(self.conv1(x, level))
        y = self.norm2(self.conv2(y, level))
        return torch.relu(y + self.skip(x))


class ResUNet(nn.Module):
    """Encoder: stem, then (stride-2 conv, ResBlock) per level; decoder: (transposed conv onto the
    encoder's sites, concatenation with the encoder's features, ResBlock) back to the finest level;
    a linear map to the feature width and a global max pool."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        c = cfg.channels
        self.voxel, self.scale, self.surface_rows = cfg.voxel, cfg.coordinate_scale, cfg.surface_rows
        self.stem = SubmanifoldConv(7 + (SURFACE_FEATURES if cfg.surface_rows else 0), c[0])
        self.stem_norm = _bn_relu(c[0])
        self.stem_block = ResBlock(c[0], c[0])
        self.down = nn.ModuleList(DownConv(c[i], c[i + 1]) for i in range(len(c) - 1))
        self.down_norm = nn.ModuleList(_bn_relu(c[i + 1]) for i in range(len(c) - 1))
        self.down_block = nn.ModuleList(ResBlock(c[i + 1], c[i + 1]) for i in range(len(c) - 1))
        self.up = nn.ModuleList(UpConv(c[i + 1], c[i]) for i in range(len(c) - 1))
        self.up_norm = nn.ModuleList(_bn_relu(c[i]) for i in range(len(c) - 1))
        # the concatenation is mixed down to the level's width by a linear map before the ResBlock:
        # the same receptive field as a ResBlock on the concatenation for 40 % fewer operations
        self.up_mix = nn.ModuleList(
            nn.Sequential(nn.Linear(2 * c[i], c[i], bias=False), _bn_relu(c[i])) for i in range(len(c) - 1)
        )
        self.up_block = nn.ModuleList(ResBlock(c[i], c[i]) for i in range(len(c) - 1))
        self.out = nn.Linear(c[0], cfg.feature)
        self.information = InformationPool(c[0], cfg.information_heads) if cfg.pooling == "information" else None

    def forward(self, points: list[torch.Tensor]) -> torch.Tensor:
        level, means, _ = voxelize(points, self.voxel)
        return self.encode(level, means, len(points))

    def encode(self, level: Level, means: torch.Tensor, batch_size: int) -> torch.Tensor:
        """The pooled feature (B, C) of scans already quantised (see voxelize)."""
        # where in its voxel the surface passes (sub-voxel shape, e.g. wall roughness) and where
        # the voxel is in the scan (range and direction matter for the constraint it gives)
        inside = means / self.voxel - level.coords[:, 1:] - 0.5
        x = torch.cat([means.new_ones((len(means), 1)), inside, means / self.scale], dim=1)
        rows = surface_rows(level, means) if self.surface_rows or self.information is not None else None
        if self.surface_rows and rows is not None:
            x = torch.cat([x, rows[:, :3], rows[:, 3:6] / self.scale, rows[:, 6:]], dim=1)
        levels = [level]
        for _ in self.down:  # coarser levels first: their kernel maps give the finer ones (Level.neighbours)
            levels.append(levels[-1].coarser()[0])
        x = self.stem_block(self.stem_norm(self.stem(x, level)), level)
        skips = [x]
        for down, norm, block in zip(self.down, self.down_norm, self.down_block):
            x, level = down(x, level)
            x = block(norm(x), level)
            skips.append(x)
        for i in reversed(range(len(self.up))):
            x = self.up_norm[i](self.up[i](x, levels[i]))
            x = self.up_block[i](self.up_mix[i](torch.cat([x, skips[i]], dim=1)), levels[i])
        pooled = global_max_pool(self.out(x), levels[0], batch_size)
        if self.information is None or rows is None:
            return pooled
        return torch.cat([pooled, self.information(x, rows, levels[0].coords[:, 0], batch_size)], dim=1)


class PointNet(nn.Module):
    """Shared per-point MLP and a global max pool (no transform nets, as in the L3E ablation)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        widths = (3, *cfg.pointnet_channels)
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(a, b, bias=False), _bn_relu(b)]
        self.mlp = nn.Sequential(*layers)
        self.out = nn.Linear(widths[-1], cfg.feature)
        self.scale = cfg.coordinate_scale

    def forward(self, points: list[torch.Tensor]) -> torch.Tensor:
        x = self.mlp(torch.cat(points) / self.scale)
        lengths = torch.tensor([len(p) for p in points], device=x.device)
        batch = torch.repeat_interleave(torch.arange(len(points), device=x.device), lengths)
        pooled = x.new_full((len(points), x.shape[1]), -torch.inf)
        pooled = pooled.scatter_reduce(0, batch[:, None].expand_as(x), x, reduce="amax")
        return self.out(pooled)


class LocalizabilityNet(nn.Module):
    """Backbone, then the paper's head: five linear layers with dropout, six logits."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.config = cfg
        if cfg.architecture == "resunet":
            self.backbone: nn.Module = ResUNet(cfg)
        elif cfg.architecture == "pointnet":
            self.backbone = PointNet(cfg)
        else:
            raise ValueError(f"unknown architecture '{cfg.architecture}' (resunet, pointnet)")
        if cfg.sampling not in ("points", "voxels"):
            raise ValueError(f"unknown sampling '{cfg.sampling}' (points, voxels)")
        if cfg.points < 1:
            raise ValueError(f"a model reads at least one point of a scan, not {cfg.points}")
        if cfg.frame not in ("sensor", "canonical"):
            raise ValueError(f"unknown frame '{cfg.frame}' (sensor, canonical)")
        if cfg.pooling not in ("max", "information"):
            raise ValueError(f"unknown pooling '{cfg.pooling}' (max, information)")
        if cfg.pooling == "information" and cfg.architecture != "resunet":
            raise ValueError("information pooling weighs the ResUNet's voxels; a PointNet has none")
        pooled = cfg.feature + (cfg.information_heads * FEATURES if cfg.pooling == "information" else 0)
        widths = (pooled + (3 if cfg.gravity else 0), *cfg.head)
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(a, b), nn.ReLU(inplace=True), nn.Dropout(cfg.dropout)]
        self.head = nn.Sequential(*layers, nn.Linear(widths[-1], 6))
        if cfg.surface_rows and cfg.architecture != "resunet":
            raise ValueError("surface rows are the ResUNet's voxels' own; a PointNet reads bare points")
        if cfg.constraints and cfg.architecture != "resunet":
            raise ValueError("the constraint layer reads the ResUNet's voxels; a PointNet has none")
        levels = cfg.constraint_levels
        if not levels or sorted(set(levels)) != list(levels) or levels[0] < 0 or levels[-1] >= len(cfg.channels):
            raise ValueError(
                f"constraint levels {levels}: distinct, ascending, each a ResUNet level 0-{len(cfg.channels) - 1}"
            )
        self.stacker = AxisStacker(FEATURES * len(levels)) if cfg.constraints else None

    def forward(self, points: list[torch.Tensor], up: torch.Tensor | None = None) -> torch.Tensor:
        """Logits (B, 6) for a batch of point sets in the sensor frame; `up` (B, 3): the world's up
        direction in each sensor frame, for a model with config.gravity (ignored otherwise)."""
        points, up, swapped = self.canonical(points, up)
        logits, features = self.parts(points, up)  # the features only for a model with the layer
        if self.stacker is not None:
            logits = self.stacker(logits, features)
        return logits if swapped is None else torch.where(swapped[:, None], logits[:, SWAP_LABELS], logits)

    def canonical(
        self, points: list[torch.Tensor], up: torch.Tensor | None = None
    ) -> tuple[list[torch.Tensor], torch.Tensor | None, torch.Tensor | None]:
        """For a model with config.frame "canonical": each scan (and up vector) in its canonical view
        (canonical_view), and which scans that view swaps x and y (B,), whose answers then come in the
        order y, x, z, pitch, roll, yaw. Otherwise the input as it is, and None."""
        if self.config.frame != "canonical":
            return points, up, None
        views = [canonical_view(p) for p in points]
        points = [symmetry_view(p, v) for p, v in zip(points, views)]
        if up is not None:
            up = torch.stack([symmetry_view(u[None], v)[0] for u, v in zip(up, views)])
        return points, up, torch.tensor([swap for _, _, swap in views], dtype=torch.bool, device=points[0].device)

    def parts(
        self, points: list[torch.Tensor], up: torch.Tensor | None = None, constraints: bool | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The network's logits (B, 6) and, for a model with config.constraints (or when asked),
        the scans' Hessian features (B, 12 per constraint level) (l3e_env.model.constraints), else None."""
        constraints = self.config.constraints if constraints is None else constraints
        features = None
        if isinstance(self.backbone, ResUNet):
            level, means, _ = voxelize(points, self.config.voxel)
            feature = self.backbone.encode(level, means, len(points))
            if constraints:
                features = scan_features(level, means, len(points), self.config.constraint_levels)
        else:
            feature = self.backbone(points)
        if not self.config.gravity:
            return self.head(feature), features
        if up is None or tuple(up.shape) != (len(points), 3):
            raise ValueError(
                "this classifier was trained with the gravity direction: give the up vector of "
                "each scan's sensor frame, (B, 3)"
            )
        return self.head(torch.cat([feature, up.to(feature)], dim=1)), features


def _norm_sites(backbone: nn.Module) -> list[tuple[nn.Module, nn.Module, str]]:
    """(layer, owner, name) of every batch norm owner.name that follows a convolution or linear layer."""
    sites: list[tuple[nn.Module, nn.Module, str]] = []
    if isinstance(backbone, ResUNet):
        sites.append((backbone.stem, backbone.stem_norm, "0"))
        for block in [backbone.stem_block, *backbone.down_block, *backbone.up_block]:
            sites += [(block.conv1, block.norm1, "0"), (block.conv2, block, "norm2")]
        for i in range(len(backbone.down)):
            sites += [
                (backbone.down[i], backbone.down_norm[i], "0"),
                (backbone.up[i], backbone.up_norm[i], "0"),
                (cast(nn.Sequential, backbone.up_mix[i])[0], cast(nn.Sequential, backbone.up_mix[i])[1], "0"),
            ]
    elif isinstance(backbone, PointNet):
        sites += [(backbone.mlp[i], backbone.mlp[i + 1], "0") for i in range(0, len(backbone.mlp), 2)]
    return sites


@torch.no_grad()
def fold_batch_norms(model: LocalizabilityNet) -> LocalizabilityNet:
    """The model in eval mode with each batch norm folded into the layer before it: in eval mode a
    norm is a per-channel scale and shift, which the layer's weight and a bias carry at no cost, so
    inference skips a pass over the features per norm (24 in the ResUNet). For inference only: the
    folded model has no norms left to train and is not a checkpoint of its config."""
    model.eval()
    for layer, owner, name in _norm_sites(model.backbone):
        norm = getattr(owner, name)
        if not isinstance(norm, nn.BatchNorm1d):
            raise ValueError(f"{type(owner).__name__}.{name} is {type(norm).__name__}, not a batch norm: folded twice?")
        running_mean, running_var = cast(torch.Tensor, norm.running_mean), cast(torch.Tensor, norm.running_var)
        scale = norm.weight / torch.sqrt(running_var + norm.eps)
        shift = norm.bias - running_mean * scale
        # output channels: the last axis of a sparse convolution's weight, the first of a linear layer's
        weight, old_bias = cast(torch.Tensor, layer.weight), cast(torch.Tensor | None, layer.bias)
        weight.mul_(scale[:, None] if isinstance(layer, nn.Linear) else scale)
        bias = shift if old_bias is None else old_bias * scale + shift
        layer.bias = nn.Parameter(bias)
        setattr(owner, name, nn.Identity())
    return model


def quantize_int8(model: LocalizabilityNet) -> LocalizabilityNet:
    """The ResUNet's gather convolutions switched to int8 gathers and products (see
    sparse.GatherConv.quantize), for inference after fold_batch_norms. The stem stays in float32:
    its inputs mix sub-voxel offsets of +-0.5 with positions of several units, which one 8-bit
    scale would round away. A torch without CPU int8 products keeps the model as it is."""
    if not isinstance(model.backbone, ResUNet) or not int8_products_work():
        return model
    for module in model.backbone.modules():
        if isinstance(module, GatherConv) and module is not model.backbone.stem:
            module.quantize()
    return model


def up_vector(T_w_s: np.ndarray) -> np.ndarray:
    """The world's up direction in the sensor frame of world-from-sensor pose(s) (..., 4, 4)."""
    return np.asarray(T_w_s)[..., 2, :3]


def up_tensor(up: np.ndarray | None, device: torch.device | str = "cpu") -> torch.Tensor | None:
    """Up vectors (B, 3) as the model's float32 input on `device`; None stays None."""
    return None if up is None else torch.from_numpy(np.array(up, dtype=np.float32).reshape(-1, 3)).to(device)


class DeviceError(ValueError):
    """A device that this torch cannot use (no CUDA GPU visible, or an unknown name)."""


DEVICES = ("cpu", "cuda", "auto")


def torch_device(name: str = "cpu") -> torch.device:
    """'cpu'; 'cuda' or 'cuda:N' (DeviceError where torch sees no CUDA GPU); 'auto': a CUDA GPU where
    one is visible, else the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise DeviceError(
                f"--device {name}: this torch sees no CUDA GPU (a CPU build, or no driver); use --device cpu"
            )
        return torch.device(name)
    raise DeviceError(f"unknown device '{name}' (cpu, cuda, cuda:N, auto)")


def model_device(model: nn.Module) -> torch.device:
    """The device of a model's weights."""
    return next(model.parameters()).device


def check_scan(points: np.ndarray) -> np.ndarray:
    """The scan as float32 (N, 3), or ScanError naming what is wrong with it."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ScanError(f"a scan is an (N, 3) array of points, got shape {points.shape}")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points)).any(axis=1).sum())
        raise ScanError(f"the scan holds {bad} point{'s' if bad != 1 else ''} with NaN or inf")
    if len(points) < MIN_POINTS:
        raise ScanError(f"the scan has {len(points)} points; the classifier needs at least {MIN_POINTS}")
    far = out_of_reach(points)
    if far is not None:
        raise ScanError(f"the scan: {far}")
    return points.astype(np.float32, copy=False)


def one_per_voxel(points: np.ndarray, voxel: float, rng: np.random.Generator) -> np.ndarray:
    """One point drawn at random from each occupied voxel of the scan."""
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    keys = np.ravel_multi_index(cells.T, tuple(cells.max(axis=0) + 1))
    order = rng.permutation(len(points))
    first = np.unique(np.asarray(keys)[order], return_index=True)[1]  # the first of each voxel in a random order
    return points[order[first]]


def sample_points(points: np.ndarray, count: int, rng: np.random.Generator) -> torch.Tensor:
    """`count` points drawn without replacement (all of them when the scan has fewer)."""
    if len(points) > count:
        points = np.take(points, rng.choice(len(points), count, replace=False), axis=0)
    return torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))


def level_scan(points: np.ndarray, T_w_s: np.ndarray | None, cfg: ModelConfig) -> np.ndarray:
    """The scan as a model of this config reads it: turned into its level frame (ModelConfig.level)
    by the pose's tilt (none: the sensor is taken as level), or as it is."""
    if not cfg.level or T_w_s is None:
        return points
    return (points @ level_rotation_of(T_w_s).T.astype(np.float32)).astype(np.float32, copy=False)


def model_input(points: np.ndarray, cfg: ModelConfig, rng: np.random.Generator) -> torch.Tensor:
    """The point set a model of this config reads from one scan already in its frame (level_scan;
    see ModelConfig.sampling)."""
    if cfg.sampling == "voxels":
        points = one_per_voxel(points, cfg.voxel, rng)
    return sample_points(points, cfg.points, rng)


def symmetry_view(points: torch.Tensor, symmetry: tuple[float, float, bool]) -> torch.Tensor:
    """Points (or up vectors), (N, 3), mirrored and swapped as the view says."""
    sx, sy, swap = symmetry
    view = points * points.new_tensor([sx, sy, 1.0])
    return view[:, [1, 0, 2]] if swap else view


def canonical_view(points: torch.Tensor) -> tuple[float, float, bool]:
    """The mirror/swap view (symmetry_view) that turns a scan into its canonical form: its larger second
    moment along x (swap x and y if it lies along y), then the third moments along x and y positive.
    Every view of a scan in the group of mirrors and 90-degree turns about z has the same canonical
    form (up to float rounding), so a model that reads it answers each alike. A scan with equal
    moments (a perfectly symmetric one) keeps its own axes there."""
    p = points.double()
    swap = bool((p[:, 1] ** 2).sum() > (p[:, 0] ** 2).sum())
    third = (p[:, :2] ** 3).sum(dim=0)
    return (-1.0 if third[0] < 0 else 1.0, -1.0 if third[1] < 0 else 1.0, swap)


@torch.inference_mode()
def model_probabilities(
    model: LocalizabilityNet, batch: list[torch.Tensor], symmetric: bool = False, up: np.ndarray | None = None
) -> np.ndarray:
    """(B, 6) probabilities; symmetric: the mean over the eight mirror/swap views of each scan (one
    forward pass of 8 B scans), each view's output mapped back onto the scan's own axes. `up`
    (B, 3): see LocalizabilityNet.forward."""
    device = model_device(model)
    batch = [p.to(device) for p in batch]
    ups = up_tensor(up, device)
    if not symmetric:
        return torch.sigmoid(model(batch, ups)).cpu().numpy().astype(np.float64)
    views = [symmetry_view(p, sym) for sym in SYMMETRIES for p in batch]
    view_ups = None if ups is None else torch.cat([symmetry_view(ups, sym) for sym in SYMMETRIES])
    probs = torch.sigmoid(model(views, view_ups)).cpu().numpy().astype(np.float64)
    probs = probs.reshape(len(SYMMETRIES), len(batch), 6)
    swapped = np.array([swap for _, _, swap in SYMMETRIES])
    probs[swapped] = probs[swapped][..., SWAP_LABELS]
    return probs.mean(axis=0)


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op threads set to `n` for the block, and set back after it (a switch costs well
    under a microsecond)."""
    before = torch.get_num_threads()
    if before == n:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def save_checkpoint(
    path: str | Path,
    model: LocalizabilityNet,
    thresholds: np.ndarray,
    meta: dict[str, Any],
    extra: dict[str, Any] | None = None,
) -> None:
    """Write atomically: a reader (or a resumed run) never sees half a checkpoint."""
    path = Path(path)
    state = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "model": plain(dataclasses.asdict(model.config)),
        "state_dict": {k: v.cpu() for k, v in model.state_dict().items()},  # read on any device
        "thresholds": [float(t) for t in thresholds],
        **meta,
        **(extra or {}),
    }
    write_atomic(path, lambda fh: torch.save(state, fh))


def torch_load_reason(exc: Exception) -> str:
    """torch.load's error in one line; its weights-only advice (load with code execution) is not ours to give."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    if lines and lines[0].startswith("Weights only load failed"):
        return "not a weights-only torch file, or corrupt"
    return lines[0] if lines else type(exc).__name__


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint's dict, checked for format and version (weights only: no code is run)."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a corrupt file
        raise CheckpointError(f"{path} is not a readable torch checkpoint ({torch_load_reason(exc)})") from exc
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not an l3e classifier checkpoint")
    if state.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint version {state.get('version')}; this code reads version {CHECKPOINT_VERSION}"
        )
    return state


def model_from_checkpoint(state: dict[str, Any], source: str = "checkpoint") -> LocalizabilityNet:
    """The network a checkpoint holds; CheckpointError naming `source` where its model settings are
    missing or unusable or its weights do not fit them."""
    if not isinstance(state.get("model"), dict) or not isinstance(state.get("state_dict"), dict):
        raise CheckpointError(f"{source} lacks its model settings or weights ('model', 'state_dict'): it is damaged")
    try:
        cfg = from_dict(ModelConfig, state["model"])
        model = LocalizabilityNet(cfg)
    except (TypeError, ValueError, KeyError) as exc:
        raise CheckpointError(f"{source} holds model settings this code cannot build: {exc}") from exc
    try:
        model.load_state_dict(state["state_dict"])
    except RuntimeError as exc:
        raise CheckpointError(
            f"{source} does not fit the {cfg.architecture} architecture of this code: {str(exc).splitlines()[0]}"
        ) from exc
    return model.eval()


@dataclass
class Classifier:
    """A trained model with its thresholds, ready to judge single scans."""

    model: LocalizabilityNet
    thresholds: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    # average over the eight mirror/swap views (8x the inference time), with the thresholds
    # chosen for those averages
    symmetric: bool = False

    @classmethod
    def load(
        cls, path: str | Path | None = None, symmetric: bool = False, int8: bool = True, device: str = "cpu"
    ) -> Classifier:
        """`int8`: on the CPU, the ResUNet's convolutions in int8 (quantize_int8), its ResBlocks fused:
        faster than float32, with the same decisions (docs/decisions.md). `device`: where the network
        runs (torch_device's names); on a GPU in float32."""
        where = torch_device(device)
        path = Path(path) if path is not None else DEFAULT_CHECKPOINT
        state = load_checkpoint(path)
        broken = [
            name
            for name, t in state["state_dict"].items()
            if torch.is_tensor(t) and t.is_floating_point() and not torch.isfinite(t).all()
        ]
        if broken:  # a model with NaN or infinite weights answers nothing trustworthy: refuse it, never judge with it
            raise CheckpointError(
                f"{path} has non-finite weights in {', '.join(broken[:3])}"
                f"{' ...' if len(broken) > 3 else ''}: the file is corrupt or its training diverged"
            )
        model = fold_batch_norms(model_from_checkpoint(state, str(path)))
        if int8 and where.type == "cpu":
            quantize_int8(model)
        model.to(where)
        meta = {k: v for k, v in state.items() if k not in ("state_dict", "optimizer", "scheduler")}
        if "thresholds" not in state:
            raise CheckpointError(f"{path} holds no thresholds")
        if symmetric and "symmetric_thresholds" not in state:
            raise CheckpointError(
                f"{path} has no thresholds for symmetric inference; add them with "
                f"'l3e calibrate --checkpoint {path} --dataset <its dataset>'"
            )
        key = "symmetric_thresholds" if symmetric else "thresholds"
        try:
            thresholds = np.asarray(state[key], dtype=np.float64)
        except (TypeError, ValueError):
            thresholds = np.full(0, np.nan)
        if thresholds.shape != (6,) or not ((thresholds > 0) & (thresholds < 1)).all():
            raise CheckpointError(
                f"{path}: its {key} must be six probabilities in (0, 1), one per axis "
                f"(x, y, z, roll, pitch, yaw); it holds {state[key]!r}"
            )
        return cls(model, thresholds, meta, symmetric=symmetric)

    def check_settings(self, lidar_model: str | None = None, registration: dict | None = None) -> None:
        """Warn when the scans or the registration differ from those the labels were made with."""
        trained = self.meta.get("sensors") or [self.meta.get("lidar", {}).get("model")]
        # the calibrated VLP-16 is the same sensor: its beams leave at most 11 mm off the axis
        if lidar_model is not None and None not in trained and lidar_model.removesuffix("-calibrated") not in trained:
            warnings.warn(
                f"the classifier was trained on {', '.join(trained)} scans and now sees {lidar_model} scans",
                stacklevel=2,
            )
        protocol = self.meta.get("protocol", 1)
        if protocol != LABEL_PROTOCOL:
            warnings.warn(
                f"the classifier learnt labels of {protocol_name(protocol)}; this version labels under "
                f"{protocol_name(LABEL_PROTOCOL)}: refit it on data labelled now (l3e fit-constraints "
                "--checkpoint ... --dataset ...) or train it again",
                stacklevel=2,
            )
            return
        in_use = plain(registration) if registration is not None else None
        stored = self.meta.get("registration")
        labelled = None if stored is None else with_defaults(RegistrationConfig, stored)
        if in_use is not None and labelled not in (None, in_use):
            warnings.warn(
                "the classifier's labels were made with other registration settings than the ones in use", stacklevel=2
            )

    @property
    def needs_pose(self) -> bool:
        """Whether the model reads the sensor's tilt (from the pose's rotation) with the scan."""
        return self.model.config.gravity or self.model.config.level

    def probabilities(self, scans: list[np.ndarray], poses: np.ndarray | None = None) -> np.ndarray:
        """(B, 6) probabilities of non-localizability, on the axes of each scan's level frame; ScanError
        for a scan that cannot be judged. `poses` (B, 4, 4) world-from-sensor: only their tilt is read
        (None: every sensor taken as level)."""
        rng = np.random.default_rng(self.seed)
        if self.model.config.gravity and poses is None:
            raise ValueError(
                "this classifier reads the sensor's tilt: give the scans' poses (an IMU's roll and pitch suffice)"
            )
        cfg = self.model.config
        batch = [
            model_input(level_scan(check_scan(s), None if poses is None else poses[k], cfg), cfg, rng)
            for k, s in enumerate(scans)
        ]
        up = up_vector(poses) if cfg.gravity and poses is not None else None
        return model_probabilities(self.model, batch, self.symmetric, up)

    def predict(self, points: np.ndarray, T_w_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One scan, on one torch thread: a single scan's work is too small for a second thread to pay
        on an idle machine, and on a busy one OpenMP's waiting threads spin against the other work
        (benchmarks/bench_load.py; docs/decisions.md)."""
        with torch_threads(1):
            p = self.probabilities([points], None if T_w_s is None else np.asarray(T_w_s)[None])[0]
        return p, p > self.thresholds
