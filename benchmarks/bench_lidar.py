"""Scan throughput as a ratio to a raw cast of the same rays with the same threads, idle and beside
competing load.

Run: python benchmarks/bench_lidar.py [--repeats 200] [--loads 0,4] [--pybullet]
The full scan (ray directions to the world frame, cast, noise, dropout, points in the sensor frame)
and `EmbreeCaster.cast` on precomputed world directions (the same caster, so the same thread pool)
take turns call by call, so that a phase of a noisy machine hits both alike; the ratio is the median
of the per-pair ratios. `--pybullet` adds PyBullet's scan against the same raw cast.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
from competing_load import loads, spinning

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import pose_to_matrix
from l3e_env.sim.lidar import Lidar, get_pattern
from l3e_env.sim.raycast import EmbreeCaster, PyBulletCaster
from scenes import make_scene

PLACES = {
    "yard": (-30.0, 0.5, 0.85, 0, 0, 0.3),
    "tunnel": (50.0, 0.0, 0.85, 0, 0, 0.0),
    "quarry": (115.0, 0.0, 0.85, 0, 0, 1.0),
}


def paired(reference: Callable[[], object], measured: Callable[[], object], repeats: int) -> tuple[float, float, float]:
    """(median reference s, median measured s, median of reference/measured per pair) after a warm-up."""
    for _ in range(3):
        reference(), measured()
    times = np.empty((repeats, 2))
    for k in range(repeats):
        t0 = time.perf_counter()
        reference()
        t1 = time.perf_counter()
        measured()
        times[k] = t1 - t0, time.perf_counter() - t1
    return float(np.median(times[:, 0])), float(np.median(times[:, 1])), float(np.median(times[:, 0] / times[:, 1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--loads", default="0", help="numbers of spinning processes, e.g. 0,4 (default idle only)")
    parser.add_argument("--pybullet", action="store_true", help="also PyBullet's scan (slow)")
    args = parser.parse_args()
    scene = make_scene("mine")
    embree = EmbreeCaster(scene.mesh)
    pybullet = PyBulletCaster.for_mesh(scene.mesh) if args.pybullet else None
    rng = np.random.default_rng(0)
    print(f"Embree on {embree.threads} threads; ratio = raw cast / scan, median over {args.repeats} pairs")
    print(
        f"{'load':>4s} {'sensor':8s} {'place':7s} {'rays':>7s} {'raw cast':>9s} {'scan':>9s} {'ratio':>6s}"
        + ("  pybullet scan  ratio" if pybullet else "")
    )
    for load in loads(args.loads):
        with spinning(load):
            for model in ("vlp16", "os0-128"):
                config = LidarConfig(model=model)
                lidar = Lidar(embree, config)
                lidar_p = Lidar(pybullet, config) if pybullet else None
                for place, pose in PLACES.items():
                    T = pose_to_matrix(np.array(pose))
                    dirs = np.ascontiguousarray(get_pattern(model).directions() @ T[:3, :3].T.astype(np.float32))
                    origin = T[:3, 3].copy()

                    def raw(origin=origin, dirs=dirs, lidar=lidar) -> np.ndarray:
                        return embree.cast(origin, dirs, lidar.max_range)

                    raw_s, scan_s, ratio = paired(raw, lambda lidar=lidar, T=T: lidar.scan(T, rng), args.repeats)
                    line = (
                        f"{load:4d} {model:8s} {place:7s} {len(dirs):7d} {raw_s * 1e3:6.2f} ms "
                        f"{scan_s * 1e3:6.2f} ms {ratio:6.2f}"
                    )
                    if lidar_p is not None:
                        _, pyb_s, pyb_ratio = paired(
                            raw, lambda lidar_p=lidar_p, T=T: lidar_p.scan(T, rng), max(3, args.repeats // 20)
                        )
                        line += f"  {pyb_s * 1e3:10.1f} ms {pyb_ratio:6.3f}"
                    print(line, flush=True)


if __name__ == "__main__":
    main()
