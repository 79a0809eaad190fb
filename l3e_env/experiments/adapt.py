"""Adapting the classifier to a new place from the place's own scans (`l3e adapt`).

The scan's own estimate (`scanmc`) needs nothing but the scan, so the scans a robot records in a new
place can be labelled by it and the shipped network fine-tuned on them: the network learns the place,
and then answers at its own cost (a forward pass, not scanmc's registrations). Three steps, each
resumable in the run folder:

  labels/   each scan read as `l3e judge` reads it (returns in the lidar frame, up from the ground's
            fit), labelled by scanmc in worker processes, chunk by chunk: a dataset folder
  network/  the checkpoint's network fine-tuned on those labels (`l3e train --init`)
  model.pt  the constraint layer refitted on them, thresholds chosen on them, and the provenance:
            the base checkpoint, the scans, their sensor, the place's name

A model adapted on a place is scored on other places of its family, never on the scans it was adapted
on: `l3e evaluate` leaves its place out of every dataset it scores.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from l3e_env.config import LidarConfig, from_dict, plain, settings_changed
from l3e_env.config.labelling import LABEL_PROTOCOL, LabelConfig, RegistrationConfig, ScanMCConfig
from l3e_env.core.files import folder_lock, npy_writer, write_atomic
from l3e_env.core.transforms import level_rotation_of
from l3e_env.core.workers import ordered_map
from l3e_env.data.dataset import ARRAYS, FORMAT_VERSION, LabelDataset, label_statistics
from l3e_env.io.ouster import is_capture
from l3e_env.io.recorded import RecordedScan
from l3e_env.io.recordings import read_recording
from l3e_env.io.scan_files import FORMATS
from l3e_env.localizability.registration import RegistrationError
from l3e_env.localizability.scan_mc import ScanPatternError, scan_errors
from l3e_env.model.classifier import (
    DEFAULT_CHECKPOINT,
    load_checkpoint,
    model_from_checkpoint,
    save_checkpoint,
    torch_device,
)
from l3e_env.model.scores import best_thresholds
from l3e_env.model.training import (
    TrainConfig,
    network_config,
    predict_dataset,
    symmetric_thresholds,
    train,
    with_fitted_layer,
)
from l3e_env.sim.patterns import BeamPattern, get_pattern, register_pattern

from .judge import LevelledScan, level_pose, read_levelled, recognise_sensor

MIN_SCANS = 20  # labelled scans a fine-tune needs at the least
CHUNK = 4  # scans a worker labels at a time: the unit of resumption


class AdaptError(ValueError):
    """Scans that cannot adapt a checkpoint (none, too few, another sensor's) or a run folder of
    another adaptation; the message says why and what to do."""


@dataclass(frozen=True)
class AdaptOptions:
    checkpoint: str | None = None  # None: the shipped model
    sensor: str | None = None  # None: a recording's own, else the one recognised from the scans
    place: str | None = None  # the place's name among the model's training scenes (None: the source's name)
    every: int = 1  # of a recording, every k-th scan
    max_scans: int = 240  # at most this many scans (a folder's spread evenly, a recording's first)
    children: int = ScanMCConfig.children  # scanmc's at most, per scan
    epochs: int = 6
    samples_per_epoch: int = 160
    learning_rate: float = 3e-4
    workers: int = 2
    seed: int = 0
    device: str = "cpu"
    # labelled datasets whose scans of the base's own training places are replayed beside the place's
    # (TrainConfig.replay_scenes), as `replay_share` of each epoch: () fine-tunes on the place alone
    replay: tuple[str, ...] = ()
    replay_share: float = 0.5


@dataclass
class AdaptResult:
    checkpoint: Path
    scans: int  # read
    labelled: int  # labelled by scanmc and learnt
    skipped: list[str] = field(default_factory=list)  # scans that could not be read or labelled, and why
    statistics: dict[str, Any] = field(default_factory=dict)  # the labels' positive rate per axis
    seconds: dict[str, float] = field(default_factory=dict)


def adapt(
    source: str | Path, out: str | Path, options: AdaptOptions = AdaptOptions(), progress: bool = True
) -> AdaptResult:
    """Adapt a checkpoint to the place whose scans `source` holds (a folder of scan files, an Ouster
    capture or a ROS bag) into the run folder `out`; resumes an interrupted run there, and answers a
    finished one's result without training again."""
    torch_device(options.device)  # a missing GPU is named first
    checkpoint = Path(options.checkpoint or DEFAULT_CHECKPOINT)
    base = load_checkpoint(checkpoint)
    out = Path(out)
    place = options.place or Path(source).stem
    with folder_lock(out):
        _open_run(out, _run_settings(source, checkpoint, None, place, options), create=False)  # before reading
        scans, skipped = _read(source, options)
        pattern = _sensor(scans, options.sensor, base, checkpoint)
        _open_run(out, _run_settings(source, checkpoint, pattern, place, options))
        t0 = time.perf_counter()
        data, failed = _labelled(out / "labels", scans, pattern, place, base, options, progress)
        seconds = {"labelling": time.perf_counter() - t0}
        if len(data) < MIN_SCANS:
            raise AdaptError(f"scanmc could label {len(data)} of the {len(scans)} scans; a fine-tune needs {MIN_SCANS}")
        if not (out / "model.pt").is_file():  # written last: where it is, this run (same settings) has finished
            provenance = {
                "base": str(checkpoint),
                "base_sha256": hashlib.sha256(checkpoint.read_bytes()).hexdigest(),
                "source": str(Path(source).resolve()),
                "place": place,
                "sensor": pattern.name,
                "scans": len(scans),
                "labelled": len(data),
                "labeller": f"scanmc:{options.children}",
                "epochs": options.epochs,
                "date": time.strftime("%Y-%m-%d"),
            }
            seconds.update(_train(out, checkpoint, base, data, provenance, options, progress))
    stats = label_statistics(data.labels)["positive_rate"]
    return AdaptResult(out / "model.pt", len(scans), len(data), skipped + failed, stats, seconds)


def _train(
    out: Path,
    checkpoint: Path,
    base: dict[str, Any],
    data: LabelDataset,
    provenance: dict[str, Any],
    options: AdaptOptions,
    progress: bool,
) -> dict[str, float]:
    """The fine-tune and the refitted layer of a run whose scans are labelled (`data`), into
    out/model.pt; the seconds each took."""
    t0 = time.perf_counter()
    network = _fine_tune(out / "labels", out / "network", checkpoint, base, provenance["place"], options, progress)
    seconds = {"fine-tuning": time.perf_counter() - t0}
    t0 = time.perf_counter()
    _finish(out / "model.pt", network, base, data, provenance, options, progress)
    seconds["layer"] = time.perf_counter() - t0
    return seconds


def _sources(source: Path, options: AdaptOptions) -> list[str | Path | RecordedScan]:
    """The scans of a folder (spread evenly over its files, at most max_scans) or a recording."""
    if source.is_dir():
        files = sorted(p for p in source.iterdir() if p.suffix.lower() in FORMATS)
        if not files:
            raise AdaptError(f"{source} holds no scan files ({' '.join(FORMATS)}): give the folder of a place's scans")
        keep = np.unique(np.linspace(0, len(files) - 1, min(len(files), options.max_scans)).round().astype(int))
        return [files[i] for i in keep]
    if not source.exists():
        raise AdaptError(f"no folder, capture or bag at {source}")
    if source.suffix.lower() in FORMATS and not is_capture(source):
        raise AdaptError(f"{source} is one scan: give the folder of the place's scans (at least {MIN_SCANS})")
    return list(islice(read_recording(source, every=options.every, one_sensor=True), options.max_scans))


def _read(source: str | Path, options: AdaptOptions) -> tuple[list[LevelledScan], list[str]]:
    """Every scan read and levelled as `l3e judge` reads it (the sensor given, else a recording's own or
    the one recognised from the first scans); the ones that cannot be, named."""
    sources = _sources(Path(source), options)
    sensor = get_pattern(options.sensor) if options.sensor else recognise_sensor(iter(sources))[1]
    scans, skipped = [], []
    for item in sources:
        scan = read_levelled(item, sensor, options.sensor is not None, None, True)
        if scan.error is not None:
            skipped.append(scan.error)
        else:
            scans.append(scan)
    if len(scans) < MIN_SCANS:
        raise AdaptError(
            f"{source}: {len(scans)} readable scans ({len(skipped)} not); a fine-tune needs at least {MIN_SCANS} "
            "of the place (more spread over it adapt better)"
            + (f". The first refused: {skipped[0]}" if skipped else "")
        )
    return scans, skipped


def _sensor(scans: list[LevelledScan], given: str | None, base: dict[str, Any], checkpoint: Path) -> BeamPattern:
    """The scans' one sensor, which the checkpoint must have been trained on; AdaptError naming both otherwise."""
    names = sorted({s.pattern.name for s in scans if s.pattern is not None})
    if not names:
        raise AdaptError("the scans' sensor could not be recognised from their returns: give it with --sensor")
    if len(names) > 1:
        raise AdaptError(f"the scans come from several sensors ({', '.join(names)}): adapt on one sensor's scans")
    trained = base.get("sensors") or [(base.get("lidar") or {}).get("model")]
    if names[0].removesuffix("-calibrated") not in trained:
        raise AdaptError(
            f"the scans are {names[0]} scans and {checkpoint} learnt {', '.join(map(str, trained))} scans: adapt a "
            "checkpoint trained on this sensor (--checkpoint), or name the sensor with --sensor if it was misread"
        )
    return next(s.pattern for s in scans if s.pattern is not None)  # type: ignore[return-value]


def _run_settings(
    source: str | Path, checkpoint: Path, pattern: BeamPattern | None, place: str, options: AdaptOptions
) -> dict:
    """What a resumed run must share with the first: all but the workers and the device (and the
    sensor, where its scans are not read yet: `pattern` None)."""
    settings = {k: v for k, v in dataclasses.asdict(options).items() if k not in ("workers", "device", "sensor")}
    where = {"source": str(Path(source).resolve()), "base": str(checkpoint.resolve())}
    sensor = {} if pattern is None else {"sensor": pattern.name}
    return plain({**settings, **where, **sensor, "place": place})


def _open_run(out: Path, settings: dict, create: bool = True) -> None:
    """Check that the run folder holds a run of the same settings (to resume), or create it (`create`);
    settings without a sensor are checked against the folder's less its sensor."""
    path = out / "adapt.json"
    if path.exists():
        before = json.loads(path.read_text())
        if "sensor" not in settings:
            before.pop("sensor", None)
        if before != settings:
            raise AdaptError(
                f"{out} holds another adaptation ({settings_changed(before, settings)}); choose another folder"
            )
        return
    if not create:
        return
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(path, lambda fh: fh.write(json.dumps(settings, indent=1).encode()))


@dataclass
class _Labeller:
    """What a worker labels scans with (a pattern of a recording's own is registered in the worker)."""

    pattern: BeamPattern
    registration: RegistrationConfig
    labels: LabelConfig
    scan_mc: ScanMCConfig
    seed: int

    def __post_init__(self) -> None:
        register_pattern(self.pattern)


def _label_chunk(
    labeller: _Labeller, chunk: list[tuple[int, np.ndarray, np.ndarray | None]]
) -> list[np.ndarray | None]:
    """scanmc's errors of each scan of a chunk, seeded by the scan's place in the run; None where it cannot judge it."""
    found: list[np.ndarray | None] = []
    lidar = LidarConfig(model=labeller.pattern.name)
    for index, points, up in chunk:
        rng = np.random.default_rng([labeller.seed, index])
        try:
            R_l_s = level_rotation_of(level_pose(up))
            found.append(
                scan_errors(points, lidar, labeller.registration, labeller.labels, labeller.scan_mc, rng, R_l_s).errors
            )
        except (RegistrationError, ScanPatternError):
            found.append(None)
    return found


def _labelled(
    folder: Path,
    scans: list[LevelledScan],
    pattern: BeamPattern,
    place: str,
    base: dict[str, Any],
    options: AdaptOptions,
    progress: bool,
) -> tuple[LabelDataset, list[str]]:
    """The scans labelled by scanmc as a dataset folder (each finished chunk kept: a rerun resumes)."""
    labels = base.get("labels") or {}  # a model of several datasets holds each one's: their thresholds are one
    labeller = _Labeller(
        pattern,
        from_dict(RegistrationConfig, base.get("registration") or {}),
        from_dict(LabelConfig, labels[0] if isinstance(labels, list) else labels),
        replace(ScanMCConfig(), children=options.children),
        options.seed,
    )
    shards = folder / "shards"
    shards.mkdir(parents=True, exist_ok=True)
    chunks = [list(range(i, min(i + CHUNK, len(scans)))) for i in range(0, len(scans), CHUNK)]
    todo = [k for k in range(len(chunks)) if not (shards / f"chunk-{k:05d}.npy").exists()]
    done = len(scans) - sum(len(chunks[k]) for k in todo)
    bar = tqdm(total=len(scans), initial=done, desc="labelling scans by scanmc", unit="scan", disable=not progress)
    jobs = ([(i, scans[i].points, scans[i].up) for i in chunks[k]] for k in todo)
    args = (labeller.pattern, labeller.registration, labeller.labels, labeller.scan_mc, labeller.seed)
    for k, found in zip(todo, ordered_map(_label_chunk, jobs, None, _Labeller, args, options.workers)):
        rows = np.array([np.full(6, np.nan) if f is None else f for f in found], dtype=np.float64)
        write_atomic(shards / f"chunk-{k:05d}.npy", npy_writer(rows))
        bar.update(len(found))
    bar.close()
    errors = np.concatenate([np.load(shards / f"chunk-{k:05d}.npy") for k in range(len(chunks))])
    kept = np.flatnonzero(np.isfinite(errors).all(axis=1))
    judged = set(kept.tolist())
    failed = [f"{scans[i].name}: scanmc cannot judge it" for i in range(len(scans)) if i not in judged]
    _write_dataset(folder, [scans[i] for i in kept], errors[kept], labeller, place)
    return LabelDataset(folder), failed


def _write_dataset(
    folder: Path, scans: list[LevelledScan], errors: np.ndarray, labeller: _Labeller, place: str
) -> None:
    """The labelled scans in the dataset format (`data.dataset`), labelled by their own estimate."""
    thresholds = labeller.labels.threshold_vector()
    arrays: dict[str, np.ndarray] = {
        "points": np.concatenate([s.points for s in scans]).astype(np.float32),
        "offsets": np.concatenate([[0], np.cumsum([len(s.points) for s in scans])]).astype(np.int64),
        "poses": np.array([level_pose(s.up) for s in scans], dtype=np.float64),
        "errors": errors.astype(np.float32),
        "labels": (errors > thresholds).astype(np.uint8),
        "scene": np.zeros(len(scans), dtype=np.int16),
        "children_failed": np.zeros(len(scans), dtype=np.int32),
    }
    assert set(arrays) == set(ARRAYS)
    for name, array in arrays.items():
        write_atomic(folder / f"{name}.npy", npy_writer(array))
    settings = {
        "scenes": [place],
        "seed": labeller.seed,
        "lidar": dataclasses.asdict(LidarConfig(model=labeller.pattern.name)),
        "labels": dataclasses.asdict(labeller.labels),
        "registration": dataclasses.asdict(labeller.registration),
        "labeller": "scan",
        "scan_mc": dataclasses.asdict(labeller.scan_mc),
    }
    manifest = {
        "format_version": FORMAT_VERSION,
        "protocol": LABEL_PROTOCOL,
        "settings": plain(settings),
        "complete": True,
        "count": len(scans),
        "scenes": [place],
        "sensor": labeller.pattern.name,
        "statistics": label_statistics(arrays["labels"]),
    }
    write_atomic(folder / "manifest.json", lambda fh: fh.write(json.dumps(manifest, indent=1).encode()))


def _fine_tune(
    labels: Path,
    folder: Path,
    checkpoint: Path,
    base: dict[str, Any],
    place: str,
    options: AdaptOptions,
    progress: bool,
) -> Path:
    """The checkpoint's network fine-tuned (into `folder`) on the place's labelled scans, by its own recipe."""
    recipe = {**(base.get("training") or {})}
    for key in ("init", "train_scenes", "validation_scenes", "epochs", "samples_per_epoch", "learning_rate"):
        recipe.pop(key, None)
    network = network_config(model_from_checkpoint(base, str(checkpoint)).config)
    replayed = _replayed_scenes(base, options.replay)
    cfg = from_dict(
        TrainConfig,
        {
            **recipe,
            "model": plain(dataclasses.asdict(network)),
            "init": str(checkpoint),
            "epochs": options.epochs,
            "samples_per_epoch": options.samples_per_epoch,
            "learning_rate": options.learning_rate,
            "train_scenes": [place, *replayed],
            "replay_scenes": replayed,
            "replay_share": options.replay_share,
            "validation_scenes": [],
            "group_dro": 0.0,  # one place: no families to weigh
            "seed": options.seed,
        },
    )
    train([labels, *options.replay], folder, cfg, progress=progress, device=options.device)
    return folder / "model.pt"


def _replayed_scenes(base: dict[str, Any], replay: tuple[str, ...]) -> list[str]:
    """The base's own training places among the replay datasets' scenes (what it learnt, replayed);
    AdaptError where the datasets hold none of them."""
    if not replay:
        return []
    learnt = (base.get("training") or {}).get("train_scenes") or []
    held = [s for folder in replay for s in LabelDataset(folder).manifest["scenes"]]
    found = [s for s in dict.fromkeys(held) if s in learnt]
    if not found:
        raise AdaptError(f"the replay datasets {list(replay)} hold none of the base model's training places")
    return found


def _finish(
    path: Path,
    network: Path,
    base: dict[str, Any],
    data: LabelDataset,
    provenance: dict[str, Any],
    options: AdaptOptions,
    progress: bool,
) -> None:
    """model.pt: the fine-tuned network with the base's constraint layer refitted on the place's labels
    (where the base has one), thresholds chosen on them, and where it came from."""
    tuned = load_checkpoint(network)
    model = model_from_checkpoint(tuned, str(network))
    base_config = model_from_checkpoint(base, "the base checkpoint").config
    rows = np.arange(len(data))
    if base_config.constraints:
        layer = (tuple(base_config.constraint_levels), base_config.frame)
        model, _ = with_fitted_layer(model, data, rows, options.seed, layer, progress)
    beta = float(base.get("threshold_beta", 1.0))
    thresholds = best_thresholds(data.labels, predict_dataset(model, data, rows, options.seed), beta=beta)
    symmetric = symmetric_thresholds(model, data, rows, options.seed, beta, progress)
    state_only = ("format", "version", "model", "state_dict", "thresholds", "optimizer", "scheduler", "best")
    meta = {k: v for k, v in tuned.items() if k not in (*state_only, "symmetric_thresholds", "epoch", "group_weights")}
    meta.update(threshold_beta=beta, adapted=provenance)
    save_checkpoint(path, model, thresholds, meta, {"symmetric_thresholds": [float(t) for t in symmetric]})


def describe(result: AdaptResult) -> Iterator[str]:
    """What `l3e adapt` prints of a result."""
    yield f"adapted on {result.labelled} of {result.scans} scans -> {result.checkpoint}"
    rates = "  ".join(f"{axis} {rate:.2f}" for axis, rate in result.statistics.items())
    yield f"scanmc's labels, non-localizable rate per axis: {rates}"
    yield "seconds: " + ", ".join(f"{step} {s:.0f}" for step, s in result.seconds.items())
    if result.skipped:
        yield f"{len(result.skipped)} scans left out; the first: {result.skipped[0]}"
