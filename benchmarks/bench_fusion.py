"""Fusion speed: the iSAM2 update per step over a long run (EKF step as the reference in the
same run), and environment steps per second with the whole pipeline in the loop (scan,
learned detector, ICP, iSAM2), with the classifier in the step's process and in one of its own
(FusionSettings.detector_process), against the bare environment.

The legs' bias states with the whole drive smoothed and with the environments' fixed-lag window
(FusionConfig.smoother_lag): with them iSAM2 revises every later pose where a bias estimate moves.

Run: python benchmarks/bench_fusion.py [--steps 3000] [--env-steps 300] [--scene mine] [--loads 0,4]
`--loads`: the environment rows idle and beside N processes that each spin a core (benchmarks/competing_load.py).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from competing_load import header, loads, ratio_row, spinning

from fusion import EKFFusion, FusionConfig, FusionGraph
from l3e_env.config import EnvConfig, FusionSettings
from l3e_env.core.transforms import pose_to_matrix
from l3e_env.detection.pipeline import ONLINE_LAG, ONLINE_RELINEARIZE
from l3e_env.envs.navigation import NavigationEnv
from l3e_env.sim.follower import RouteFollower


def update_times(
    backend, steps: int, seed: int = 0, hessians: bool = False, config: FusionConfig | None = None
) -> np.ndarray:
    """Seconds per add_step along a winding 3-D run with noisy odometry, ICP and random masks;
    with `hessians`, each ICP step comes with a point-to-plane Hessian (its information then
    enters as a full square-root model instead of the fixed diagonal)."""
    rng = np.random.default_rng(seed)
    fusion = backend(np.eye(4), config)
    sigmas = np.array([0.01, 0.01, 0.01, 0.002, 0.002, 0.004])
    times = np.empty(steps)
    for k in range(steps):
        true = pose_to_matrix(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.02 * np.sin(k / 50)]))
        odom = true @ pose_to_matrix(rng.normal(0, sigmas))
        icp = true @ pose_to_matrix(rng.normal(0, sigmas / 5))
        mask = rng.random(6) < 0.2
        rows = rng.normal(size=(200, 6)) * np.array([1.0, 1.0, 1.0, 5.0, 5.0, 5.0])
        hessian = rows.T @ rows if hessians else None
        t0 = time.perf_counter()
        fusion.add_step(odom, sigmas, icp, mask, hessian)
        times[k] = time.perf_counter() - t0
    return times


def env_rate(fusion: FusionSettings, scene: str, steps: int) -> float:
    env = NavigationEnv(EnvConfig(scene=scene, fusion=fusion))
    _, info = env.reset(seed=0)
    follow = RouteFollower(env.route)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, info = env.step(follow(info["T_w_b"]))
        if terminated or truncated:
            _, info = env.reset()
            follow.reset()
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--env-steps", type=int, default=300)
    parser.add_argument("--scene", default="mine")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--loads", default="0", help="numbers of spinning processes for the environment rows, e.g. 0,4")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    isam = update_times(FusionGraph, args.steps) * 1e3
    ekf = update_times(EKFFusion, args.steps) * 1e3
    print(
        f"iSAM2 update over {args.steps} steps: median {np.median(isam):.3f} ms, "
        f"p90 {np.percentile(isam, 90):.3f} ms, "
        f"last 500 median {np.median(isam[-500:]):.3f} ms (target <= 1 ms)"
    )
    print(f"EKF step (reference): median {np.median(ekf):.3f} ms; iSAM2 / EKF {np.median(isam) / np.median(ekf):.2f}x")
    weighed = update_times(FusionGraph, args.steps, hessians=True) * 1e3
    print(
        f"iSAM2 update with each step's Hessian as the ICP information: median {np.median(weighed):.3f} ms "
        f"({np.median(weighed) / np.median(isam):.2f}x the fixed sigmas')"
    )
    for axes in (("yaw",), ("yaw", "z")):
        biased = update_times(FusionGraph, args.steps, hessians=True, config=FusionConfig(odometry_bias=axes)) * 1e3
        print(
            f"iSAM2 update with the legs' {'+'.join(axes)} bias as states: median {np.median(biased):.3f} ms, "
            f"p90 {np.percentile(biased, 90):.3f} ms ({np.median(biased) / np.median(weighed):.2f}x without)"
        )
    whole = (
        update_times(FusionGraph, args.steps, hessians=True, config=FusionConfig(odometry_bias=("yaw", "scale"))) * 1e3
    )
    window = (
        update_times(
            FusionGraph,
            args.steps,
            hessians=True,
            config=FusionConfig(
                odometry_bias=("yaw", "scale"), smoother_lag=ONLINE_LAG, relinearize_threshold=ONLINE_RELINEARIZE
            ),
        )
        * 1e3
    )
    for name, times in (("the whole drive", whole), (f"a {ONLINE_LAG}-step window (the environments')", window)):
        print(
            f"iSAM2 update with the legs' yaw+scale bias as states, {name}: median {np.median(times):.3f} ms, "
            f"last 500 median {np.median(times[-500:]):.3f} ms and mean {times[-500:].mean():.3f} ms, "
            f"max {times.max():.1f} ms"
        )
    print(f"  window over whole drive, last 500 mean: {window[-500:].mean() / whole[-500:].mean():.2f}x")
    rows: dict[str, dict[int, float]] = {
        "scan + learned detector + ICP + iSAM2": {},
        "  the classifier in a process of its own": {},
        "bare environment (scan, no fusion)": {},
    }
    settings = [
        FusionSettings(enabled=True, detector="learned"),
        FusionSettings(enabled=True, detector="learned", detector_process=True),
        FusionSettings(enabled=False),
    ]
    for load in loads(args.loads):
        with spinning(load):
            for row, fusion in zip(rows.values(), settings):
                row[load] = env_rate(fusion, args.scene, args.env_steps)
    print(f"{args.scene} env, VLP-16, steps/s (ratio: loaded over idle)")
    print(header(loads(args.loads), width=44))
    for name, row in rows.items():
        print(ratio_row(name, row, "steps/s", width=44))


if __name__ == "__main__":
    main()
