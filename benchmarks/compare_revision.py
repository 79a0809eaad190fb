"""The shipped model's inference at an earlier git revision against the working tree, in one
process: paired per-scan latency on the mine route (the rows of bench_classifier.py take turns on
blocks of five scans), and, on whole datasets, how far the probabilities move and how many of the
thresholded decisions change. For changes to the inference path that must not change its answers.

The revision's `l3e_env` (with its shipped checkpoint) is extracted with `git archive` and imported
under another name; its imports are relative, so it runs its own code throughout.

Run: python benchmarks/compare_revision.py REV [--scans 40] [--runs 4] [--dataset FOLDER ...]
"""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np
import torch
from bench_classifier import latencies_ms, route_scans

from l3e_env.data.dataset import LabelDataset
from l3e_env.model.classifier import Classifier
from l3e_env.model.training import predict_dataset

ROOT = Path(__file__).resolve().parent.parent


def import_revision(rev: str, folder: Path, name: str = "l3e_env_then"):
    """The revision's l3e_env package, imported as `name`: its classifier, training and dataset modules."""
    archive = folder / "rev.tar"
    subprocess.run(["git", "-C", str(ROOT), "archive", "-o", str(archive), rev, "l3e_env"], check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(folder, filter="data")
    (folder / "l3e_env").rename(folder / name)
    sys.path.insert(0, str(folder))
    return tuple(importlib.import_module(f"{name}.{module}") for module in ("classifier", "training", "dataset"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rev", help="a git revision of this repository, e.g. HEAD~3")
    parser.add_argument("--scans", type=int, default=40)
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--dataset", action="append", default=[], help="labelled dataset to compare answers on")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        then_classifier, then_training, then_dataset = import_revision(args.rev, Path(tmp))
        then, now = then_classifier.Classifier.load(), Classifier.load()
        scans = route_scans(args.scans)
        print(f"{args.rev} against the working tree, {len(scans)} mine-route scans, {args.threads} threads")
        for run in range(args.runs):
            ms = latencies_ms([then.predict, now.predict], scans)
            print(
                f"run {run}: median ms {np.median(ms[0]):.1f} then, {np.median(ms[1]):.1f} now; "
                f"median per-scan ratio now / then {np.median(ms[1] / ms[0]):.3f}"
            )
        for folder in args.dataset:
            data = LabelDataset(folder)
            rows = np.arange(len(data))
            p_then = then_training.predict_dataset(then.model, then_dataset.LabelDataset(folder), rows, batch_size=1)
            p_now = predict_dataset(now.model, data, rows, batch_size=1)
            moved = np.abs(p_now - p_then)
            changed = int(((p_now > now.thresholds) != (p_then > then.thresholds)).sum())
            print(
                f"{folder}: {len(rows)} scans, probabilities moved by at most {moved.max():.5f} (99th percentile "
                f"{np.quantile(moved, 0.99):.5f}); {changed} of {moved.size} decisions changed"
            )


if __name__ == "__main__":
    main()
