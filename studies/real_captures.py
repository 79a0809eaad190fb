"""What the detectors say on real scans: Ouster's own test captures (tests/data/ouster, ordinary
places without ground truth), each read from its .osf (and the OS1-128's .pcap) in the lidar frame.

Run: python studies/real_captures.py [--detector SPEC ...] [--seed 0]

Printed, as markdown: per capture, each detector's count of flagged axes over its scans (x/y/z/roll/
pitch/yaw) and the scans it could not judge; then, over every scan, the share of axis decisions on
which each pair of detectors agrees; then the shipped classifier's decisions kept when each scan is
turned 180 deg about z (a degenerate axis is degenerate whichever way the sensor faces), against the
scan judged twice (the reference in the same run, 100%).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from l3e_env.config import LidarConfig
from l3e_env.detection.detectors import make_detector
from l3e_env.experiments.judge import JudgeOptions, judge_scans
from l3e_env.io.ouster import read_capture
from l3e_env.localizability.labels import AXES

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "ouster"
CAPTURES = [
    "OS-1-128_v2.3.0_1024x10_lb_n3.osf",
    "OS-0-128_v3.0.1_1024x10_20241017_141645.osf",
    "osf_fw_3.2_10scans.osf",
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--detector", action="append", help="detector specs (default: learned, eigen:30, dcreg:50, scanmc)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    specs = args.detector or ["learned", "eigen:30", "dcreg:50", "scanmc"]
    masks: dict[str, list[np.ndarray]] = {}
    print("| capture | scans | " + " | ".join(specs) + " |\n|---|---|" + "---|" * len(specs))
    for capture in CAPTURES:
        judged = [j for j in judge_scans([DATA / capture], specs, options=JudgeOptions(seed=args.seed)) if not j.error]
        names = list(judged[0].predictions)
        cells = []
        for name in names:
            known = [j.predictions[name] for j in judged if j.predictions[name].known]
            flags = np.sum([p.mask for p in known], axis=0) if known else np.zeros(6, int)
            unknown = len(judged) - len(known)
            cells.append("/".join(str(int(f)) for f in flags) + (f" ({unknown} unknown)" if unknown else ""))
            masks.setdefault(name, []).extend(
                p.mask if p.known else np.full(6, np.nan) for p in (j.predictions[name] for j in judged)
            )
        print(f"| {capture} | {len(judged)} | " + " | ".join(cells) + " |")
    print(
        f"\nflagged axes counted {'/'.join(AXES)}\n\n| agreement | "
        + " | ".join(masks)
        + " |\n|---|"
        + "---|" * len(masks)
    )
    for a in masks:
        row = []
        for b in masks:
            x, y = np.asarray(masks[a], float), np.asarray(masks[b], float)
            both = np.isfinite(x) & np.isfinite(y)
            row.append(f"{np.mean(x[both] == y[both]):.0%}" if both.any() else "-")
        print(f"| {a} | " + " | ".join(row) + " |")

    learned = make_detector("learned", seed=args.seed, sensor=LidarConfig())
    turn = np.diag([-1.0, -1.0, 1.0])
    kept = twice = total = 0
    for capture in CAPTURES:
        for scan in read_capture(DATA / capture):
            if scan.points is None:
                continue
            a, b = learned.predict(scan.points, None, None), learned.predict(scan.points @ turn.T, None, None)
            again = learned.predict(scan.points, None, None)
            kept += int((a.mask == b.mask).sum())
            twice += int((a.mask == again.mask).sum())
            total += len(AXES)
    print(
        f"\nlearned under a 180 deg turn: {kept}/{total} axis decisions kept ({kept / total:.1%}); "
        f"judged twice: {twice}/{total}"
    )


if __name__ == "__main__":
    main()
