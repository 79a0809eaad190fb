"""Where the scan Monte-Carlo estimate (scanmc) and the labels part, and whether the scan's openness explains it.

Run: python studies/scan_mc_scatter.py --dataset data/l3e48 --dataset data/level --dataset data/mine-test
     [--children 60] [--scans 240] [--workers 2] [--cache scatter.npz]

Every scan of the validation and test scenes, and `--scans` of the training scenes, gets `--children`
children every time (no stages, no calibration). Two tables follow.

1. Per split and axis, over the scans whose label error lies within a factor e^0.5 of its threshold
   (the scans a detector can get wrong): the median of log(label / calibrated estimate) (bias), its
   spread (1.4826 x MAD), and the parts of that spread that Monte-Carlo noise explains: the
   estimate's (the children's spread / sqrt(children)) and the label's (the same children's spread
   over the label's own count of children, as if the scene's children spread as the mesh's do).
   What is left is the scan's mesh differing from the scene.
2. A calibration that follows the scan's openness (the share of the beam-and-column grid with no
   return, where the mesh has nothing for a child to see) against the constant one: log(label /
   estimate) = a + b x openness per axis, least absolute deviations, fitted on the training scans
   only, scored on all three splits.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
from tqdm import tqdm

from l3e_env.core.workers import ordered_map
from l3e_env.data.dataset import open_datasets, row_thresholds
from l3e_env.data.scan_estimates import DatasetScans, open_dataset_scans, row_estimate
from l3e_env.localizability.labels import AXES
from l3e_env.localizability.scan_mc import ScanMCConfig
from l3e_env.model.scores import axis_scores, mean_scores
from l3e_env.model.training import split_indices
from l3e_env.sim.patterns import get_pattern
from scenes import TEST_SCENES, TRAIN_SCENES, VALIDATION_SCENES

NEAR = 0.5  # |log(label error / threshold)| under this: a scan near its threshold


def _raw_rows(scans: DatasetScans, rows: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Each row's children's raw errors, NaN-padded to the configured count, and its openness."""
    pattern = get_pattern(scans.lidar.model)
    out = []
    for row in rows:
        children = np.full((scans.config.children, 6), np.nan)
        if (found := row_estimate(scans, row)) is not None:  # seeded by the row, as dataset_scan_errors is
            children[: len(found.child_errors)] = found.child_errors
        part, at = scans.data.locate(int(row))
        out.append((children, 1.0 - len(part.scan(at)) / (pattern.n_beams * pattern.n_azimuth)))
    return out


