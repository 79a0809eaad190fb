"""CPU cost of one full-pipeline step of a navigation episode, by part: the scan, the ICP target's
preparation (normals, k-d tree), ICP, the detector, the fusion, the local layer and the follower, and
the rest (the walk, odometry, collision checks). The reference in the same run is the raw cast: the
scene's Embree cast of the same revolution's rays from the robot's sensor poses, on one thread, with
nothing around it (no noise, frames or points): the physical floor of a simulated scan. Every part,
and the whole step, is printed as a multiple of it beside its milliseconds.
The fusion is the policies' evaluation's (FusionSettings(): scans registered onto keyframes, so
that a target is prepared once a keyframe).

CPU time (time.process_time: every thread of the process counted), as a policy evaluation on 2 cores
pays it; the follower walks the scene's route steering on the fused estimate, as `l3e policy evaluate`.

The fusion's window fills after ONLINE_LAG steps, and only then does it marginalize: the run covers
an episode, and the fusion's cost is printed over its second half too, with the window full.

Run: python benchmarks/bench_step.py [--scene bypass-100] [--steps 1200] [--detector learned]
     [--keyframe-distance 0] [--detector-every 4]
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import numpy as np
import torch

import l3e_env.detection.pipeline as pipeline_module
from l3e_env.config import FusionSettings
from l3e_env.core.threads import one_thread_per_part
from l3e_env.detection.pipeline import ONLINE_LAG
from l3e_env.envs.navigation import NavigationEnv
from l3e_env.sim.avoidance import FreeHeadings
from l3e_env.sim.follower import RouteFollower
from l3e_env.sim.raycast import EmbreeCaster

PARTS = ("scan", "ICP target", "ICP", "detector", "fusion", "local layer and follower")


class Clock:
    """CPU seconds spent in each timed part."""

    def __init__(self) -> None:
        self.spent: dict[str, float] = defaultdict(float)

    def wrap(self, part: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.spent[part] += time.process_time() - t0

        return timed


def instrumented_env(
    scene: str, detector: str, clock: Clock, keyframe_distance: float, detector_every: int
) -> NavigationEnv:
    """The evaluation's environment with each part's calls timed."""
    settings = {**asdict(FusionSettings()), "keyframe_distance": keyframe_distance, "detector_every": detector_every}
    fusion = {**settings, "enabled": True, "detector": detector}
    env = NavigationEnv(scene=scene, arrival="estimate", fusion=fusion)
    online = env.fusion
    env.lidar.scan = clock.wrap("scan", env.lidar.scan)  # type: ignore[method-assign]
    online.registrar._prepare = clock.wrap("ICP target", online.registrar._prepare)  # type: ignore[method-assign]
    pipeline_module.register = clock.wrap("ICP", pipeline_module.register)  # type: ignore[assignment]
    online.pipeline.detector.predict = clock.wrap("detector", online.pipeline.detector.predict)  # type: ignore[method-assign]
    start = online.pipeline.start

    def timed_start(T_w_b: np.ndarray, ground: np.ndarray | None = None) -> None:
        start(T_w_b, ground)
        backend = online.pipeline.backend
        backend.add_step = clock.wrap("fusion", backend.add_step)  # type: ignore[method-assign]
        backend.add_attitude = clock.wrap("fusion", backend.add_attitude)  # type: ignore[method-assign]
        if hasattr(backend, "add_ground"):  # the graph's: the EKF keeps no ground
            backend.add_ground = clock.wrap("fusion", backend.add_ground)  # type: ignore[method-assign]

    online.pipeline.start = timed_start  # type: ignore[method-assign]
    return env


def raw_cast_seconds(env: NavigationEnv, poses: list[np.ndarray]) -> float:
    """CPU seconds of one raw Embree cast of the LiDAR's revolution on one thread, the mean over `poses`."""
    caster = EmbreeCaster(env.scene.mesh, threads=1)
    directions, reach = env.lidar.pattern.directions(), env.lidar.max_range
    caster.cast(poses[0][:3, 3], directions @ poses[0][:3, :3].T, reach)  # warm up
    t0 = time.process_time()
    for T_w_s in poses:
        caster.cast(T_w_s[:3, 3], (directions @ T_w_s[:3, :3].T).astype(np.float32), reach)
    return (time.process_time() - t0) / len(poses)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bypass-100")
    parser.add_argument("--steps", type=int, default=1200)
    parser.add_argument("--detector", default="learned")
    parser.add_argument(
        "--keyframe-distance",
        type=float,
        default=FusionSettings().keyframe_distance,
        help="0: each scan registered onto the one before (default: the evaluation's)",
    )
    parser.add_argument(
        "--detector-every",
        type=int,
        default=FusionSettings().detector_every,
        help="the detector judges every K-th scan, its answer held between (default: the evaluation's)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)  # as each evaluation worker
    one_thread_per_part()
    clock = Clock()
    env = instrumented_env(args.scene, args.detector, clock, args.keyframe_distance, args.detector_every)
    local = FreeHeadings()
    follow = RouteFollower(env.route, avoid=local)

    def steer(T_w_b: np.ndarray) -> np.ndarray:
        return follow(T_w_b, FreeHeadings.obstacles(env.scan.points, env.robot.T_b_s, env.config.robot))

    policy = clock.wrap("local layer and follower", steer)
    _, info = env.reset(seed=0)
    for _ in range(20):  # warm up: compiled kernels, caches
        _, _, done, cut, info = env.step(policy(info["fused_T_w_b"]))
    clock.spent.clear()
    steps, t0, half, poses = 0, time.process_time(), 0.0, []
    while steps < args.steps:
        _, _, done, cut, info = env.step(policy(info["fused_T_w_b"]))
        steps += 1
        if steps % 10 == 0:
            poses.append(env.robot.T_w_s.copy())
        if steps == args.steps // 2:
            half = clock.spent["fusion"]
        if done or cut:
            _, info = env.reset(seed=steps)
            follow.reset()
    total = (time.process_time() - t0) / steps
    raw = raw_cast_seconds(env, poses)
    env.close()
    print(
        f"{args.scene}, detector {args.detector} every {args.detector_every} scan(s), keyframes every "
        f"{args.keyframe_distance:g} m: "
        f"{total * 1e3:.1f} ms of CPU a step over {steps} steps = {total / raw:.2f} raw casts"
    )
    rest = total - sum(clock.spent[p] for p in PARTS) / steps
    for part, spent in [*((p, clock.spent[p] / steps) for p in PARTS), ("the rest (walk, odometry)", rest)]:
        print(f"  {part:26s} {spent * 1e3:6.2f} ms  {spent / raw:5.2f} raw casts")
    second = (clock.spent["fusion"] - half) / (steps - args.steps // 2)
    print(f"the fusion over the second half: {second * 1e3:.2f} ms a step (its window full after {ONLINE_LAG} steps)")
    print(f"reference: the raw cast of the revolution, one thread: {raw * 1e3:.2f} ms (mean of {len(poses)} poses)")


if __name__ == "__main__":
    main()
