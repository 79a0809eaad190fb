"""Training the localizability classifier on a labelled dataset, resumable after a kill.

Every epoch is seeded by (seed, epoch), so a run resumed from `last.pt` goes on exactly as the
uninterrupted run would have. The folder holds:
  config.yaml   the training and model settings
  log.jsonl     one line of losses and validation scores per epoch
  last.pt       the latest state (model, optimizer, scheduler), rewritten atomically each epoch
  best.pt       the epoch with the best validation F1, with thresholds from its PR curves
  model.pt      best.pt without the optimizer state: the file to ship and load
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from l3e_env.config import dump_yaml, plain, settings_changed, to_dict
from l3e_env.core.files import new_folder
from l3e_env.data.dataset import (
    DatasetUnion,
    LabelDataset,
    check_ground_truth,
    error_ratios,
    open_datasets,
    scan_labelled,
    sensors_of,
)
from scenes import HELDOUT_SCENES, TEST_SCENES, TRAIN_SCENES, VALIDATION_SCENES, canonical_scene_name, scene_family

from .classifier import (
    SWAP_LABELS,
    SYMMETRIES,
    CheckpointError,
    LocalizabilityNet,
    ModelConfig,
    level_scan,
    load_checkpoint,
    model_device,
    model_from_checkpoint,
    model_input,
    model_probabilities,
    save_checkpoint,
    torch_device,
    up_tensor,
    up_vector,
)
from .constraints import FEATURES, AxisStacker, fit_stacker
from .scores import axis_scores, best_thresholds, mean_scores, micro_f1


@dataclass
class TrainConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    epochs: int = 12
    batch_size: int = 8
    # AdamW: in a short budget it fits faster than the paper's SGD (momentum 0.9, lr 0.02),
    # whose training loss was still 0.65 after 400 steps (AdamW: 0.62 after 300)
    optimizer: str = "adamw"  # or "sgd"
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    lr_decay: float = 0.9  # exponential, per epoch
    balance: bool = True  # power-set up-sampling to the second most common combination
    max_upsampling: float = 100.0
    samples_per_epoch: int = 1600  # drawn from the balanced pool; 0 = the whole pool each epoch
    augment: bool = True  # mirror and x/y swap with the matching label permutation
    train_scenes: list[str] = field(default_factory=lambda: list(TRAIN_SCENES))
    validation_scenes: list[str] = field(default_factory=lambda: list(VALIDATION_SCENES))
    seed: int = 0
    threads: int = 2
    # fine-tuning: start from this checkpoint's weights (same architecture and model settings)
    init: str | None = None
    # model.pt stores the F-beta-best validation thresholds: in fusion a missed degenerate axis
    # corrupts the estimate while a false flag only hands that axis to the odometry for a step,
    # so recall weighs more (beta 2). Epochs are still chosen by validation F1.
    threshold_beta: float = 2.0
    # 0: the paper's hard labels. k > 0: soft targets sigmoid(k * ln(error / label threshold)),
    # so a scan whose error sits just at the threshold is taught 0.5 instead of a hard 0 or 1
    # (at k = 4, twice the threshold gives 0.94 and half of it 0.06)
    soft_labels: float = 0.0
    # 0: every training scan weighs alike. eta > 0: group DRO (Sagawa et al., ICLR 2020) over the
    # training scene families: each family's weight grows as exp(eta * its loss) step by step and
    # the loss is the families' weighted mean, so the network cannot buy a low mean loss with
    # cues that serve the common families and fail a rarer one, as they fail the unseen test ones
    group_dro: float = 0.0
    # 1: no scaling. f > 1: each training scan is also scaled by a factor drawn log-uniformly from
    # [1/f, f], labels kept: a corridor stays degenerate along its axis at any width, so the
    # network is taught shapes rather than the training scenes' sizes
    scale_augment: float = 1.0
    # fine-tuning with replay: training scenes whose scans are replayed beside the new ones (the
    # base's own places), drawn as `replay_share` of each epoch's samples, so that a network taught a
    # place does not forget the others (and is not taught only the place's few scans)
    replay_scenes: list[str] = field(default_factory=list)
    replay_share: float = 0.5


class TrainingError(RuntimeError):
    """A run that cannot start or resume; the message says why."""


def distilled_scenes(folders: list[str | Path]) -> list[str]:
    """The places of the distillation sets among `folders` (`l3e train --distilled` trains on them
    too); a TrainingError where one lies in a test or held-out family or is a validation scene,
    which the classifier must never have learnt, not even from an estimate."""
    places: list[str] = []
    for folder in folders:
        data = LabelDataset(folder)
        if data.labeller == "scan":
            places += [s for s in data.manifest["scenes"] if s not in places]
    if not places:
        raise TrainingError(
            "--distilled: none of the datasets is a distillation set (l3e dataset generate --labeller scan)"
        )
    unseen = {scene_family(s) for s in [*TEST_SCENES, *HELDOUT_SCENES]}
    banned = [s for s in places if scene_family(s) in unseen or s in VALIDATION_SCENES]
    if banned:
        raise TrainingError(
            f"the distillation sets hold {', '.join(banned[:5])}: a test or held-out family or a validation "
            "scene is never trained on; label other places"
        )
    return places


def split_indices(data: LabelDataset | DatasetUnion, scenes: list[str]) -> np.ndarray:
    """Rows of the dataset whose scene is in `scenes` (all must be in the dataset)."""
    names = data.manifest["scenes"]
    missing = sorted(set(scenes) - set(names))
    if missing:
        raise TrainingError(f"scenes {missing} are not in dataset {data.folder} (it has {names})")
    wanted = [names.index(s) for s in scenes]
    return np.flatnonzero(np.isin(np.asarray(data.arrays["scene"]), wanted))


def training_targets(data: LabelDataset | DatasetUnion, softness: float) -> np.ndarray:
    """(N, 6) float targets: the labels, or soft ones from each row's mean errors and its own
    dataset's label thresholds (the parts of a union may differ)."""
    if softness <= 0:
        return data.labels.astype(np.float32)
    ratio = np.maximum(error_ratios(data), 1e-9)
    return (1.0 / (1.0 + ratio**-softness)).astype(np.float32)  # = sigmoid(k ln ratio)


