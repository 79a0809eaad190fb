"""Table III for this project: per-axis scores of trained classifiers, and of the eigenvalue
detector they replace, on the train, validation and test splits (and on whole datasets of another
sensor or of unseen families), with PR curves per axis."""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from l3e_env.config import from_dict
from l3e_env.core.files import new_folder
from l3e_env.core.transforms import level_rotation_of
from l3e_env.data.dataset import DatasetUnion, LabelDataset, check_ground_truth, open_datasets, row_thresholds
from l3e_env.data.scan_estimates import dataset_scan_errors
from l3e_env.detection.detectors import near_threshold
from l3e_env.localizability.degeneracy import PlaneRows, drpm_mask, scan_rows, xicp_mask
from l3e_env.localizability.labels import AXES
from l3e_env.localizability.registration import (
    RegistrationConfig,
    RegistrationError,
    dcreg_mask,
    eigen_mask,
    hessian_in_level,
    scan_hessian,
)
from l3e_env.localizability.scan_mc import ScanMCConfig
from l3e_env.model.classifier import Classifier, load_checkpoint
from l3e_env.model.scores import (
    MIN_POSITIVES,
    axis_scores,
    best_thresholds,
    format_table,
    mean_interval,
    mean_scores,
    micro_f1,
    pr_curve,
)
from l3e_env.model.training import predict_dataset, split_indices
from scenes import TEST_SCENES, is_mesh_path, make_scene, scene_family


def model_name(classifier: Classifier, path: Path, taken: set[str]) -> str:
    """The architecture, with the run folder's name where two models share it."""
    name = classifier.model.config.architecture
    return name if name not in taken else f"{name}:{path.parent.name}/{path.stem}"


def test_scenes_in(data: LabelDataset | DatasetUnion) -> list[str]:
    """The test families that the dataset holds."""
    return [s for s in TEST_SCENES if s in data.manifest["scenes"]]


