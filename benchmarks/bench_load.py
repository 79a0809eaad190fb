"""The shipped classifier's latency on one VLP-16 scan, idle and beside competing load: N processes that
each spin a core, started and stopped by the benchmark. A robot's computer is never idle, so the figure
that matters is the loaded latency over the idle one.

Rows: the detector as shipped (`Classifier.predict`: one torch thread a scan) and, as the reference in the
same run, the same model called with torch's two threads (its default on this machine). Each load level
alternates the rows on the same scans.

Run: python benchmarks/bench_load.py [--scans 20] [--loads 0,2,4]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from competing_load import header, loads, ratio_row, spinning

from l3e_env.core.transforms import planar_pose
from l3e_env.model.classifier import Classifier
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def _scans(count: int) -> list[np.ndarray]:
    """VLP-16 scans at evenly spaced places along the mine's route (yard, tunnel, quarry)."""
    scene = make_scene("mine")
    lidar = Lidar(EmbreeCaster(scene.mesh))
    route = scene.sampling_paths[0]
    picks = np.linspace(0, len(route) - 1, count).astype(int)
    return [
        lidar.scan(planar_pose(*route[k][:2], route[k][2] + 0.85, 0.3), np.random.default_rng(int(k))).points
        for k in picks
    ]


def _median_ms(call, scans: list[np.ndarray], repeats: int = 2) -> float:
    times = []
    for _ in range(repeats):
        for scan in scans:
            t0 = time.perf_counter()
            call(scan)
            times.append(time.perf_counter() - t0)
    return 1000 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=20)
    parser.add_argument("--loads", default="0,2,4", help="comma-separated numbers of spinning processes")
    args = parser.parse_args()
    torch.set_num_threads(2)
    classifier = Classifier.load()
    scans = _scans(args.scans)

    def shipped(scan: np.ndarray) -> None:
        classifier.predict(scan)

    def two_threads(scan: np.ndarray) -> None:
        classifier.probabilities([scan])

    for scan in scans[:3]:
        shipped(scan), two_threads(scan)  # warm: numba's cache, torch's first passes
    rows: dict[str, dict[int, float]] = {"shipped (one thread)": {}, "reference (two threads)": {}}
    for load in loads(args.loads):
        with spinning(load):
            for _ in range(2):  # alternate the rows, so that a phase of the machine hits both
                rows["shipped (one thread)"].setdefault(load, []).append(_median_ms(shipped, scans))
                rows["reference (two threads)"].setdefault(load, []).append(_median_ms(two_threads, scans))
    order = list(next(iter(rows.values())))
    print(f"median ms a scan ({len(scans)} mine scans, {torch.__version__}); ratio: loaded over idle")
    print(header(order, width=26))
    for name, by_load in rows.items():
        print(ratio_row(name, {n: float(np.median(v)) for n, v in by_load.items()}, width=26))
    shipped_idle = np.median(rows["shipped (one thread)"][order[0]])
    reference_idle = np.median(rows["reference (two threads)"][order[0]])
    print(f"idle: shipped / reference = {shipped_idle / reference_idle:.2f}")


if __name__ == "__main__":
    main()
