"""The registration's time with the ground plane's normals (the default) against small_gicp's plain
point-to-plane ICP, on consecutive scan pairs along the mine's route.

Run: python benchmarks/bench_registration.py [--pairs 30] [--repeats 3]
Reference (same run, interleaved pair by pair): `register` with `ground_normals=False`, which runs
small_gicp's own PLANE_ICP on its neighbours' normals. Two figures: a whole registration as the
fusion runs one each step (both scans prepared, ICP, the Hessian), and the ICP alone onto a prepared
target, as the labels run one per child.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from l3e_env.core.transforms import planar_pose
from l3e_env.localizability.registration import PreparedTarget, RegistrationConfig, prepare_source, register
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def scan_pairs(count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Level scans 0.1 m apart at `count` places along the mine's route, facing along it."""
    scene = make_scene("mine")
    lidar = Lidar(EmbreeCaster(scene.mesh))
    rng = np.random.default_rng(0)
    route = scene.route
    pairs = []
    for k in np.linspace(0, len(route) - 2, count).astype(int):
        heading = float(np.arctan2(*(route[k + 1, 1::-1] - route[k, 1::-1])))
        before = planar_pose(route[k, 0], route[k, 1], route[k, 2] + 0.85, heading)
        after = before @ planar_pose(0.1, 0.0, 0.0, 0.0)
        pairs.append((lidar.scan(after, rng).points, lidar.scan(before, rng).points))
    return pairs


def timed(call, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3, help="the best of this many runs of each pair")
    args = parser.parse_args()
    configs = {"small_gicp (reference)": RegistrationConfig(ground_normals=False), "default": RegistrationConfig()}
    whole = {name: [] for name in configs}
    icp = {name: [] for name in configs}
    for source, target in scan_pairs(args.pairs):
        for name, config in configs.items():
            whole[name].append(timed(lambda c=config, s=source, t=target: register(s, t, c), args.repeats))
            prepared, thinned = PreparedTarget(target, config), prepare_source(source, config)
            icp[name].append(
                timed(lambda c=config, t=prepared, s=thinned: register(s, t, c, with_hessian=False), args.repeats)
            )
    reference = "small_gicp (reference)"
    print(f"{args.pairs} scan pairs of the mine's route, median ms (best of {args.repeats})")
    print(f"{'registration':26s} {'whole':>8s} {'ratio':>6s} {'ICP alone':>10s} {'ratio':>6s}")
    for name in configs:
        w, i = np.median(whole[name]) * 1e3, np.median(icp[name]) * 1e3
        w_ref, i_ref = np.median(whole[reference]) * 1e3, np.median(icp[reference]) * 1e3
        print(f"{name:26s} {w:8.2f} {w / w_ref:6.2f} {i:10.2f} {i / i_ref:6.2f}")


if __name__ == "__main__":
    main()