def family_rows(data: LabelDataset | DatasetUnion, rows: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The positions in `rows` (default: every row) of each scene family present ('yard': the rows
    of yard-0, yard-1, ...), the families in the order the dataset lists its scenes."""
    names = data.manifest["scenes"]
    scene = np.asarray(data.arrays["scene"], dtype=np.int64)
    of_row = np.array([scene_family(n) for n in names] or [""])[scene if rows is None else scene[rows]]
    return {f: np.flatnonzero(of_row == f) for f in dict.fromkeys(map(scene_family, names)) if (of_row == f).any()}


def region_rows(data: LabelDataset | DatasetUnion, rows: np.ndarray) -> dict[str, np.ndarray]:
    """The positions in `rows` of each named region of a procedural scene ('tunnel of mine-0': the
    parents that stood in the mine's tunnel), regions in the order the scene lists them; a parent
    outside every region is in none."""
    names = data.manifest["scenes"]
    scene = np.asarray(data.arrays["scene"], dtype=np.int64)[rows]
    xy = data.poses[rows][:, :2, 3]
    out: dict[str, np.ndarray] = {}
    for si in dict.fromkeys(scene.tolist()):
        if is_mesh_path(names[si]):
            continue  # a user's mesh names no regions
        built = make_scene(names[si])
        at = np.flatnonzero(scene == si)
        place = np.array([built.region_of(p) or "" for p in xy[at]])
        out.update(
            {f"{region} of {names[si]}": at[place == region] for region in built.regions if (place == region).any()}
        )
    return out


def split_rows(data: LabelDataset | DatasetUnion, training: dict[str, Any]) -> dict[str, np.ndarray]:
    """A checkpoint's train and validation rows (its own scenes) and the test rows (the test
    families that the dataset holds)."""
    return {
        "train": split_indices(data, training["train_scenes"]),
        "valid": split_indices(data, training["validation_scenes"]),
        "test": split_indices(data, test_scenes_in(data)),
    }


@dataclass
class Table3Result:
    """Table III: `results` as results.json holds them (per model and detector, per split), the table's
    text, and the files written."""

    results: dict[str, Any]
    table: str
    written: list[Path]

    @property
    def models(self) -> dict[str, Any]:
        """Per checkpoint and detector: its thresholds and its scores per split."""
        return self.results["models"]


@dataclass
class Table3Options:
    """What `run_table3` scores beside the checkpoints, and how.

    others: datasets scored whole (another sensor, scene families the model never saw: column 'all
    of <folder>'). symmetric: probabilities averaged over the eight mirror/swap views, with the
    thresholds chosen for them. eigen: thresholds tau of the eigenvalue detector, scored on the first
    checkpoint's splits from each scan's own Hessian (`scan_hessian`); a scan too small to register
    flags nothing, as the detector's UNKNOWN does. dcreg: condition ratio thresholds kappa of DCReg's
    detection (registration.dcreg_mask), scored alike. xicp, drpm: thresholds of X-ICP's localizability
    analysis and signal-to-noise factors of DRPM's test (localizability.degeneracy), from each scan's own
    correspondences, scored alike. int8: the ResUNet's convolutions as deployed
    (Classifier.load); False scores them in float32. by_family: each scene family of the test split
    and of an `others` dataset, where it holds several, also gets a column of its own ('mine of
    test'): a mean over families of unlike difficulty hides which one a model fails on. by_region: the
    same for each named region of a scene there ('tunnel of mine-0'). scan_mc: children of the scan's
    own Monte-Carlo estimate (scan_mc.py), scored on the first checkpoint's splits but its training
    split (up to M registrations a scan, over `workers` processes); the estimates are saved in
    scan_mc.npz. draws: each checkpoint also scored on that many draws of the points it reads from a
    scan (seeds 0 ... draws-1; the table is draw 0's): which 4000 points a scan gives moves a split's
    mean F1 by a few hundredths, as much as some differences between models. cascade: margins
    (log-odds) of the first checkpoint checked by the scan estimate where it is unsure
    (detectors.CascadeDetector), scored from the same probabilities and estimates; it needs scan_mc.
    """

    others: list[str | Path] = field(default_factory=list)
    symmetric: bool = False
    eigen: list[float] = field(default_factory=list)
    dcreg: list[float] = field(default_factory=list)
    xicp: list[float] = field(default_factory=list)
    drpm: list[float] = field(default_factory=list)
    int8: bool = True
    device: str = "cpu"  # where the networks run (classifier.torch_device's names); int8 on the CPU only
    by_family: bool = False
    by_region: bool = False
    scan_mc: int = 0
    workers: int = 1
    draws: int = 1
    cascade: list[float] = field(default_factory=list)

    def check(self, checkpoints: list[str | Path], dataset: Any) -> None:
        """ValueError for a combination no run can score, before anything is read or written."""
        if not dataset and not self.others:
            raise ValueError(
                "nothing to score: give the training dataset(s) (--dataset, scored by split), other "
                "datasets (--other, scored whole), or both"
            )
        if dataset and not checkpoints:
            raise ValueError(
                "a dataset is split by a checkpoint's training and validation scenes: give a "
                "checkpoint, or score the dataset whole as an other"
            )
        if any(not v > 0 for v in self.eigen) or any(not v > 1 for v in self.dcreg):
            raise ValueError(
                f"eigen: thresholds tau must be positive, got {self.eigen}; dcreg: condition ratios kappa must "
                f"exceed 1, got {self.dcreg}"
            )
        if any(not v > 0 for v in [*self.xicp, *self.drpm]):
            raise ValueError(f"X-ICP's and DRPM's thresholds must be positive, got {self.xicp} and {self.drpm}")
        if self.draws < 1:
            raise ValueError(f"draws must be at least 1 (the table's own draw), got {self.draws}")
        if self.cascade and not (self.scan_mc and checkpoints):
            raise ValueError(
                "the cascade checks a checkpoint's unsure scans with the scan estimate: give a "
                "checkpoint and --scan-mc M"
            )
        if any(not m >= 0 for m in self.cascade):
            raise ValueError(f"a cascade's margin is a log-odds distance >= 0, got {self.cascade}")
        if self.scan_mc < 0 or self.workers < 1:
            raise ValueError(
                f"the scan estimate needs 0 (none) or more children and at least one worker, got "
                f"{self.scan_mc} and {self.workers}"
            )


Split = tuple[LabelDataset | DatasetUnion, np.ndarray]  # a dataset and the rows of it scored


class Scoreboard:
    """The table being filled: scores, 95% intervals and results.json's entries per model (or
    detector) and column, the PR curves of the checkpoints; a split's family and region columns are
    found once and shared by every model."""

    def __init__(
        self,
        results: dict[str, Any],
        others: dict[str, LabelDataset],
        options: Table3Options,
        seen: set[str] | None = None,
    ):
        self.results, self.others, self.options = results, others, options
        # each other dataset's rows of scenes no checkpoint was adapted on: every detector is scored on
        # these alone, so an adapted model is never scored on the place it was adapted on
        self.other_rows = {column: unseen_rows(d, seen or set()) for column, d in others.items()}
        self.table: dict[str, dict[str, dict[str, np.ndarray]]] = {}
        self.curves: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
        self.intervals: dict[tuple[str, str], dict[str, tuple[float, float]]] = {}
        self._columns: dict[str, dict[str, np.ndarray]] = {}
        # per model, the labels and decisions of each column a test family is scored in (the test
        # split, each other dataset): what the headline pools
        self.decisions: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}

    def add_model(self, name: str, entry: dict[str, Any]) -> None:
        self.table[name] = {}
        self.results["models"][name] = {**entry, "splits": {}}

    def columns(self, split: str, ds: LabelDataset | DatasetUnion, rows: np.ndarray) -> dict[str, np.ndarray]:
        """Column name -> positions in `rows` of each family (of a split of several) and of each
        region, for a test or `others` split, as asked."""
        if split != "test" and split not in self.others:
            return {}
        if split not in self._columns:  # the same rows for every model: scenes are built once
            parts = family_rows(ds, rows) if self.options.by_family else {}
            name = split.removeprefix("all of ")
            columns = {f"{f} of {name}": at for f, at in parts.items()} if len(parts) > 1 else {}
            self._columns[split] = {**columns, **(region_rows(ds, rows) if self.options.by_region else {})}
        return self._columns[split]

    def score(
        self,
        name: str,
        split: str,
        ds: LabelDataset | DatasetUnion,
        rows: np.ndarray,
        predicted: np.ndarray,
        **fields: Any,
    ) -> None:
        """The split's scores, and those of each of its families and regions where asked."""
        parts = {split: np.arange(len(rows)), **self.columns(split, ds, rows)}
        for column, subset in parts.items():
            y = ds.labels[rows[subset]]
            self.table[name][column] = scores = axis_scores(y, predicted[subset])
            self.intervals[name, column] = mean_interval(y, predicted[subset])
            if column == split and (split == "test" or split in self.others):
                self.decisions.setdefault(name, {})[split] = (y, np.asarray(predicted, dtype=bool))
            self.results["models"][name]["splits"][column] = {
                "count": len(subset),
                "dataset": ds.name,
                "sensor": ds.manifest["sensor"],
                **(fields if column == split else {}),
                "mean": mean_scores(scores),
                "micro_f1": micro_f1(y, predicted[subset]),
                "mean_95_interval": self.intervals[name, column],
                **{k: np.asarray(v).tolist() for k, v in scores.items()},
            }


@dataclass
class ScanEstimates:
    """The scan estimate's errors, children drawn and decisions per split it judged."""

    errors: dict[str, np.ndarray] = field(default_factory=dict)
    drawn: dict[str, np.ndarray] = field(default_factory=dict)
    judged: dict[str, np.ndarray] = field(default_factory=dict)


def run_table3(
    checkpoints: list[str | Path],
    dataset: str | Path | list[str | Path] | None,
    out_dir: str | Path,
    options: Table3Options | None = None,
    progress: bool = True,
) -> Table3Result:
    """Score each checkpoint on its own train/validation split and on the test families of the
    dataset, and on every scan of each of `options.others` (see Table3Options for the detectors
    beside them); writes table.txt, results.json and pr_curves.png (and cascade.png with a cascade)
    into out_dir and returns the results, with the table's text and the files written. Without
    `dataset` only the others are scored: how a model does on a user's own scenes needs no training
    data."""
    options = options or Table3Options()
    options.check(checkpoints, dataset)
    data = open_datasets(dataset) if dataset else None
    if data is not None:
        check_ground_truth(data, "score a classifier against (score the training scenes' own datasets)")
    others = other_columns(options.others)
    seen = seen_scenes(checkpoints)
    out = Path(out_dir)
    board = Scoreboard(
        {
            "dataset": data.name if data is not None else None,
            "test_scenes": test_scenes_in(data) if data is not None else [],
            "symmetric": options.symmetric,
            "int8": options.int8,
            "models": {},
            "left_out": {c: sorted(set(d.manifest["scenes"]) & seen) for c, d in others.items()},
        },
        others,
        options,
        seen,
    )
    with new_folder(out):  # a checkpoint refused leaves no folder behind
        first_splits = score_checkpoints(board, checkpoints, data, progress)
    score_hessian_detectors(board, first_splits, progress)
    score_correspondence_detectors(board, first_splits, progress)
    estimates = score_scan_estimate(board, first_splits, out, progress)
    score_cascades(board, first_splits, estimates, out)
    text = table_text(board, estimates)
    written = write_table3(board, text, out)
    return Table3Result(board.results, text, written)


def seen_scenes(checkpoints: list[str | Path]) -> set[str]:
    """The places any of the checkpoints was adapted on (`l3e adapt`): their scans are never scored."""
    places = ((load_checkpoint(path).get("adapted") or {}).get("place") for path in checkpoints)
    return {place for place in places if isinstance(place, str)}


def unseen_rows(data: LabelDataset, seen: set[str]) -> np.ndarray:
    """The rows of a dataset whose scene is not among `seen`."""
    fresh = np.array([name not in seen for name in data.manifest["scenes"]], dtype=bool)
    return np.flatnonzero(fresh[np.asarray(data.arrays["scene"])])


def other_columns(others: list[str | Path]) -> dict[str, LabelDataset]:
    """Each other dataset under its column's name ('all of <name>', the folder where two share a name)."""
    extra: dict[str, LabelDataset] = {}
    for d in map(LabelDataset, others):
        check_ground_truth(d, "score a classifier against")
        extra[f"all of {d.name}" if f"all of {d.name}" not in extra else f"all of {d.folder}"] = d
    return extra


def score_checkpoints(
    board: Scoreboard, checkpoints: list[str | Path], data: LabelDataset | DatasetUnion | None, progress: bool
) -> dict[str, Split]:
    """Every checkpoint scored on its own splits and the others; returns the first one's splits, on
    which the detectors without a checkpoint are scored (the others' alone without a checkpoint)."""
    options = board.options
    first_splits: dict[str, Split] = (
        {} if checkpoints else {column: (d, board.other_rows[column]) for column, d in board.others.items()}
    )
    for path in map(Path, checkpoints):
        clf = Classifier.load(path, symmetric=options.symmetric, int8=options.int8, device=options.device)
        name = model_name(clf, path, set(board.table))
        splits = (
            {}
            if data is None
            else {split: (data, rows) for split, rows in split_rows(data, clf.meta["training"]).items()}
        )
        splits.update({column: (d, board.other_rows[column]) for column, d in board.others.items()})
        splits = {split: (ds, rows) for split, (ds, rows) in splits.items() if len(rows)}
        first_splits = first_splits or splits
        board.add_model(name, {"checkpoint": str(path), "thresholds": clf.thresholds.tolist()})
        board.curves[name] = {}
        for split, (ds, rows) in splits.items():
            if progress:
                print(f"{name}: {split} ({len(rows)} scans)")
            probs = predict_dataset(clf.model, ds, rows, progress=progress, symmetric=options.symmetric)
            board.curves[name][split] = (ds.labels[rows], probs)
            board.score(name, split, ds, rows, probs > clf.thresholds)
            if options.draws > 1:
                board.results["models"][name]["splits"][split]["draws"] = draw_scores(
                    clf, ds, rows, probs, options.draws, progress, options.symmetric
                )
        if "valid" in board.curves[name]:
            parts = {split: board.columns(split, *splits[split]) for split in board.curves[name]}
            board.results["models"][name]["f1_operating_point"] = f1_operating_point(board.curves[name], parts)
    return first_splits


def score_hessian_detectors(board: Scoreboard, first_splits: dict[str, Split], progress: bool) -> None:
    """The eigenvalue test and DCReg at each of their thresholds; one Hessian per scan serves all."""
    eigen, dcreg = board.options.eigen, board.options.dcreg
    if not (eigen or dcreg):
        return
    hessians = {
        split: [H if np.isfinite(H).all() else None for H in dataset_hessians(ds, rows, progress)]
        for split, (ds, rows) in first_splits.items()
    }
    tests = (("eigen", eigen_mask, eigen, "tau"), ("dcreg", dcreg_mask, dcreg, "kappa"))
    score_threshold_tests(board, first_splits, hessians, tests)


def score_correspondence_detectors(board: Scoreboard, first_splits: dict[str, Split], progress: bool) -> None:
    """X-ICP and DRPM at each of their thresholds; one set of correspondences per scan serves all."""
    xicp, drpm = board.options.xicp, board.options.drpm
    if not (xicp or drpm):
        return
    rows = {
        split: [r if r is not None and len(r.points) >= 6 else None for r in dataset_rows(ds, at, progress)]
        for split, (ds, at) in first_splits.items()
    }
    tests = (("xicp", xicp_mask, xicp, "threshold"), ("drpm", drpm_mask, drpm, "threshold"))
    score_threshold_tests(board, first_splits, rows, tests)


def score_threshold_tests(
    board: Scoreboard, first_splits: dict[str, Split], inputs: dict[str, list[Any]], tests: tuple
) -> None:
    """Each (kind, judge, thresholds, name of the threshold) test at each threshold, judging each scan's
    input (`judge(input, threshold)` -> (scores, mask)); a scan without one (too small to register)
    flags nothing, as a detector's UNKNOWN does, and is counted."""
    for kind, judge, values, key in tests:
        for value in values:
            name = f"{kind}:{value:g}"
            board.add_model(name, {key: value})
            for split, (ds, rows) in first_splits.items():
                predicted = np.zeros((len(rows), 6), bool)
                for k, found in enumerate(inputs[split]):
                    if found is not None:
                        predicted[k] = judge(found, value)[1]
                unknown = sum(found is None for found in inputs[split])
                board.score(name, split, ds, rows, predicted, unregistrable=unknown)


def dataset_rows(data: LabelDataset | DatasetUnion, rows: np.ndarray, progress: bool = False) -> list[PlaneRows | None]:
    """Each scan's own point-to-plane rows (degeneracy.scan_rows) with the dataset's registration
    settings; None for a scan too small to register."""
    config = from_dict(RegistrationConfig, data.manifest["settings"]["registration"])
    out: list[PlaneRows | None] = []
    for i in tqdm(rows, desc="correspondences", disable=not progress, leave=False):
        try:
            out.append(scan_rows(data.scan(int(i)), config).turned(level_rotation_of(data.poses[int(i)])))
        except RegistrationError:
            out.append(None)
    return out


def score_scan_estimate(board: Scoreboard, first_splits: dict[str, Split], out: Path, progress: bool) -> ScanEstimates:
    """`scanmc:M` on every split but the training one; its estimates saved in scan_mc.npz."""
    children, found = board.options.scan_mc, ScanEstimates()
    if not children:
        return found
    name = f"scanmc:{children}"
    board.add_model(name, {"children": children})
    for split, (ds, rows) in first_splits.items():
        if split == "train":
            continue
        if progress:
            print(f"{name}: {split} ({len(rows)} scans)")
        found.errors[split], found.drawn[split] = dataset_scan_errors(
            [str(p.folder) for p in ds.parts],
            rows,
            ScanMCConfig(children=children),
            workers=board.options.workers,
            progress=progress,
        )
        known = np.isfinite(found.errors[split]).all(axis=1)
        found.judged[split] = np.where(known[:, None], found.errors[split] > row_thresholds(ds)[rows], False)
        board.score(
            name,
            split,
            ds,
            rows,
            found.judged[split],
            unjudged=int((~known).sum()),
            mean_children=float(found.drawn[split][known].mean()) if known.any() else 0.0,
        )
    stored: dict[str, Any] = {
        **{split.replace(" ", "_"): e for split, e in found.errors.items()},
        **{f"children_{split.replace(' ', '_')}": n for split, n in found.drawn.items()},
    }
    np.savez(out / "scan_mc.npz", **stored)
    return found


def score_cascades(board: Scoreboard, first_splits: dict[str, Split], estimates: ScanEstimates, out: Path) -> None:
    """The first checkpoint checked by the scan estimate within each margin, against random checks of
    as many scans (cascade.png)."""
    margins = board.options.cascade
    if not margins:
        return
    first = next(iter(board.curves))  # the cascade was refused without a checkpoint
    thresholds = np.asarray(board.results["models"][first]["thresholds"])
    for margin in margins:
        name = f"{first}+scanmc:{margin:g}"
        board.add_model(name, {"margin": margin, "children": board.options.scan_mc})
        for split in estimates.errors:
            ds, rows = first_splits[split]
            probs = board.curves[first][split][1]
            checked = near_threshold(probs, thresholds, margin)
            predicted = np.where(checked[:, None], estimates.judged[split], probs > thresholds)
            board.score(name, split, ds, rows, predicted, checked=float(checked.mean()))
    board.results["cascade_random_checks"] = {
        split: random_checks(
            first_splits[split][0].labels[first_splits[split][1]],
            board.curves[first][split][1] > thresholds,
            estimates.judged[split],
        )
        for split in estimates.errors
    }
    plot_cascade(board.results, first, board.options.scan_mc, out / "cascade.png")


def headline(board: Scoreboard) -> dict[str, Any]:
    """Per model, the test families' scores as the classifier is judged: each column's F1 on the axes
    with at least MIN_POSITIVES positives and its micro-F1, and the micro-F1 of every test family's
    decisions pooled, each with its 95% bootstrap interval."""
    out: dict[str, Any] = {}
    for name, columns in board.decisions.items():
        entry: dict[str, Any] = {"columns": {}}
        for column, (y, p) in columns.items():
            interval = board.intervals[name, column]
            support = y.sum(axis=0)
            entry["columns"][column] = {
                "axes": {
                    axis: {
                        "f1": float(board.table[name][column]["f1"][a]),
                        "interval": interval[f"f1 {axis}"],
                        "positives": int(support[a]),
                    }
                    for a, axis in enumerate(AXES)
                    if support[a] >= MIN_POSITIVES
                },
                "micro_f1": micro_f1(y, p),
                "micro_f1_interval": interval["micro_f1"],
            }
        if len(columns) > 1:
            y, p = (np.concatenate([np.asarray(c[k]) for c in columns.values()]) for k in (0, 1))
            entry["pooled"] = {"micro_f1": micro_f1(y, p), "interval": mean_interval(y, p)["micro_f1"]}
        out[name] = entry
    return out


def format_headline(found: dict[str, Any]) -> str:
    """The headline as lines: a model's per-axis F1 (axes with enough positives) and micro-F1 per
    test column, then pooled over the test families."""
    if not found:
        return ""
    lines = [
        f"\n\nheadline: F1 per axis with at least {MIN_POSITIVES} positives (positives), micro-F1 over every "
        "axis decision; 95% bootstrap intervals"
    ]

    def cell(value: float, interval: tuple[float, float]) -> str:
        return f"{value:.3f} ({interval[0]:.3f}-{interval[1]:.3f})" if np.isfinite(value) else "n/a"

    for name, entry in found.items():
        for column, scored in entry["columns"].items():
            axes = "  ".join(
                f"{axis} {cell(a['f1'], a['interval'])} [{a['positives']}]" for axis, a in scored["axes"].items()
            )
            lines.append(
                f"  {name:22s} {column:22s} micro-F1 {cell(scored['micro_f1'], scored['micro_f1_interval'])}"
                + (f"  {axes}" if axes else "")
            )
        if "pooled" in entry:
            pooled = entry["pooled"]
            lines.append(
                f"  {name:22s} {'test families pooled':22s} micro-F1 {cell(pooled['micro_f1'], pooled['interval'])}"
            )
    return "\n".join(lines)


def table_text(board: Scoreboard, estimates: ScanEstimates) -> str:
    """The table with its intervals, the F1-operating points, the draws, the scan estimate's children
    and the cascades' shares of scans checked."""
    options, models = board.options, board.results["models"]
    board.results["headline"] = found = headline(board)
    text = (
        format_table(board.table, intervals=board.intervals)
        + format_headline(found)
        + format_f1_operating_points(models)
        + format_draws(models, options.draws)
    )
    if options.scan_mc:
        scored = models[f"scanmc:{options.scan_mc}"]["splits"]
        text += (
            f"\nscanmc:{options.scan_mc} children drawn a scan (mean): "
            + ", ".join(
                f"{split} {scored[split]['mean_children']:.1f}"
                for split in estimates.drawn
                if scored[split]["mean_children"]
            )
            + "\n"
        )
    for name, model in models.items():
        if "margin" in model:  # a cascade, and random checks of as many scans as it checked
            random = board.results["cascade_random_checks"]
            text += (
                f"{name}: share of scans checked by scanmc:{options.scan_mc}: "
                + ", ".join(
                    f"{split} {r['checked']:.2f} (F1 of random checks that many: "
                    f"{np.interp(r['checked'], random[split]['share'], random[split]['mean_f1']):.3f})"
                    for split, r in model["splits"].items()
                    if "checked" in r
                )
                + "\n"
            )
    for column, scenes in board.results.get("left_out", {}).items():
        if scenes:
            text += f"{column}: {', '.join(scenes)} left out (a checkpoint was adapted there)\n"
    if options.symmetric:
        text = "probabilities averaged over the eight mirror/swap views of each scan\n" + text
    return text


def write_table3(board: Scoreboard, text: str, out: Path) -> list[Path]:
    """table.txt, results.json and pr_curves.png (cascade.png is written with the cascades)."""
    (out / "table.txt").write_text(text + "\n")
    (out / "results.json").write_text(json.dumps(board.results, indent=1, default=_nan_safe))
    models = board.results["models"]
    plot_pr_curves(
        board.curves,
        {n: np.asarray(r["thresholds"]) for n, r in models.items() if n in board.curves},
        out / "pr_curves.png",
    )
    return [
        out / name
        for name in ("table.txt", "results.json", "pr_curves.png", *(["cascade.png"] if board.options.cascade else []))
    ]


def dataset_hessians(data: LabelDataset | DatasetUnion, rows: np.ndarray, progress: bool = False) -> np.ndarray:
    """(len(rows), 6, 6) Hessians of the scans registered onto themselves with the dataset's own
    registration settings; NaN for a scan too small to register."""
    config = from_dict(RegistrationConfig, data.manifest["settings"]["registration"])
    out = np.full((len(rows), 6, 6), np.nan)
    for k, i in enumerate(tqdm(rows, desc="Hessians", disable=not progress, leave=False)):
        with contextlib.suppress(RegistrationError):
            out[k] = hessian_in_level(scan_hessian(data.scan(int(i)), config), level_rotation_of(data.poses[int(i)]))
    return out


def draw_scores(
    clf: Classifier,
    data: LabelDataset | DatasetUnion,
    rows: np.ndarray,
    first: np.ndarray,
    draws: int,
    progress: bool,
    symmetric: bool,
) -> dict[str, list[float]]:
    """Mean accuracy and F1 over axes at the stored thresholds, one per draw of the scans' points
    (`first`: draw 0's probabilities, already computed)."""
    y = data.labels[rows]
    out: dict[str, list[float]] = {"mean_accuracy": [], "mean_f1": []}
    for seed in range(draws):
        probs = (
            first
            if seed == 0
            else predict_dataset(clf.model, data, rows, seed=seed, progress=progress, symmetric=symmetric)
        )
        means = mean_scores(axis_scores(y, probs > clf.thresholds))
        out["mean_accuracy"].append(means["accuracy"])
        out["mean_f1"].append(means["f1"])
    return out


def format_draws(models: dict[str, Any], draws: int) -> str:
    lines = []
    for name, model in models.items():
        for split, scored in model["splits"].items():
            if "draws" not in scored:
                continue
            f1, acc = (np.array(scored["draws"][k], dtype=float) for k in ("mean_f1", "mean_accuracy"))
            lines.append(
                f"  {name:10s} {split:16s} f1 {np.nanmean(f1):.3f} +- {np.nanstd(f1):.3f} "
                f"({np.nanmin(f1):.3f}-{np.nanmax(f1):.3f})  accuracy {np.nanmean(acc):.3f} +- "
                f"{np.nanstd(acc):.3f}"
            )
    if not lines:
        return ""
    return (
        f"\n\nover {draws} draws of the points read from each scan (seeds 0-{draws - 1}; the table is draw 0), "
        "means over axes at the stored thresholds, mean +- std (range):\n" + "\n".join(lines)
    )


def f1_operating_point(
    curves: dict[str, tuple[np.ndarray, np.ndarray]], parts: dict[str, dict[str, np.ndarray]] | None = None
) -> dict[str, Any]:
    """Mean scores of every split (and of the `parts` columns of a split: column -> its rows) at
    the F1-best validation thresholds. The stored thresholds weigh recall (a missed degenerate axis
    corrupts the fused estimate); this shows what a pure classification operating point would score."""
    thresholds = best_thresholds(*curves["valid"], beta=1.0)
    splits = {}
    for split, (y, p) in curves.items():
        for column, rows in {split: np.arange(len(y)), **(parts or {}).get(split, {})}.items():
            splits[column] = mean_scores(axis_scores(y[rows], p[rows] > thresholds))
    return {"thresholds": thresholds.tolist(), "splits": splits}


def format_f1_operating_points(models: dict[str, Any]) -> str:
    lines = []
    for name, model in models.items():
        point = model.get("f1_operating_point")
        if point is None:
            continue
        lines.append(
            f"{name} at the F1-best validation thresholds "
            f"({' '.join(f'{t:.2f}' for t in point['thresholds'])}), means over axes:"
        )
        lines += [
            f"  {split:16s} accuracy {m['accuracy']:.3f}  f1 {m['f1']:.3f}  precision {m['precision']:.3f}  "
            f"recall {m['recall']:.3f}"
            for split, m in point["splits"].items()
        ]
    return "\n\n" + "\n".join(lines) if lines else ""


def random_checks(
    labels: np.ndarray, first: np.ndarray, second: np.ndarray, shares: int = 11, repeats: int = 20, seed: int = 0
) -> dict[str, list[float]]:
    """Mean F1 over axes when a random share of the scans (0, 0.1, ... 1) takes `second`'s
    prediction instead of `first`'s, averaged over `repeats` draws of that share: what checking
    that many scans would give if the cascade chose them blindly, the reference its margins beat."""
    rng = np.random.default_rng(seed)
    out: dict[str, list[float]] = {"share": [], "mean_f1": []}
    for share in np.linspace(0, 1, shares):
        f1 = []
        for _ in range(repeats):
            checked = rng.random(len(labels)) < share
            f1.append(mean_scores(axis_scores(labels, np.where(checked[:, None], second, first)))["f1"])
        out["share"].append(float(share))
        scored = [v for v in f1 if np.isfinite(v)]  # NaN: no positive label and no flag in that draw
        out["mean_f1"].append(float(np.mean(scored)) if scored else float("nan"))
    return out


def plot_cascade(results: dict[str, Any], first: str, children: int, path: Path) -> None:
    """One panel per scored split: mean F1 against the share of scans the estimate checked, for the
    classifier alone (0), each margin, the estimate alone (1) and random checks of the same share."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models, reference = results["models"], results["cascade_random_checks"]
    fig, axes = plt.subplots(1, len(reference), figsize=(5.5 * len(reference), 4.5), squeeze=False)
    for ax, (split, random) in zip(axes[0], reference.items()):
        cascades = sorted((m["margin"], m["splits"][split]) for m in models.values() if "margin" in m)
        share = [0.0] + [r["checked"] for _, r in cascades] + [1.0]
        f1 = (
            [models[first]["splits"][split]["mean"]["f1"]]
            + [r["mean"]["f1"] for _, r in cascades]
            + [models[f"scanmc:{children}"]["splits"][split]["mean"]["f1"]]
        )
        ax.plot(random["share"], random["mean_f1"], "--", color="0.5", label="random checks of that share")
        ax.plot(share, f1, "o-", color="C0", label="cascade by margin (log-odds)")
        for (margin, _), x, y in zip(cascades, share[1:-1], f1[1:-1]):
            ax.annotate(f"{margin:g}", (x, y), textcoords="offset points", xytext=(4, -12), fontsize=8)
        ax.plot([0], f1[:1], "s", color="C1", ms=8, label=f"{first} alone")
        ax.plot([1], f1[-1:], "D", color="C2", ms=8, label=f"scanmc:{children} alone")
        ax.set_title(f"{split}")
        ax.set_xlabel("share of scans checked by the estimate")
        ax.set_ylabel("mean F1 over axes")
        ax.set_xlim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="best")  # the validation panel's points fall towards the lower right
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _nan_safe(value: Any) -> Any:
    return None if isinstance(value, float) and not np.isfinite(value) else value


def plot_pr_curves(
    curves: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]], thresholds: dict[str, np.ndarray], path: Path
) -> None:
    """One panel per axis: the PR curve of each model on each non-training split, with the
    operating point of its stored threshold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 8), sharex=True, sharey=True)
    styles = ["-", "--", ":", "-."]
    for a, ax in enumerate(axes.flat):
        for m, (name, splits) in enumerate(curves.items()):
            for s, (split, (y, p)) in enumerate((k, v) for k, v in splits.items() if k != "train"):
                if not y[:, a].any():
                    continue
                precision, recall, _ = pr_curve(y[:, a], p[:, a])
                (line,) = ax.plot(recall, precision, styles[s % 4], color=f"C{m}", label=f"{name} {split}")
                op = axis_scores(y, p > thresholds[name])
                ax.plot(op["recall"][a], op["precision"][a], "o", color=line.get_color())
        ax.set_title(f"{AXES[a]} (dot: stored threshold)")
        ax.set_xlim(0, 1.02)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("recall")
    for ax in axes[:, 0]:
        ax.set_ylabel("precision")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    for ax in axes.flat[1:]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
