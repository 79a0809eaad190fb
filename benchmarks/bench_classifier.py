"""Classifier inference latency on single VLP-16 scans along the mine route (yard, tunnel,
quarry), with the paper's 28 ms (i7-10700F, 8 cores) as the reference, plus the shipped network
without its constraint layer, the shipped model averaged over its eight mirror/swap views, the
PointNet baseline, the shipped widths reading one point of each of 2000 voxels
(ModelConfig.sampling "voxels") and a full-width (FCGF 32-64-128-256) ResUNet, measured in the
same run.

Run: python benchmarks/bench_classifier.py [--checkpoint PATH] [--scans 60] [--threads 2]
"""
from __future__ import annotations

import argparse
import copy
import time

import numpy as np
import torch

from l3e_env.classifier import Classifier, LocalizabilityNet, ModelConfig, model_input
from l3e_env.lidar import Lidar
from l3e_env.raycast import EmbreeCaster
from l3e_env.transforms import pose_to_matrix
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


def latency_ms(fn, scans: list[np.ndarray], warmup: int = 3) -> np.ndarray:
    for s in scans[:warmup]:
        fn(s)
    times = []
    for s in scans:
        t0 = time.perf_counter()
        fn(s)
        times.append(time.perf_counter() - t0)
    return np.array(times) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", help="default: the shipped model")
    parser.add_argument("--scans", type=int, default=60)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scans = route_scans(args.scans)
    clf = Classifier.load(args.checkpoint)
    rows = [("shipped ResUNet (scan -> mask)", latency_ms(clf.predict, scans))]
    if clf.model.stacker is not None:  # the same network without the constraint layer's Hessian
        network = copy.deepcopy(clf.model)
        network.stacker = None
        rows.append(("the same, no constraint layer", latency_ms(Classifier(network, clf.thresholds).predict, scans)))
    symmetric = Classifier.load(args.checkpoint, symmetric=True)
    rows.append(("the same, 8 mirror/swap views", latency_ms(symmetric.predict, scans)))
    rng = np.random.default_rng(0)
    for label, cfg in [("PointNet baseline", ModelConfig(architecture="pointnet")),
                       ("ResUNet on 2000 voxels' points", ModelConfig(sampling="voxels", points=2000)),
                       ("ResUNet at FCGF width", ModelConfig(channels=(32, 64, 128, 256)))]:
        model = LocalizabilityNet(cfg).eval()

        def run(s, model=model, cfg=cfg):
            with torch.inference_mode():
                return model([model_input(s, cfg, rng)])

        rows.append((label, latency_ms(run, scans)))
    print(f"{len(scans)} VLP-16 scans along the mine route, {args.threads} threads, "
          f"median {np.median([len(s) for s in scans]):.0f} points per scan")
    print(f"{'model':32s} {'median ms':>10s} {'p90 ms':>8s} {'paper 28 ms / ours':>20s}")
    for label, ms in rows:
        print(f"{label:32s} {np.median(ms):10.1f} {np.percentile(ms, 90):8.1f} {PAPER_MS / np.median(ms):19.2f}x")


if __name__ == "__main__":
    main()
