"""Does a classifier answer a scan the same whichever way the sensor faces? A degenerate axis is
degenerate whichever way it points, so a scan turned 180 deg about z, or mirrored, has the same labels.

Run: python studies/equivariance.py --checkpoint A.pt [--checkpoint B.pt ...] --dataset data/mine-test
     [--dataset ...] [--frame sensor|canonical]

For every scan of the datasets, each checkpoint judges the scan as stored and the scan turned 180 deg
about z, mirrored across x-z and mirrored across y-z. Printed per checkpoint and view: the share of axis
decisions that agree with the stored scan's and the mean absolute change of the probabilities. The
reference in the same run is the stored scan judged twice (agreement 1, change 0). `--frame` also
scores each checkpoint with its model reading that frame (ModelConfig.frame; the thresholds as stored).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from l3e_env.data.dataset import open_datasets
from l3e_env.model.classifier import Classifier, model_input

VIEWS = {
    "turned 180 deg": np.float32([-1, -1, 1]),
    "mirrored x-z": np.float32([1, -1, 1]),
    "mirrored y-z": np.float32([-1, 1, 1]),
}


def probabilities(clf: Classifier, scans: list[np.ndarray], sign: np.ndarray | None, seed: int = 0) -> np.ndarray:
    out = []
    for i, scan in enumerate(scans):  # the same points drawn from each view of a scan
        pts = model_input(scan, clf.model.config, np.random.default_rng([seed, i]))
        if sign is not None:
            pts = pts * torch.from_numpy(sign)
        with torch.inference_mode():
            out.append(torch.sigmoid(clf.model([pts])).numpy()[0])
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", action="append", required=True)
    ap.add_argument("--dataset", action="append", required=True)
    ap.add_argument("--frame", choices=["sensor", "canonical"])
    args = ap.parse_args()
    data = open_datasets(args.dataset)
    scans = [np.asarray(data.scan(i)) for i in range(len(data))]
    print(f"{len(scans)} scans of {', '.join(args.dataset)}")
    for path in args.checkpoint:
        clf = Classifier.load(path)
        if args.frame:
            clf.model.config.frame = args.frame
        base = probabilities(clf, scans, None)
        print(f"{path} (frame {clf.model.config.frame})")
        for name, sign in {"stored, again": None, **VIEWS}.items():
            p = probabilities(clf, scans, sign)
            agree = ((p > clf.thresholds) == (base > clf.thresholds)).mean()
            print(f"  {name:15s} decisions agree {agree:.4f}   mean |change| {np.abs(p - base).mean():.4f}")


if __name__ == "__main__":
    main()