def scene_families(data: LabelDataset | DatasetUnion, rows: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Each row's scene family (`scene_family`: tunnel-3 is a tunnel) as an index, and the
    families' names."""
    names = data.manifest["scenes"]
    of_row = [scene_family(names[i]) for i in np.asarray(data.arrays["scene"])[rows]]
    families = sorted(set(of_row))
    return np.array([families.index(f) for f in of_row], dtype=np.int64), families


class GroupWeights:
    """Group DRO's weights over the training families: a step raises each family in the batch by
    exp(eta * its mean loss), and the batch's loss is the families' mean under those weights."""

    def __init__(self, families: list[str], eta: float, weights: list[float] | None = None):
        self.families, self.eta = families, eta
        self.q = torch.tensor(
            weights if weights is not None else [1.0 / len(families)] * len(families), dtype=torch.float64
        )

    def loss(self, per_scan: torch.Tensor, group: torch.Tensor) -> torch.Tensor:
        present = torch.unique(group)
        means = torch.stack([per_scan[group == g].mean() for g in present])
        self.q[present] *= torch.exp(self.eta * means.detach().double())
        self.q /= self.q.sum()
        weights = self.q[present].float()
        return (weights * means).sum() / weights.sum()

    def state(self) -> dict[str, float]:
        return {f: float(w) for f, w in zip(self.families, self.q)}


def _training_pool(data: LabelDataset | DatasetUnion, train_rows: np.ndarray, cfg: TrainConfig) -> np.ndarray:
    """Positions in `train_rows` that an epoch draws from: the balanced pool (or every row); with
    replay scenes, the new scenes' pool and the replayed ones' each balanced on their own, the
    replayed drawn to `replay_share` of the whole (seeded by cfg.seed)."""

    def pool_of(positions: np.ndarray) -> np.ndarray:
        if not cfg.balance or not len(positions):
            return positions
        return positions[balanced_pool(data.labels[train_rows[positions]], cfg.max_upsampling)]

    every = np.arange(len(train_rows))
    if not cfg.replay_scenes:
        return pool_of(every)
    replayed = np.isin(train_rows, split_indices(data, cfg.replay_scenes))
    new, old = pool_of(every[~replayed]), pool_of(every[replayed])
    if not len(new) or not len(old):
        raise TrainingError(
            f"replay needs new scans and replayed ones among the training scenes: {len(new)} new, {len(old)} replayed"
        )
    wanted = int(round(len(new) * cfg.replay_share / (1 - cfg.replay_share)))
    rng = np.random.default_rng([cfg.seed, 7])
    return np.concatenate([new, rng.choice(old, wanted, replace=wanted > len(old))])


def balanced_pool(labels: np.ndarray, max_upsampling: float) -> np.ndarray:
    """Row indices with each of the 64 label combinations repeated up to the count of the second
    most common combination (at most `max_upsampling` times), as in the paper."""
    codes = (np.asarray(labels, dtype=np.int64) << np.arange(6)).sum(1)
    counts = np.bincount(codes, minlength=64)
    target = np.sort(counts)[-2] if (counts > 0).sum() > 1 else counts.max()
    pool = []
    for code in np.flatnonzero(counts):
        rows = np.flatnonzero(codes == code)
        repeat = int(round(min(max(target / len(rows), 1.0), max_upsampling)))
        pool.append(np.tile(rows, repeat))
    return np.concatenate(pool)


def augment(
    points: np.ndarray, labels: np.ndarray, rng: np.random.Generator, up: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A random mirror/swap view of the scan, with its labels (and up vector) to match."""
    sign = np.array([rng.choice([-1, 1]), rng.choice([-1, 1]), 1], dtype=np.float32)
    swap = rng.random() < 0.5

    def view(v: np.ndarray) -> np.ndarray:
        v = v * sign
        return v[..., [1, 0, 2]] if swap else v

    return view(points), labels[SWAP_LABELS] if swap else labels, None if up is None else view(up)


def scaled(points: np.ndarray, factor: float, rng: np.random.Generator) -> np.ndarray:
    """The scan scaled by a factor drawn log-uniformly from [1/factor, factor]; as it is (and
    nothing drawn) at factor 1, so runs without scaling keep their draws."""
    if factor <= 1.0:
        return points
    return points * np.float32(np.exp(rng.uniform(-1.0, 1.0) * np.log(factor)))


def _dataset_batches(
    model: LocalizabilityNet,
    data: LabelDataset | DatasetUnion,
    rows: np.ndarray,
    seed: int,
    batch_size: int,
    progress: bool,
):
    """(start, model inputs, up vectors or None) per batch of `rows`; the point sampling of scan i
    is seeded by (seed, i), so the figures do not depend on the batch size or the order."""
    ups = up_vector(data.poses[rows]) if model.config.gravity else None
    for start in tqdm(range(0, len(rows), batch_size), desc="predicting", disable=not progress, leave=False):
        chunk = rows[start : start + batch_size]
        batch = [
            model_input(
                level_scan(data.scan(int(i)), data.poses[int(i)], model.config),
                model.config,
                np.random.default_rng([seed, int(i)]),
            )
            for i in chunk
        ]
        yield start, batch, None if ups is None else ups[start : start + len(chunk)]


def predict_dataset(
    model: LocalizabilityNet,
    data: LabelDataset | DatasetUnion,
    rows: np.ndarray,
    seed: int = 0,
    batch_size: int = 16,
    progress: bool = False,
    symmetric: bool = False,
) -> np.ndarray:
    """(len(rows), 6) probabilities (averaged over the mirror/swap views if `symmetric`)."""
    model.eval()
    if symmetric:  # the same number of views per forward pass
        batch_size = max(1, batch_size // len(SYMMETRIES))
    out = np.zeros((len(rows), 6))
    for start, batch, up in _dataset_batches(model, data, rows, seed, batch_size, progress):
        out[start : start + len(batch)] = model_probabilities(model, batch, symmetric, up)
    return out


@torch.inference_mode()
def network_parts(
    model: LocalizabilityNet,
    data: LabelDataset | DatasetUnion,
    rows: np.ndarray,
    seed: int = 0,
    batch_size: int = 16,
    progress: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The network's own logits (len(rows), 6), before any constraint layer, the scans' Hessian
    features (len(rows), 12 per level of config.constraint_levels), both on the axes of the view the
    model reads (LocalizabilityNet.canonical), and which rows that view swaps x and y (len(rows),):
    their labels in that view are labels[SWAP_LABELS]."""
    model.eval()
    logits = np.zeros((len(rows), 6))
    features = np.zeros((len(rows), FEATURES * len(model.config.constraint_levels)))
    swapped = np.zeros(len(rows), dtype=bool)
    device = model_device(model)
    for start, batch, up in _dataset_batches(model, data, rows, seed, batch_size, progress):
        views, view_up, swap = model.canonical([p.to(device) for p in batch], up_tensor(up, device))
        net, feats = model.parts(views, view_up, constraints=True)
        if feats is None:
            raise TrainingError("the model gives no constraint features: it has no constraint levels")
        logits[start : start + len(batch)] = net.cpu().numpy()
        features[start : start + len(batch)] = feats.cpu().numpy()
        if swap is not None:
            swapped[start : start + len(batch)] = swap.cpu().numpy()
    return logits, features, swapped


def _optimizer(cfg: TrainConfig, model: torch.nn.Module) -> torch.optim.Optimizer:
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(model.parameters(), lr=cfg.learning_rate, momentum=0.9, weight_decay=cfg.weight_decay)
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(model.parameters(), lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
    raise TrainingError(f"unknown optimizer '{cfg.optimizer}' (sgd, adamw)")


def _label_meta(data: LabelDataset | DatasetUnion) -> dict[str, Any]:
    """What a checkpoint records of the labels it learnt: their protocol, sensors and registration."""
    settings = data.manifest["settings"]
    return {
        "protocol": data.manifest["protocol"],
        "lidar": settings["lidar"],  # the first part's
        "sensors": sensors_of(data),
        "registration": settings["registration"],
        "labels": settings["labels"],
    }


def _meta(cfg: TrainConfig, data: LabelDataset | DatasetUnion) -> dict[str, Any]:
    return {
        "training": plain(to_dict(cfg)),
        **_label_meta(data),
        "dataset": {"folder": data.name, "count": len(data), "seed": data.manifest["settings"]["seed"]},
    }


def check_train_config(cfg: TrainConfig) -> None:
    """TrainingError for settings no run can use, before any folder or data is touched."""
    problems = [
        f"{name} must be {rule}, got {value}"
        for name, value, ok, rule in [
            ("epochs", cfg.epochs, cfg.epochs >= 1, "at least 1"),
            ("batch_size", cfg.batch_size, cfg.batch_size >= 1, "at least 1"),
            ("learning_rate", cfg.learning_rate, cfg.learning_rate >= 0, "0 or more"),
            ("lr_decay", cfg.lr_decay, 0 < cfg.lr_decay <= 1, "in (0, 1]"),
            ("samples_per_epoch", cfg.samples_per_epoch, cfg.samples_per_epoch >= 0, "0 (the whole pool) or more"),
            ("threads", cfg.threads, cfg.threads >= 1, "at least 1"),
            ("optimizer", cfg.optimizer, cfg.optimizer in ("sgd", "adamw"), "sgd or adamw"),
            ("group_dro", cfg.group_dro, cfg.group_dro >= 0, "0 (off) or more"),
            ("scale_augment", cfg.scale_augment, cfg.scale_augment >= 1, "1 (off) or more"),
            ("replay_share", cfg.replay_share, 0 <= cfg.replay_share < 1, "in [0, 1)"),
        ]
        if not ok
    ]
    if problems:
        raise TrainingError("; ".join(problems))


def _initial_model(cfg: TrainConfig) -> LocalizabilityNet:
    """Fresh weights seeded by cfg.seed, or (fine-tuning) the weights of cfg.init."""
    if cfg.model.constraints:
        raise TrainingError(
            "the constraint layer is fitted after training (l3e fit-constraints): train the network "
            "without it, from a checkpoint without it"
        )
    torch.manual_seed(cfg.seed)
    if cfg.init is None:
        return LocalizabilityNet(cfg.model)
    start = model_from_checkpoint(load_checkpoint(cfg.init), cfg.init)
    network = network_config(start.config)
    if plain(to_dict(network)) != plain(to_dict(cfg.model)):
        raise TrainingError(
            f"--init {cfg.init}: its model settings {plain(to_dict(network))} differ from "
            f"this run's {plain(to_dict(cfg.model))}"
        )
    if network == start.config:
        return start
    model = LocalizabilityNet(network)  # a checkpoint with a constraint layer: its network, without the layer
    model.load_state_dict({k: v for k, v in start.state_dict().items() if not k.startswith("stacker.")})
    return model


def network_config(config: ModelConfig) -> ModelConfig:
    """A model's settings without its constraint layer: what training starts from, since the
    layer is fitted after the network (fit_constraints)."""
    return replace(config, constraints=False, constraint_levels=ModelConfig.constraint_levels)


def _resumable(training: dict[str, Any]) -> dict[str, Any]:
    """The settings a resumed run must share with the first one: all but the epoch count (a
    finished run can be trained further) and the thread count (a resumed run may get more cores)."""
    full = {**plain(to_dict(TrainConfig())), **training}  # settings added since the run began: their defaults
    return {k: v for k, v in full.items() if k not in ("epochs", "threads", "threshold_beta")}


def _split(data: LabelDataset | DatasetUnion, cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """The training and validation rows; validation rows must hold labels made in the scene."""
    train_rows, val_rows = split_indices(data, cfg.train_scenes), split_indices(data, cfg.validation_scenes)
    if len(train_rows) == 0:
        raise TrainingError("the training split is empty")
    if scan_labelled(data)[val_rows].any():
        raise TrainingError(
            "validation scenes are in a dataset labelled by each scan's own estimate: epochs and "
            "thresholds are chosen on labels made in the scene; give the validation scenes' dataset "
            "labelled in the scene and leave them out of the distillation set"
        )
    return train_rows, val_rows


@dataclass
class _Run:
    """A training run under way: its data and split, its targets, the model and its optimiser, and
    where it stands (the epoch to begin with, the best epoch so far)."""

    cfg: TrainConfig
    data: LabelDataset | DatasetUnion
    out: Path
    train_rows: np.ndarray
    val_rows: np.ndarray
    targets: np.ndarray
    poses: np.ndarray  # (N, 4, 4) the scans' poses, whose tilt levels each scan (ModelConfig.level)
    up: np.ndarray | None
    meta: dict[str, Any]
    model: LocalizabilityNet  # on the run's device
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.ExponentialLR
    pool: np.ndarray
    groups: GroupWeights | None = None
    row_family: dict[int, int] = field(default_factory=dict)
    first_epoch: int = 0
    best: dict[str, Any] = field(default_factory=lambda: {"f1": -1.0, "micro_f1": -1.0})


def train(
    dataset: str | Path | list[str | Path],
    out_dir: str | Path,
    cfg: TrainConfig,
    progress: bool = True,
    device: str = "cpu",
) -> dict[str, Any]:
    """Train (or resume) into `out_dir` on one dataset or several read as one; returns the
    summary of the best epoch. `device`: where the network trains (classifier.torch_device's names);
    a run may resume on another."""
    check_train_config(cfg)
    where = torch_device(device)
    # a mesh scene by its absolute path, as its dataset names it, whatever folder the config was written in
    cfg = replace(
        cfg,
        train_scenes=[canonical_scene_name(s) for s in cfg.train_scenes],
        validation_scenes=[canonical_scene_name(s) for s in cfg.validation_scenes],
    )
    torch.set_num_threads(cfg.threads)
    data = open_datasets(dataset, mixed_sensors=True)  # a network may learn several sensors' scans
    out = Path(out_dir)
    with new_folder(out):  # a new run refused at its start, or failing in its first epoch, leaves no folder
        run = _start(cfg, data, out, where)
        if run.first_epoch < cfg.epochs:
            _run_epoch(run, run.first_epoch, progress)
    for epoch in range(run.first_epoch + 1, cfg.epochs):
        _run_epoch(run, epoch, progress)
    return finalize(data, out, cfg, run.val_rows, run.meta)


def _run_epoch(run: _Run, epoch: int, progress: bool) -> None:
    """One epoch: trained, validated and saved (last.pt, and model.pt where it improved)."""
    t0 = time.perf_counter()
    losses = _train_epoch(run, epoch, progress)
    run.scheduler.step()
    record: dict[str, Any] = {
        "epoch": epoch + 1,
        "train_loss": float(np.mean(losses)),
        "lr": run.scheduler.get_last_lr()[0],
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if run.groups is not None:
        record["family_weights"] = {f: round(w, 4) for f, w in run.groups.state().items()}
    thresholds, improved = _validate(run, record)
    _save_epoch(run, epoch, record, thresholds, improved)
    if progress:
        val = f", val loss {record['val_loss']:.3f}, F1 {record['val_f1']:.3f}" if "val_f1" in record else ""
        print(f"epoch {epoch + 1}/{run.cfg.epochs}: train loss {record['train_loss']:.3f}{val} ({record['seconds']} s)")


def _start(cfg: TrainConfig, data: LabelDataset | DatasetUnion, out: Path, device: torch.device) -> _Run:
    """The run in `out`: a new one, or the one its last.pt holds, resumed where it stopped (refused
    where its settings differ)."""
    train_rows, val_rows = _split(data, cfg)
    meta = _meta(cfg, data)
    last = out / "last.pt"
    state = load_checkpoint(last) if last.exists() else None
    if state is not None:
        before = {**_resumable(state["training"]), "dataset": state["dataset"]}
        now = {**_resumable(meta["training"]), "dataset": meta["dataset"]}
        if before != now:
            raise TrainingError(
                f"{out} holds a run with other settings ({settings_changed(before, now)}); choose another folder"
            )
        model = model_from_checkpoint(state, str(last))
    else:
        model = _initial_model(cfg)
        dump_yaml(cfg, out / "config.yaml")
    model.to(device)  # before the optimiser, whose state follows the weights
    optimizer = _optimizer(cfg, model)
    pool = _training_pool(data, train_rows, cfg)
    run = _Run(
        cfg,
        data,
        out,
        train_rows,
        val_rows,
        training_targets(data, cfg.soft_labels),
        np.asarray(data.poses),
        up_vector(data.poses) if cfg.model.gravity else None,
        meta,
        model,
        optimizer,
        torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=cfg.lr_decay),
        pool,
    )
    if state is not None:
        run.optimizer.load_state_dict(state["optimizer"])
        run.scheduler.load_state_dict(state["scheduler"])
        run.first_epoch, run.best = state["epoch"] + 1, state["best"]
        print(f"resuming {out} after epoch {state['epoch'] + 1}")
    if cfg.group_dro > 0:
        family, families = scene_families(data, train_rows)
        run.row_family = dict(zip(train_rows.tolist(), family.tolist()))
        saved = state.get("group_weights") if state is not None else None
        run.groups = GroupWeights(families, cfg.group_dro, list(saved.values()) if saved else None)
    return run


def _train_epoch(run: _Run, epoch: int, progress: bool) -> list[float]:
    """One epoch of steps over scans drawn from the balanced pool; the steps' losses."""
    cfg, model = run.cfg, run.model
    rng = np.random.default_rng([cfg.seed, epoch])
    torch.manual_seed(cfg.seed * 100_003 + epoch)
    # at least one whole batch: a pool smaller than a batch (a small dataset of one's own scene)
    # would otherwise give epochs without a single step
    count = max(cfg.samples_per_epoch or len(run.pool), cfg.batch_size)
    order = run.train_rows[rng.choice(run.pool, count, replace=count > len(run.pool))]
    model.train()
    losses: list[float] = []
    bar = tqdm(
        range(0, count - cfg.batch_size + 1, cfg.batch_size),
        disable=not progress,
        leave=False,
        desc=f"epoch {epoch + 1}/{cfg.epochs}",
    )
    for start in bar:
        rows = order[start : start + cfg.batch_size]
        batch, targets, ups = [], [], []
        for i in rows:
            pts = level_scan(run.data.scan(int(i)), run.poses[i], cfg.model)
            lab, up = run.targets[i], run.up[i] if run.up is not None else None
            if cfg.augment:
                pts, lab, up = augment(pts, lab, rng, up)
            pts = scaled(pts, cfg.scale_augment, rng)
            batch.append(model_input(pts, cfg.model, rng))
            targets.append(lab)
            ups.append(up)
        device = model_device(model)
        up_batch = up_tensor(np.array(ups), device) if run.up is not None else None
        logits = model([p.to(device) for p in batch], up_batch)
        truth = torch.tensor(np.array(targets), dtype=torch.float32, device=device)
        if run.groups is None:
            loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, truth)
        else:  # the families' weights are kept on the CPU
            per_scan = torch.nn.functional.binary_cross_entropy_with_logits(logits, truth, reduction="none").mean(1)
            loss = run.groups.loss(per_scan.cpu(), torch.tensor([run.row_family[int(i)] for i in rows]))
        run.optimizer.zero_grad()
        loss.backward()
        run.optimizer.step()
        losses.append(loss.item())
        bar.set_postfix(loss=f"{np.mean(losses[-50:]):.3f}")
    return losses


def _validate(run: _Run, record: dict[str, Any]) -> tuple[np.ndarray, bool]:
    """The validation split's loss, scores and F1-best thresholds into `record`; the thresholds and
    whether the epoch is the best so far by the micro-F1 of every axis decision (without a validation
    split: thresholds 0.5, always). The mean F1 over axes swings by a sixth wherever an axis with no
    positive (z under protocol 3) gets one false flag; the micro-F1 counts each decision alike."""
    if not len(run.val_rows):
        return np.full(6, 0.5), True
    probs = predict_dataset(run.model, run.data, run.val_rows, seed=run.cfg.seed)
    y = run.data.labels[run.val_rows]
    record["val_loss"] = float(
        torch.nn.functional.binary_cross_entropy_with_logits(
            torch.logit(torch.tensor(probs).clamp(1e-6, 1 - 1e-6)), torch.tensor(y, dtype=torch.float64)
        )
    )
    thresholds = best_thresholds(y, probs)
    scores = mean_scores(axis_scores(y, probs > thresholds))
    scores["micro_f1"] = micro_f1(y, probs > thresholds)
    record.update({f"val_{k}": v for k, v in scores.items()})
    record["thresholds"] = thresholds.round(4).tolist()
    return thresholds, scores["micro_f1"] > run.best.get("micro_f1", -1.0)


def _save_epoch(run: _Run, epoch: int, record: dict[str, Any], thresholds: np.ndarray, improved: bool) -> None:
    """The epoch's line in log.jsonl, best.pt where it is the best so far, and last.pt to resume from."""
    with open(run.out / "log.jsonl", "a") as fh:
        fh.write(json.dumps(record) + "\n")
    if improved:
        run.best = {
            "f1": record.get("val_f1", float("nan")),
            "micro_f1": record.get("val_micro_f1", float("nan")),
            "epoch": epoch + 1,
        }
        save_checkpoint(run.out / "best.pt", run.model, thresholds, run.meta, {"epoch": epoch, "scores": record})
    save_checkpoint(
        run.out / "last.pt",
        run.model,
        thresholds,
        run.meta,
        {
            "epoch": epoch,
            "best": run.best,
            "optimizer": run.optimizer.state_dict(),
            "scheduler": run.scheduler.state_dict(),
            "group_weights": run.groups.state() if run.groups is not None else None,
        },
    )


def finalize(
    data: LabelDataset | DatasetUnion, out: Path, cfg: TrainConfig, val_rows: np.ndarray, meta: dict[str, Any]
) -> dict:
    """model.pt: the best epoch's weights with the operating thresholds (F-beta on validation), for
    single and for symmetric (eight-view) inference."""
    state = load_checkpoint(out / "best.pt")
    model = model_from_checkpoint(state, "best.pt")
    thresholds = symmetric = np.asarray(state["thresholds"])
    if len(val_rows):
        probs = predict_dataset(model, data, val_rows, seed=cfg.seed)
        thresholds = best_thresholds(data.labels[val_rows], probs, beta=cfg.threshold_beta)
        symmetric = symmetric_thresholds(model, data, val_rows, cfg.seed, cfg.threshold_beta)
    save_checkpoint(
        out / "model.pt",
        model,
        thresholds,
        {**meta, "threshold_beta": cfg.threshold_beta},
        {"epoch": state["epoch"], "scores": state["scores"], "symmetric_thresholds": [float(t) for t in symmetric]},
    )
    return {"best_epoch": state["epoch"] + 1, **state["scores"], "thresholds": thresholds.round(4).tolist()}


def symmetric_thresholds(
    model: LocalizabilityNet,
    data: LabelDataset | DatasetUnion,
    val_rows: np.ndarray,
    seed: int,
    beta: float,
    progress: bool = False,
) -> np.ndarray:
    """F-beta-best validation thresholds for the eight-view averaged probabilities: averaging
    narrows the spread of the probabilities, so the single-view thresholds do not carry over."""
    probs = predict_dataset(model, data, val_rows, seed=seed, progress=progress, symmetric=True)
    return best_thresholds(data.labels[val_rows], probs, beta=beta)


def _checkpoint_meta(state: dict[str, Any]) -> dict[str, Any]:
    """What a rewritten checkpoint keeps of the old one: all but what save_checkpoint writes anew."""
    return {k: v for k, v in state.items() if k not in ("format", "version", "model", "state_dict", "thresholds")}


def calibrate_symmetric(
    checkpoint: str | Path, dataset: str | Path | list[str | Path], out: str | Path | None = None, progress: bool = True
) -> np.ndarray:
    """Add symmetric-inference thresholds to a checkpoint made before they existed, from its own
    validation scenes and F-beta; everything else in the file is kept. Written to `out`, or back
    into the checkpoint (atomically)."""
    state = load_checkpoint(checkpoint)
    training = state.get("training")
    if not isinstance(training, dict) or not training.get("validation_scenes"):
        raise CheckpointError(f"{checkpoint} does not name its validation scenes")
    data = open_datasets(dataset)
    rows = split_indices(data, training["validation_scenes"])
    model = model_from_checkpoint(state, str(checkpoint))
    thresholds = symmetric_thresholds(
        model, data, rows, int(training.get("seed", 0)), float(state.get("threshold_beta", 1.0)), progress
    )
    save_checkpoint(
        out or checkpoint,
        model,
        np.asarray(state["thresholds"]),
        _checkpoint_meta(state),
        {"symmetric_thresholds": [float(t) for t in thresholds]},
    )
    return thresholds


def with_fitted_layer(
    base: LocalizabilityNet,
    data: LabelDataset | DatasetUnion,
    rows: np.ndarray,
    seed: int,
    layer: tuple[tuple[int, ...], str | None],
    progress: bool,
) -> tuple[LocalizabilityNet, AxisStacker]:
    """The base network with a constraint layer over the ResUNet levels `layer[0]`, read in the view
    `layer[1]` (the base's own where None), fitted on `rows` (each row's labels in the view it was read
    in); the model and the fitted layer."""
    levels, frame = layer
    try:
        model = LocalizabilityNet(
            replace(base.config, constraints=True, constraint_levels=levels, frame=frame or base.config.frame)
        )
    except ValueError as exc:
        raise TrainingError(str(exc)) from exc
    model.load_state_dict({**model.state_dict(), **base.state_dict()})  # the base's network, the layer unfitted
    logits, features, swapped = network_parts(model, data, rows, seed, progress=progress)
    labels = np.array(data.labels[rows])
    labels[swapped] = labels[swapped][:, SWAP_LABELS]
    stacker = fit_stacker(logits, features, labels)
    if model.stacker is None:
        raise TrainingError("the model has no constraint layer to fit")
    model.stacker.load_state_dict(stacker.state_dict())
    return model.eval(), stacker


def fit_constraints(
    checkpoint: str | Path,
    dataset: str | Path | list[str | Path],
    out: str | Path,
    beta: float | None = None,
    levels: tuple[int, ...] = (0, 1),
    progress: bool = True,
    frame: str | None = None,
) -> dict[str, Any]:
    """A checkpoint with the constraint layer (l3e_env.model.constraints): the network of `checkpoint` as
    it is, a per-axis logistic layer over its logits and the Hessian features of the ResUNet levels
    `levels` fitted on its own training scenes, and thresholds (single and eight-view) chosen on its
    validation scenes by F-beta (`beta`: the checkpoint's own by default). `frame`: the view the model
    reads (ModelConfig.frame; the checkpoint's own by default), the layer fitted in it. The dataset
    must be labelled in the scene; the training scenes it lacks (a distillation set's) are left out."""
    state = load_checkpoint(checkpoint)
    training = state.get("training")
    if not isinstance(training, dict) or not training.get("train_scenes") or not training.get("validation_scenes"):
        raise CheckpointError(f"{checkpoint} does not name its training and validation scenes")
    base = model_from_checkpoint(state, str(checkpoint))
    if base.config.architecture != "resunet":
        raise CheckpointError(
            f"{checkpoint} is a {base.config.architecture}; the constraint layer reads a ResUNet's voxels"
        )
    data = open_datasets(dataset)
    check_ground_truth(data, "fit the constraint layer and choose thresholds on")
    # the training scenes the dataset holds: a network trained with a distillation set is fitted on
    # the scenes labelled in the scene
    held = [s for s in training["train_scenes"] if s in data.manifest["scenes"]]
    train_rows = split_indices(data, held)
    val_rows = split_indices(data, training["validation_scenes"])
    if not len(train_rows) or not len(val_rows):
        raise TrainingError(f"the dataset holds no scans of {checkpoint}'s training or validation scenes")
    Path(out).parent.mkdir(parents=True, exist_ok=True)  # before minutes of fitting, not after
    seed = int(training.get("seed", 0))
    model, stacker = with_fitted_layer(base, data, train_rows, seed, (tuple(levels), frame), progress)
    beta = float(state.get("threshold_beta", 1.0) if beta is None else beta)
    val_labels, val_probs = data.labels[val_rows], predict_dataset(model, data, val_rows, seed)
    thresholds = best_thresholds(val_labels, val_probs, beta=beta)
    symmetric = symmetric_thresholds(model, data, val_rows, seed, beta, progress)
    # the base network's epoch and validation scores describe the network without the layer: kept apart
    kept = {k: v for k, v in _checkpoint_meta(state).items() if k not in ("epoch", "scores")}
    scores = {f"val_{k}": v for k, v in mean_scores(axis_scores(val_labels, val_probs > thresholds)).items()}
    meta = {
        **kept,
        **_label_meta(data),
        "threshold_beta": beta,
        "scores": scores,
        "constraints": {
            "base": str(checkpoint),
            "fitted_rows": int(len(train_rows)),
            "dataset": data.name,
            "base_epoch": state.get("epoch"),
            "base_scores": state.get("scores"),
        },
    }
    save_checkpoint(out, model, thresholds, meta, {"symmetric_thresholds": [float(t) for t in symmetric]})
    return {"thresholds": thresholds.round(4).tolist(), "weights": stacker.weight.detach().numpy().round(3).tolist()}
