"""Reading datasets: a finished dataset folder through memory maps, several read as one, and
their labels' statistics; no simulation is needed (generation makes them: `generation`).

Layout of a dataset folder:
  manifest.json          settings, package versions, seeds, counts, label statistics
  shards/<scene>-<k>.npz one finished shard (written to a temporary name, then renamed)
  points.npy offsets.npy poses.npy errors.npy labels.npy scene.npy children_failed.npy
                         consolidated arrays, opened with numpy's mmap_mode="r" for training;
                         scan i is points[offsets[i]:offsets[i+1]]
"""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from l3e_env.config import LidarConfig, from_dict, settings_changed, with_defaults
from l3e_env.config.labelling import AXES, LABEL_PROTOCOL, LabelConfig, RegistrationConfig, protocol_name

FORMAT_VERSION = 1
ARRAYS = ("points", "offsets", "poses", "errors", "labels", "scene", "children_failed")


class DatasetError(RuntimeError):
    """A dataset folder that cannot be written, resumed or read; the message says why."""


def remake_command(manifest: dict[str, Any], folder: Path) -> str:
    """The command that labels a manifest's scenes and parents again, into a folder beside it."""
    settings = manifest.get("settings") or {}
    scenes = ",".join(settings.get("scenes") or ["..."])
    level = " --preset level" if (settings.get("labels") or {}).get("heading") == "path" else ""
    return (
        f"l3e dataset generate --out {folder}-p{LABEL_PROTOCOL}{level} --scenes {scenes} "
        f"--parents {settings.get('parents_per_scene', '...')} --seed {settings.get('seed', 0)}"
    )


def check_protocol(manifest: dict[str, Any], folder: Path, what: str) -> None:
    """DatasetError naming the protocol and the command that remakes a dataset labelled under
    another label protocol than this version's."""
    protocol = manifest.get("protocol", 1)
    if protocol != LABEL_PROTOCOL:
        raise DatasetError(
            f"{folder} was labelled under {protocol_name(protocol)}; this version labels under "
            f"{protocol_name(LABEL_PROTOCOL)}, and cannot {what}. Label it again: "
            f"{remake_command(manifest, folder)}"
        )


def label_statistics(labels: np.ndarray) -> dict[str, Any]:
    """Positive rate per axis and the histogram of the 64 label combinations (bit i = axis i)."""
    labels = np.asarray(labels, dtype=np.uint8).reshape(-1, 6)
    codes = (labels.astype(np.int64) << np.arange(6)).sum(axis=1)
    hist = np.bincount(codes, minlength=64)
    return {
        "positive_rate": {a: float(labels[:, i].mean()) if len(labels) else 0.0 for i, a in enumerate(AXES)},
        "powerset_histogram": {combo_name(c): int(n) for c, n in enumerate(hist) if n},
    }


def combo_name(code: int) -> str:
    flagged = [a for i, a in enumerate(AXES) if code >> i & 1]
    return "+".join(flagged) if flagged else "none"


def format_statistics(stats: dict[str, Any]) -> str:
    rate = "  ".join(f"{a} {v:.2f}" for a, v in stats["positive_rate"].items())
    combos = sorted(stats["powerset_histogram"].items(), key=lambda kv: -kv[1])
    lines = [f"non-localizable rate per axis: {rate}", "label combinations (most common first):"]
    lines += [f"  {n:6d}  {name}" for name, n in combos]
    return "\n".join(lines)


def _refuse(where: Path, problems: list[str]) -> None:
    if problems:
        raise DatasetError(
            f"{where}: {'; '.join(problems)}; the dataset is damaged or not this version's: generate it again"
        )


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _thresholds_problem(labels: Any) -> str | None:
    parts = labels if isinstance(labels, list) else [labels]
    for part in parts:
        t = part.get("thresholds") if isinstance(part, dict) else None
        ok = isinstance(t, list) and len(t) == 6 and all(isinstance(v, (int, float)) and v > 0 for v in t)
        if not ok:
            return f"settings.labels.thresholds must be six positive numbers, not {t!r}"
    return None


