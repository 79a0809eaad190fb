"""Fit the scan Monte-Carlo estimate's calibration (ScanMCConfig.calibration) on training scenes.

Run: python studies/scan_mc_calibration.py --dataset data/l3e48 --dataset data/level
     [--scans 240] [--children 20] [--workers 2] [--seed 0] [--shadow-deg 3] [--beyond-deg 4]
     [--out estimates.npz]

The estimate (l3e_env/scan_mc.py) meshes a scan's range image and registers children ray-cast
against that mesh. Surfaces the scan did not see are missing from it, so the estimate runs low.
The calibration of each axis is 1 / the median ratio of estimate to label error over a random
subset of the training scenes' scans, made here without any calibration. It prints the factors,
and how the estimate scores against the labels on that subset, without and with them.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from l3e_env.data.dataset import open_datasets, row_thresholds
from l3e_env.data.scan_estimates import dataset_scan_errors
from l3e_env.localizability.labels import AXES
from l3e_env.localizability.scan_mc import ScanMCConfig
from l3e_env.model.scores import axis_scores, mean_scores
from l3e_env.model.training import split_indices
from scenes import TRAIN_SCENES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", action="append", required=True)
    parser.add_argument("--scans", type=int, default=240)
    parser.add_argument("--children", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--shadow-deg",
        type=float,
        default=ScanMCConfig.shadow_deg,
        help="continue the background behind depth jumps this far (ScanMCConfig.shadow_deg)",
    )
    parser.add_argument(
        "--beyond-deg",
        type=float,
        default=ScanMCConfig.beyond_deg,
        help="continue the edge beams' surfaces this far past the field of view (ScanMCConfig.beyond_deg)",
    )
    parser.add_argument("--out", help="save rows, estimates and label errors here (.npz)")
    args = parser.parse_args()
    data = open_datasets(args.dataset)
    rows = split_indices(data, [s for s in TRAIN_SCENES if s in data.manifest["scenes"]])
    rows = np.sort(np.random.default_rng(args.seed).permutation(rows)[: args.scans])
    t0 = time.perf_counter()
    # every scan gets all its children: stopping early is judged against calibrated thresholds
    config = ScanMCConfig(
        children=args.children,
        calibration=(1.0,) * 6,
        settle=0.0,
        shadow_deg=args.shadow_deg,
        beyond_deg=args.beyond_deg,
    )
    estimates, _ = dataset_scan_errors(args.dataset, rows, config, seed=args.seed, workers=args.workers, progress=True)
    seconds = time.perf_counter() - t0
    known = np.isfinite(estimates).all(axis=1)
    errors, labels, thresholds = data.errors[rows], data.labels[rows], row_thresholds(data)[rows]
    calibration = 1.0 / np.median(estimates[known] / errors[known], axis=0)
    print(
        f"{len(rows)} training scans ({int((~known).sum())} not judged), {args.children} children, "
        f"{seconds:.0f} s ({1000 * seconds * args.workers / len(rows):.0f} ms a scan on one worker)"
    )
    print("axis      calibration  log-error correlation")
    for a, axis in enumerate(AXES):
        corr = np.corrcoef(np.log(estimates[known, a]), np.log(errors[known, a]))[0, 1]
        print(f"{axis:8s}  {calibration[a]:11.2f}  {corr:21.2f}")
    for name, factor in (("without calibration", np.ones(6)), ("with it", calibration)):
        scores = axis_scores(labels[known], estimates[known] * factor > thresholds[known])
        mean = mean_scores(scores)
        print(
            f"{name:20s} accuracy {mean['accuracy']:.3f} F1 {mean['f1']:.3f}  per axis F1 "
            + " ".join(f"{f:.2f}" for f in scores["f1"])
        )
    print("calibration = (" + ", ".join(f"{c:.2f}" for c in calibration) + ")")
    if args.out:
        np.savez(args.out, rows=rows, estimates=estimates, errors=errors, labels=labels)


if __name__ == "__main__":
    main()
