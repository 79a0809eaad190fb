"""Classifier inference latency on single VLP-16 scans along the mine route (yard, tunnel,
quarry), with the paper's 28 ms (i7-10700F, 8 cores) as the reference, plus the shipped model with
float32 convolutions (Classifier.load runs them in int8), the shipped network without its
constraint layer, the shipped model with its batch norms as trained and in float32 (Classifier.load
folds them into the layers before them), the shipped model averaged over its eight mirror/swap
views, the PointNet baseline, the shipped widths reading one point of each of 2000 voxels
(ModelConfig.sampling "voxels") and a full-width (FCGF 32-64-128-256) ResUNet (these three folded
too), measured in the same run.

The rows take turns on blocks of five scans, so that a machine that slows down for a while
slows every row alike; the last column is each row's speed relative to the FCGF-width ResUNet
(the issue's starting point) in the same run.

Run: python benchmarks/bench_classifier.py [--checkpoint PATH] [--scans 60] [--threads 2]
"""

from __future__ import annotations

import argparse
import copy
import time

import numpy as np
import torch

from l3e_env.core.transforms import pose_to_matrix
from l3e_env.model.classifier import (
    DEFAULT_CHECKPOINT,
    Classifier,
    LocalizabilityNet,
    ModelConfig,
    fold_batch_norms,
    load_checkpoint,
    model_from_checkpoint,
    model_input,
)
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene
from scenes.geometry import polyline_length, resample_polyline

PAPER_MS = 28.0


def route_scans(count: int) -> list[np.ndarray]:
    scene = make_scene("mine")
    lidar = Lidar(EmbreeCaster(scene.mesh))
    route = np.asarray(scene.route)[:, :2]
    length = polyline_length(route)
    xy = resample_polyline(route, length / (count - 1))[:count]
    heading = np.arctan2(*np.gradient(xy, axis=0).T[::-1])
    rng = np.random.default_rng(0)
    return [lidar.scan(pose_to_matrix(np.array([x, y, 0.85, 0, 0, h])), rng).points for (x, y), h in zip(xy, heading)]


def latencies_ms(fns: list, scans: list[np.ndarray], block: int = 5) -> np.ndarray:
    """(len(fns), len(scans)) milliseconds. The functions take turns, in a rotating order, on blocks
    of `block` scans, each after one untimed call on its block's first scan: a machine that slows
    down for a while slows every row alike, and no row is timed cold just after another model ran."""
    times = np.zeros((len(fns), len(scans)))
    for b, start in enumerate(range(0, len(scans), block)):
        for k in range(len(fns)):
            i = (b + k) % len(fns)  # the order rotates from block to block
            fns[i](scans[start])
            for j in range(start, min(start + block, len(scans))):
                t0 = time.perf_counter()
                fns[i](scans[j])
                times[i, j] = time.perf_counter() - t0
    return times * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", help="default: the shipped model")
    parser.add_argument("--scans", type=int, default=60)
    parser.add_argument(
        "--threads", type=int, default=2, help="torch's threads outside predict, which runs one scan on one thread"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scans = route_scans(args.scans)
    clf = Classifier.load(args.checkpoint)
    rows = [
        ("shipped ResUNet (scan -> mask)", clf.predict),
        ("the same in float32", Classifier.load(args.checkpoint, int8=False).predict),
    ]
    if clf.model.stacker is not None:  # the same network without the constraint layer's Hessian
        network = copy.deepcopy(clf.model)
        network.stacker = None
        rows.append(("the same, no constraint layer", Classifier(network, clf.thresholds).predict))
    unfolded = model_from_checkpoint(load_checkpoint(args.checkpoint or DEFAULT_CHECKPOINT))  # and float32
    rows.append(("the same, batch norms not folded", Classifier(unfolded, clf.thresholds).predict))
    symmetric = Classifier.load(args.checkpoint, symmetric=True)
    rows.append(("the same, 8 mirror/swap views", symmetric.predict))
    rng = np.random.default_rng(0)
    for label, cfg in [
        ("PointNet baseline", ModelConfig(architecture="pointnet")),
        ("ResUNet on 2000 voxels' points", ModelConfig(sampling="voxels", points=2000)),
        ("ResUNet at FCGF width", ModelConfig(channels=(32, 64, 128, 256))),
    ]:
        model = fold_batch_norms(LocalizabilityNet(cfg))  # as Classifier.load runs a model

        def run(s, model=model, cfg=cfg):
            with torch.inference_mode():
                return model([model_input(s, cfg, rng)])

        rows.append((label, run))
    times = latencies_ms([fn for _, fn in rows], scans)
    print(
        f"{len(scans)} VLP-16 scans along the mine route, predict on one torch thread ({args.threads} for "
        "batches), "
        f"median {np.median([len(s) for s in scans]):.0f} points per scan"
    )
    reference = np.median(times[-1])  # the FCGF-width ResUNet, the starting point
    print(f"{'model':32s} {'median ms':>10s} {'p90 ms':>8s} {'paper 28 ms / ours':>20s} {'FCGF width / ours':>18s}")
    for (label, _), ms in zip(rows, times):
        print(
            f"{label:32s} {np.median(ms):10.1f} {np.percentile(ms, 90):8.1f} {PAPER_MS / np.median(ms):19.2f}x"
            f" {reference / np.median(ms):17.2f}x"
        )


if __name__ == "__main__":
    main()