def _settings_problems(settings: dict[str, Any]) -> list[str]:
    """The manifest's settings read as the generation's config, each field against its type, and the
    values no run can use (`generation.value_problems`)."""
    from .generation import DatasetConfig, value_problems  # generation imports this module

    try:
        config = from_dict(DatasetConfig, {k: v for k, v in settings.items() if k != "mesh_sha256"})
    except (TypeError, ValueError) as exc:
        return [f"settings: {exc}"]
    return [f"settings.{problem}" for problem in value_problems(config)]


def manifest_problems(manifest: dict[str, Any]) -> list[str]:
    """What a finished dataset's manifest.json holds that this version cannot read (its schema)."""
    problems = []
    if manifest.get("format_version", FORMAT_VERSION) != FORMAT_VERSION:
        problems.append(f"format_version {manifest.get('format_version')!r} (this version reads {FORMAT_VERSION})")
    settings = manifest.get("settings")
    if not isinstance(settings, dict):
        return [*problems, f"settings must be a mapping, not {settings!r}"]
    for key in ("lidar", "registration"):
        if not isinstance(settings.get(key), dict):
            problems.append(f"settings.{key} must be a mapping, not {settings.get(key)!r}")
    if isinstance(settings.get("lidar"), dict) and not isinstance(settings["lidar"].get("model"), str):
        problems.append(f"settings.lidar.model must be a sensor's name, not {settings['lidar'].get('model')!r}")
    if (problem := _thresholds_problem(settings.get("labels"))) is not None:
        problems.append(problem)
    problems += _settings_problems(settings)
    scenes = manifest.get("scenes")
    if not isinstance(scenes, list) or not scenes or not all(isinstance(s, str) for s in scenes):
        problems.append(f"scenes must be a list of scene names, not {scenes!r}")
    if not _is_int(manifest.get("count")) or manifest["count"] < 0:
        problems.append(f"count must be a whole number of scans, not {manifest.get('count')!r}")
    return problems


def array_problems(arrays: dict[str, np.ndarray], manifest: dict[str, Any]) -> list[str]:
    """What the arrays hold that no generation writes: shapes, types, labels other than 0 and 1,
    offsets or scene indices out of range (each a pass over the small arrays; the points are not read)."""
    n, scenes = manifest["count"], len(manifest["scenes"])
    expected = {
        "labels": ((n, 6), "iub"),
        "errors": ((n, 6), "f"),
        "poses": ((n, 4, 4), "f"),
        "offsets": ((n + 1,), "iu"),
        "scene": ((n,), "iu"),
        "children_failed": ((n,), "iu"),
    }
    problems = [
        f"{k}.npy is {a.dtype} {a.shape}, not {shape} of {kinds}"
        for k, (shape, kinds) in expected.items()
        if (a := arrays[k]).shape != shape or a.dtype.kind not in kinds
    ]
    points = arrays["points"]
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind != "f":
        problems.append(f"points.npy is {points.dtype} {points.shape}, not (M, 3) floats")
    if problems:  # the checks below read these arrays
        return problems
    labels, offsets, scene = np.asarray(arrays["labels"]), np.asarray(arrays["offsets"]), np.asarray(arrays["scene"])
    if not np.isin(labels, (0, 1)).all():
        others = sorted({float(v) for v in np.unique(labels)} - {0.0, 1.0})[:5]
        problems.append(f"labels.npy holds values other than 0 and 1: {[f'{v:g}' for v in others]}")
    if not (np.isfinite(arrays["errors"]).all() and np.isfinite(arrays["poses"]).all()):
        problems.append("errors.npy or poses.npy holds NaN or infinite values")
    if n and (offsets[0] != 0 or offsets[-1] != len(points) or (np.diff(offsets) < 0).any()):
        problems.append(f"offsets.npy does not cut the {len(points)} points into scans (from 0, rising, to the end)")
    if n and (scene.min() < 0 or scene.max() >= scenes):
        problems.append(f"scene.npy holds indices outside the manifest's {scenes} scenes")
    return problems


