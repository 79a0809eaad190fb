"""Time per scan of the learned+scanmc cascade along the mine route (yard, tunnel, quarry), beside
the classifier alone and the scan estimate alone (the reference), measured in the same run on one
process: the cascade pays for the estimate only on the scans where the classifier is unsure.

Run: python benchmarks/bench_cascade.py [--scans 40] [--margin 1] [--threads 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from bench_classifier import route_scans  # the same route scans as the classifier's benchmark

from l3e_env.config import LidarConfig
from l3e_env.detection.detectors import CASCADE_MARGIN, CascadeDetector, LearnedDetector, ScanMCDetector


def seconds_per_scan(judge, scans: list[np.ndarray]) -> np.ndarray:
    out = []
    for k, points in enumerate(scans):
        t0 = time.perf_counter()
        judge(points, np.random.default_rng([0, k]))
        out.append(time.perf_counter() - t0)
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scans", type=int, default=40)
    ap.add_argument("--margin", type=float, default=CASCADE_MARGIN)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    scans = route_scans(args.scans)
    learned, scan_mc = LearnedDetector(), ScanMCDetector(LidarConfig())
    cascade = CascadeDetector(learned, scan_mc, args.margin)
    learned.predict(scans[0])  # warm
    rows = {
        "scanmc (reference)": seconds_per_scan(scan_mc.judge, scans),
        cascade.name: seconds_per_scan(cascade.judge, scans),
        "learned": seconds_per_scan(lambda points, rng: learned.predict(points), scans),
    }
    reference = rows["scanmc (reference)"].mean()
    print(
        f"{len(scans)} scans along the mine route; the cascade checked {cascade.checked} of them "
        f"({cascade.checked / len(scans):.0%})"
    )
    print(f"{'detector':24s} {'mean ms':>9s} {'median ms':>10s} {'max ms':>9s} {'x scanmc':>9s}")
    for name, t in rows.items():
        print(
            f"{name:24s} {1e3 * t.mean():9.1f} {1e3 * np.median(t):10.1f} {1e3 * t.max():9.1f} "
            f"{t.mean() / reference:9.3f}"
        )


if __name__ == "__main__":
    main()
