"""Scan throughput of both ray backends, as a ratio to a raw Embree cast of the same rays.

Run: python benchmarks/bench_lidar.py [--repeats 200]
The full scan (ray directions to the world frame, cast, noise, dropout, points in the sensor
frame) is compared with `EmbreeScene.run` on precomputed origin and direction arrays, in the same
process, so the ratio survives a noisy machine.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from l3e_env.config import LidarConfig
from l3e_env.sim.lidar import Lidar, get_pattern
from l3e_env.sim.raycast import EmbreeCaster, PyBulletCaster
from l3e_env.core.transforms import pose_to_matrix
from scenes import make_scene

PLACES = {"yard": (-30.0, 0.5, 0.85, 0, 0, 0.3), "tunnel": (50.0, 0.0, 0.85, 0, 0, 0.0),
          "quarry": (115.0, 0.0, 0.85, 0, 0, 1.0)}


def best_of(fn, repeats: int) -> float:
    """Median seconds per call after a warm-up."""
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    scene = make_scene("mine")
    embree = EmbreeCaster(scene.mesh)
    pybullet = PyBulletCaster.for_mesh(scene.mesh)
    rng = np.random.default_rng(0)
    print(f"{'sensor':8s} {'place':7s} {'rays':>7s} {'raw embree':>11s} {'embree scan':>12s} {'ratio':>6s} "
          f"{'pybullet scan':>14s} {'ratio':>6s}")
    for model in ("vlp16", "os0-128"):
        pattern = get_pattern(model)
        lidar_e, lidar_p = Lidar(embree, LidarConfig(model=model)), Lidar(pybullet, LidarConfig(model=model))
        for place, pose in PLACES.items():
            T = pose_to_matrix(np.array(pose))
            dirs = np.ascontiguousarray(pattern.directions() @ T[:3, :3].T.astype(np.float32))
            origins = np.ascontiguousarray(np.broadcast_to((T[:3, 3] - embree.offset).astype(np.float32), dirs.shape))
            raw = best_of(lambda: embree.scene.run(origins, dirs, query="DISTANCE"), args.repeats)
            full = best_of(lambda: lidar_e.scan(T, rng), args.repeats)
            pyb = best_of(lambda: lidar_p.scan(T, rng), max(3, args.repeats // 20))
            n = len(dirs)
            print(f"{model:8s} {place:7s} {n:7d} {raw * 1e3:8.2f} ms {full * 1e3:9.2f} ms {raw / full:6.2f} "
                  f"{pyb * 1e3:11.1f} ms {raw / pyb:6.3f}   "
                  f"({n / full / 1e6:.1f} M rays/s embree, {n / pyb / 1e6:.2f} pybullet)")


if __name__ == "__main__":
    main()
