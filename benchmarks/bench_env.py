"""Environment steps per second along a scene's route (no learned part), with the scan alone
measured in the same run as the reference.

Run: python benchmarks/bench_env.py [--scene mine] [--steps 1000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from l3e_env.config import EnvConfig, LidarConfig
from l3e_env.envs.navigation import NavigationEnv
from l3e_env.sim.follower import RouteFollower


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="mine")
    parser.add_argument("--sensor", default="vlp16")
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    env = NavigationEnv(EnvConfig(scene=args.scene, lidar=LidarConfig(model=args.sensor)))
    obs, info = env.reset(seed=0)
    follow = RouteFollower(env.route)
    actions, t0 = 0, time.perf_counter()
    for _ in range(args.steps):
        obs, _, terminated, truncated, info = env.step(follow(info["T_w_b"]))
        actions += 1
        if terminated or truncated:
            obs, info = env.reset()
            follow.reset()
    elapsed = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    T = env.robot.T_w_s
    t1 = time.perf_counter()
    for _ in range(200):
        env.lidar.scan(T, rng)
    scan = (time.perf_counter() - t1) / 200
    step = elapsed / actions
    print(
        f"{args.scene} / {args.sensor}: {actions / elapsed:.0f} steps/s ({step * 1e3:.2f} ms per step, "
        f"{scan * 1e3:.2f} ms of it a scan alone; scan share {scan / step:.2f})"
    )


if __name__ == "__main__":
    main()