class LabelDataset:
    """Random access to a finished dataset through memory maps."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        path = self.folder / "manifest.json"
        if not path.exists():
            raise DatasetError(f"{self.folder} is not a dataset (no manifest.json)")
        try:
            self.manifest = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{path} cannot be read ({exc}); the dataset is damaged: generate it again") from exc
        if not isinstance(self.manifest, dict):
            raise DatasetError(
                f"{path} holds a JSON {type(self.manifest).__name__}, not a dataset's manifest (a mapping): "
                "the dataset is damaged: generate it again"
            )
        if not self.manifest.get("complete"):
            raise DatasetError(f"{self.folder}: generation has not finished; run the same command again to resume")
        check_protocol(self.manifest, self.folder, "read it")
        _refuse(self.folder / "manifest.json", manifest_problems(self.manifest))
        self.arrays = {}
        for k in ARRAYS:
            try:
                self.arrays[k] = np.load(self.folder / f"{k}.npy", mmap_mode="r", allow_pickle=False)
            except (OSError, ValueError, EOFError) as exc:
                raise DatasetError(
                    f"{self.folder / f'{k}.npy'} cannot be read ({exc}); the dataset is damaged: generate it again"
                ) from exc
        _refuse(self.folder, array_problems(self.arrays, self.manifest))

    def __len__(self) -> int:
        return len(self.arrays["labels"])

    def scan(self, i: int) -> np.ndarray:
        """Scan i's points; DatasetError naming the file and the scan where they are not all finite
        (the opening checks leave the points unread)."""
        o = self.arrays["offsets"]
        points = np.asarray(self.arrays["points"][o[i] : o[i + 1]])
        if not np.isfinite(points).all():
            raise DatasetError(
                f"{self.folder / 'points.npy'}: scan {i} holds NaN or infinite coordinates, which no generation "
                "writes: the dataset is damaged; generate it again"
            )
        return points

    @property
    def name(self) -> str:
        return self.folder.name

    @property
    def parts(self) -> list[LabelDataset]:
        """The datasets read as this one: itself (a DatasetUnion has several)."""
        return [self]

    def locate(self, i: int) -> tuple[LabelDataset, int]:
        """The dataset holding row i, and the row there: itself (a DatasetUnion has several)."""
        return self, i

    @property
    def labels(self) -> np.ndarray:
        return np.asarray(self.arrays["labels"])

    @property
    def errors(self) -> np.ndarray:
        return np.asarray(self.arrays["errors"])

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) world-from-sensor poses of the parent scans."""
        return np.asarray(self.arrays["poses"])

    @property
    def labeller(self) -> str:
        """Where the errors come from (LABELLERS): "scan" for a distillation set."""
        return str(self.manifest["settings"].get("labeller", "scene"))

    @property
    def label_config(self) -> LabelConfig:
        """The label settings the dataset was made with (its thresholds turn errors into labels)."""
        return from_dict(LabelConfig, self.manifest["settings"]["labels"])


def comparable_settings(manifest: dict[str, Any], key: str) -> dict[str, Any]:
    """A manifest's lidar or registration settings with every option it predates at its default: a
    dataset made before an option existed (the LiDAR's `sweep`) was made as that default makes it."""
    return with_defaults({"lidar": LidarConfig, "registration": RegistrationConfig}[key], manifest["settings"][key])