def raw_estimates(folders: list[str], rows: np.ndarray, children: int, workers: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, children, 6) raw child errors and (rows,) openness, over `workers` processes."""
    config = ScanMCConfig(children=children, settle=0.0, calibration=(1.0,) * 6)
    chunks = [rows[i : i + 4] for i in range(0, len(rows), 4)]
    found: list[tuple[np.ndarray, float]] = []
    with tqdm(total=len(rows), desc=f"{children} children a scan", leave=False) as bar:
        for part in ordered_map(_raw_rows, chunks, None, open_dataset_scans, (folders, config, 0), workers):
            found.extend(part)
            bar.update(len(part))
    return np.stack([c for c, _ in found]), np.array([o for _, o in found])


def least_absolute_line(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(a, b) of y ~ a + b x by least absolute deviations (iteratively reweighted least squares):
    the median counterpart of the constant calibration's median ratio."""
    design = np.stack([np.ones_like(x), x], axis=1)
    coef = np.linalg.lstsq(design, y, rcond=None)[0]
    for _ in range(100):
        w = np.sqrt(1.0 / np.maximum(np.abs(y - design @ coef), 1e-3))
        coef = np.linalg.lstsq(design * w[:, None], y * w, rcond=None)[0]
    return coef


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", action="append", required=True)
    parser.add_argument("--children", type=int, default=ScanMCConfig.children)
    parser.add_argument("--scans", type=int, default=240, help="training scans the openness calibration is fitted on")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--cache", help="keep the raw estimates here (.npz) and read them back on the next run")
    args = parser.parse_args()
    warnings.filterwarnings("ignore", "Mean of empty slice")  # a scan none of whose children registered
    data = open_datasets(args.dataset)
    names = data.manifest["scenes"]
    rows = {
        split: split_indices(data, [s for s in scenes if s in names])
        for split, scenes in (("train", TRAIN_SCENES), ("valid", VALIDATION_SCENES), ("test", TEST_SCENES))
    }
    rows["train"] = np.sort(np.random.default_rng(0).permutation(rows["train"])[: args.scans])
    cache = Path(args.cache) if args.cache else None
    if cache is not None and cache.exists():
        stored = np.load(cache)
        children = {s: stored[f"{s}_children"] for s in rows}
        openness = {s: stored[f"{s}_openness"] for s in rows}
    else:
        t0 = time.perf_counter()
        found = {s: raw_estimates(args.dataset, r, args.children, args.workers) for s, r in rows.items()}
        children, openness = {s: f[0] for s, f in found.items()}, {s: f[1] for s, f in found.items()}
        print(
            f"{sum(map(len, rows.values()))} scans, {args.children} children each: "
            f"{time.perf_counter() - t0:.0f} s on {args.workers} workers"
        )
        if cache is not None:
            np.savez(
                cache,
                **{f"{s}_children": c for s, c in children.items()},
                **{f"{s}_openness": o for s, o in openness.items()},
            )
    calibration = np.asarray(ScanMCConfig.calibration)
    labels = data.manifest["settings"]["labels"]  # one dict, or one per dataset of a union
    label_children = min(s["children"] for s in (labels if isinstance(labels, list) else [labels]))
    thresholds = row_thresholds(data)

    print(
        "\n1. Scans near the threshold: log(label / estimate x calibration "
        + " ".join(f"{c:.2f}" for c in calibration)
        + ")"
    )
    print("split  axis    scans  bias   spread  estimate MC  label MC  rest")
    for split, r in (("valid", rows["valid"]), ("test", rows["test"])):
        kids = children[split]
        n = np.isfinite(kids[..., 0]).sum(axis=1)[:, None]
        estimate = np.nanmean(kids, axis=1)
        relative = np.nanstd(kids, axis=1) / estimate  # a child's spread relative to the mean
        ratio = np.log(data.errors[r] / (estimate * calibration))
        near = np.abs(np.log(data.errors[r] / thresholds[r])) < NEAR
        for a, axis in enumerate(AXES):
            m = near[:, a] & np.isfinite(ratio[:, a])
            if m.sum() < 3:
                continue
            spread = 1.4826 * np.median(np.abs(ratio[m, a] - np.median(ratio[m, a])))
            own = np.median(relative[m, a] / np.sqrt(n[m, 0]))
            label = np.median(relative[m, a]) / np.sqrt(label_children)
            rest = np.sqrt(max(spread**2 - own**2 - label**2, 0.0))
            print(
                f"{split:6s} {axis:6s} {m.sum():6d}  {np.median(ratio[m, a]):+.2f}  {spread:6.2f}  {own:11.2f}  "
                f"{label:8.2f}  {rest:4.2f}"
            )

    train = children["train"]
    known = np.isfinite(np.nanmean(train, axis=1)).all(axis=1)  # scans with a registered child
    estimate = np.nanmean(train[known], axis=1)
    log_ratio = np.log(data.errors[rows["train"][known]] / estimate)
    constant = np.exp(np.median(log_ratio, axis=0))
    line = np.array([least_absolute_line(openness["train"][known], log_ratio[:, a]) for a in range(6)])
    print(
        "\n2. Openness: mean share of the grid with no return: "
        + ", ".join(f"{s} {openness[s].mean():.3f}" for s in rows)
    )
    print("axis    corr(openness, log label/estimate) on train  constant  a     b")
    for a, axis in enumerate(AXES):
        corr = np.corrcoef(openness["train"][known], log_ratio[:, a])[0, 1]
        print(f"{axis:6s}  {corr:+.2f}{'':38s}  {constant[a]:.3f}    {line[a, 0]:+.2f}  {line[a, 1]:+.2f}")
    print("split  calibration  accuracy  F1     F1 per axis")
    for split, r in rows.items():
        estimate = np.nanmean(children[split], axis=1)
        ok = np.isfinite(estimate).all(axis=1)
        factors = {"constant": constant[None], "openness": np.exp(line[:, 0] + line[:, 1] * openness[split][:, None])}
        for name, factor in factors.items():
            flags = (estimate * factor > thresholds[r])[ok]
            scores = axis_scores(data.labels[r][ok], flags)
            means = mean_scores(scores)
            print(
                f"{split:6s} {name:11s}  {means['accuracy']:.3f}     {means['f1']:.3f}  "
                + " ".join(f"{f:.2f}" for f in scores["f1"])
            )


if __name__ == "__main__":
    main()
