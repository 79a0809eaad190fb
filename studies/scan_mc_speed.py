"""How far a cheaper scan estimate moves its decisions: each child casting every k-th column
(ScanMCConfig.column_stride), against the estimate as it is, on the same scans with the same seeds;
and, as the yardstick, the estimate as it is with another seed (its own Monte-Carlo spread).

    python studies/scan_mc_speed.py --dataset data/mine-test --scans 96 --strides 1,2,3,4
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from l3e_env.config import LidarConfig, from_dict
from l3e_env.data.dataset import LabelDataset
from l3e_env.localizability.registration import RegistrationConfig, RegistrationError
from l3e_env.localizability.scan_mc import ScanMCConfig, ScanPatternError, scan_errors


def estimates(data: LabelDataset, rows: np.ndarray, config: ScanMCConfig, seed: int) -> tuple[np.ndarray, float]:
    """(len(rows), 6) decisions (NaN rows where a scan cannot be judged) and the seconds a scan took."""
    lidar = from_dict(LidarConfig, data.manifest["settings"]["lidar"])
    registration = from_dict(RegistrationConfig, data.manifest["settings"]["registration"])
    labels = data.label_config
    out = np.full((len(rows), 6), np.nan)
    t0 = time.perf_counter()
    for k, row in enumerate(rows):
        try:
            found = scan_errors(
                data.scan(int(row)), lidar, registration, labels, config, np.random.default_rng([seed, int(row)])
            )
        except (RegistrationError, ScanPatternError):
            continue
        out[k] = found.errors > labels.threshold_vector()
    return out, (time.perf_counter() - t0) / len(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--scans", type=int, default=96, help="scans, evenly spread over the dataset")
    ap.add_argument("--strides", default="1,2,3,4")
    ap.add_argument("--children", type=int, default=60)
    args = ap.parse_args()
    data = LabelDataset(args.dataset)
    rows = np.linspace(0, len(data) - 1, min(args.scans, len(data))).astype(int)
    base = ScanMCConfig(children=args.children)
    reference, seconds = estimates(data, rows, base, seed=0)
    other, _ = estimates(data, rows, base, seed=1)
    known = np.isfinite(reference).all(axis=1) & np.isfinite(other).all(axis=1)
    print(f"{len(rows)} scans of {args.dataset}, up to {args.children} children")
    labels = data.labels[rows]
    seeds = np.mean(reference[known] == other[known])
    print(f"as it is: {seconds * 1000:.0f} ms a scan; another seed agrees on {seeds:.1%} of axis decisions")
    print(f"the labels agree with it on {np.mean(reference[known] == labels[known]):.1%}")
    for stride in map(int, args.strides.split(",")):
        if stride == 1:
            continue
        found, took = estimates(data, rows, replace(base, column_stride=stride), seed=0)
        both = known & np.isfinite(found).all(axis=1)
        same, right = np.mean(found[both] == reference[both]), np.mean(found[both] == labels[both])
        print(
            f"every {stride}th column: {took * 1000:.0f} ms a scan ({seconds / took:.2f}x), decisions as it is on "
            f"{same:.1%}, the labels' on {right:.1%}"
        )


if __name__ == "__main__":
    main()