class DatasetUnion:
    """Datasets of one sensor and one registration read as one, e.g. the paper's poses and the
    level operating poses of the same scenes: scenes matched by name, rows in the given order.
    Offers what training and evaluation read of a LabelDataset. `mixed_sensors`: the parts may come
    from different sensors (a network trained on several beam patterns), one registration still."""

    def __init__(self, folders: list[str | Path], mixed_sensors: bool = False):
        self.parts = [LabelDataset(f) for f in folders]
        first = self.parts[0].manifest
        for part in self.parts[1:]:
            for key in ("registration",) if mixed_sensors else ("lidar", "registration"):
                ours, theirs = comparable_settings(first, key), comparable_settings(part.manifest, key)
                if theirs != ours:
                    raise DatasetError(
                        f"{part.folder} and {self.parts[0].folder} differ in their {key} settings "
                        f"({settings_changed(ours, theirs)}): they cannot be trained on together"
                    )
        names: list[str] = []
        for part in self.parts:
            names += [s for s in part.manifest["scenes"] if s not in names]
        scene = [
            np.array([names.index(s) for s in p.manifest["scenes"]], dtype=np.int16)[np.asarray(p.arrays["scene"])]
            for p in self.parts
        ]
        self.folder = self.parts[0].folder
        self.manifest = {
            **first,
            "scenes": names,
            "settings": {
                **first["settings"],
                "labels": [p.manifest["settings"]["labels"] for p in self.parts],
                "seed": [p.manifest["settings"]["seed"] for p in self.parts],
            },
        }
        self.arrays = {"scene": np.concatenate(scene)}
        self._starts = np.cumsum([0] + [len(p) for p in self.parts])
        self.manifest.update(count=len(self), statistics=label_statistics(self.labels))

    @property
    def name(self) -> str:
        return "+".join(p.name for p in self.parts)

    def __len__(self) -> int:
        return int(self._starts[-1])

    def locate(self, i: int) -> tuple[LabelDataset, int]:
        """The part holding row i, and the row there."""
        k = int(np.searchsorted(self._starts, i, side="right")) - 1
        return self.parts[k], i - int(self._starts[k])

    def scan(self, i: int) -> np.ndarray:
        part, row = self.locate(i)
        return part.scan(row)

    @cached_property  # read many times per epoch; the parts do not change once opened
    def labels(self) -> np.ndarray:
        return np.concatenate([p.labels for p in self.parts])

    @cached_property
    def errors(self) -> np.ndarray:
        return np.concatenate([p.errors for p in self.parts])

    @cached_property
    def poses(self) -> np.ndarray:
        return np.concatenate([p.poses for p in self.parts])


def row_thresholds(data: LabelDataset | DatasetUnion) -> np.ndarray:
    """(N, 6) each row's own label thresholds (the parts of a union may differ)."""
    return np.concatenate([np.tile(p.label_config.threshold_vector(), (len(p), 1)) for p in data.parts])


def error_ratios(data: LabelDataset | DatasetUnion) -> np.ndarray:
    """(N, 6) mean registration errors over each row's own label thresholds: above 1 is a
    positive label."""
    return data.errors / row_thresholds(data)


def scan_labelled(data: LabelDataset | DatasetUnion) -> np.ndarray:
    """(N,) bool: the rows labelled by their scan's own estimate (a distillation set's), not in the scene."""
    return np.concatenate([np.full(len(p), p.labeller == "scan") for p in data.parts])


def check_ground_truth(data: LabelDataset | DatasetUnion, use: str) -> None:
    """DatasetError where a dataset (or a part of one) holds a distillation set's labels, which are an
    estimate and no ground truth to `use` against."""
    for part in data.parts:
        if part.labeller == "scan":
            raise DatasetError(
                f"{part.folder} is labelled by each scan's own estimate (a distillation set, for "
                f"training): it is no ground truth to {use}. Give datasets labelled in the scene "
                "(`l3e dataset generate` without --labeller scan)"
            )


def open_datasets(folders: str | Path | list[str | Path], mixed_sensors: bool = False) -> LabelDataset | DatasetUnion:
    """One dataset folder, or several read as one (of several sensors where `mixed_sensors`)."""
    if isinstance(folders, (str, Path)):
        return LabelDataset(folders)
    if not folders:
        raise DatasetError("no dataset folder given")
    return LabelDataset(folders[0]) if len(folders) == 1 else DatasetUnion(list(folders), mixed_sensors)


def sensors_of(data: LabelDataset | DatasetUnion) -> list[str]:
    """The sensors whose scans a dataset holds, in the order of its parts."""
    return list(dict.fromkeys(str(p.manifest["settings"]["lidar"]["model"]) for p in data.parts))
