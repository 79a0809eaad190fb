"""Where the fused estimate drifts on a bypass's feature-rich way round, and why.

Two parts:
1. `--drive`: the planner's route followed on the true pose, with the fusion in the loop (the
   learned detector, the ground plane's normals, the legs' yaw and stride biases as states, the
   IMU's tilt unless `--attitude none`), printing every few metres the estimate's error along and
   across the robot's heading, in height and heading, and the share of steps the detector masked
   each axis. Nothing is masked on the way round; the error is what scan-to-scan ICP and the legs leave.
2. The registration alone at level poses along a straight stretch of the way round (x from X0 to
   X1 at lane offset Y): one 0.1 m step forward registered, many times, with the mean error per
   step of x (as a ratio), y, roll and yaw and their standard errors. A bias of a millidegree a step
   is a degree over 60 m of walking.

Run: python studies/rich_route_drift.py --scene bypass-100 --y 14.5 --x0 62 --x1 125 [--drive --seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import asdict

import numpy as np

from l3e_env.config import FusionSettings
from l3e_env.core.transforms import matrix_to_pose, planar_pose, yaw_of
from l3e_env.localizability.registration import RegistrationConfig, register
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import make_caster
from scenes import make_scene


def step_bias(scene_name: str, y: float, x0: float, x1: float, count: int, ground_normals: bool) -> None:
    scene = make_scene(scene_name)
    lidar = Lidar(make_caster("embree", scene.mesh))
    config = dataclasses.replace(RegistrationConfig(), ground_normals=ground_normals)
    rng, steps = np.random.default_rng(0), []
    for x in np.linspace(x0, x1, count):
        before, after = planar_pose(x, y, 0.85, 0.0), planar_pose(x + 0.1, y, 0.85, 0.0)
        result = register(lidar.scan(after, rng).points, lidar.scan(before, rng).points, config)
        steps.append(matrix_to_pose(result.T_target_source))
    steps = np.array(steps)
    mean, error = steps.mean(0), steps.std(0) / np.sqrt(len(steps))
    print(
        f"ground normals {ground_normals}: x {mean[0] / 0.1:.4f} +- {error[0] / 0.1:.4f} of the step; "
        f"y {mean[1] * 1e3:.2f} +- {error[1] * 1e3:.2f} mm; z {mean[2] * 1e3:.2f} +- {error[2] * 1e3:.2f} mm; "
        f"pitch {np.degrees(mean[4]) * 1e3:.1f} +- {np.degrees(error[4]) * 1e3:.1f} mdeg; "
        f"roll {np.degrees(mean[3]) * 1e3:.1f} +- "
        f"{np.degrees(error[3]) * 1e3:.1f} mdeg; yaw {np.degrees(mean[5]) * 1e3:.1f} +- "
        f"{np.degrees(error[5]) * 1e3:.1f} mdeg a step"
    )


def drive(scene_name: str, seed: int, settings: FusionSettings) -> None:
    from l3e_env.envs import NavigationEnv
    from l3e_env.sim.avoidance import FreeHeadings
    from policies.context import scene_context
    from policies.evaluation import MapSource, make_controller

    env = NavigationEnv(scene=scene_name, fusion={**asdict(settings), "enabled": True, "detector": "learned"})
    ctx = scene_context(scene_name, "learned", None, build=False)
    steer, _ = make_controller("planner", MapSource(scene_name), 50.0, env.config.odometry, ctx, FreeHeadings())
    _, info = env.reset(seed=seed)
    rows, done = [], False
    while not done:
        obstacles = FreeHeadings.obstacles(env.scan.points, env.robot.T_b_s, env.config.robot)
        _, _, terminated, truncated, info = env.step(steer(info["T_w_b"], env.steps, obstacles))
        done = terminated or truncated
        T, F = info["T_w_b"], info["fused_T_w_b"]
        along, across = (T[:3, :3].T @ (F[:3, 3] - T[:3, 3]))[:2]
        rows.append(
            [
                *T[:2, 3],
                along,
                across,
                np.degrees(yaw_of(F) - yaw_of(T)),
                F[2, 3] - T[2, 3],
                *info["localizability_mask"],
            ]
        )
    env.close()
    rows = np.array(rows)
    walked = np.r_[0, np.cumsum(np.linalg.norm(np.diff(rows[:, :2], axis=0), axis=1))]
    print(
        f"{'walked m':>8s} {'x':>7s} {'y':>6s} {'along':>6s} {'across':>6s} {'yaw deg':>7s} {'z':>6s}  "
        "masked x y z r p yaw"
    )
    for k in range(0, len(rows), max(1, len(rows) // 20)):
        masked = " ".join(f"{m:.1f}" for m in rows[max(0, k - 50) : k + 1, 6:].mean(0))
        print(
            f"{walked[k]:8.1f} {rows[k, 0]:7.1f} {rows[k, 1]:6.1f} {rows[k, 2]:6.2f} {rows[k, 3]:6.2f} "
            f"{rows[k, 4]:7.2f} {rows[k, 5]:6.2f}  {masked}"
        )
    print(
        f"end: {walked[-1]:.1f} m walked, error along {rows[-1, 2]:.2f} m, across {rows[-1, 3]:.2f} m, "
        f"height {rows[-1, 5]:.2f} m, heading {rows[-1, 4]:.2f} deg"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bypass-100")
    parser.add_argument("--y", type=float, default=14.5, help="the lane's offset where the steps are registered")
    parser.add_argument("--x0", type=float, default=62.0)
    parser.add_argument("--x1", type=float, default=125.0)
    parser.add_argument("--steps", type=int, default=250, help="registrations along the stretch")
    parser.add_argument("--drive", action="store_true", help="also follow the planner's route with the fusion")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--attitude",
        choices=["none", "tilt"],
        default="tilt",
        help="the IMU's roll and pitch in the drive's fusion (default: tilt)",
    )
    args = parser.parse_args()
    for ground_normals in (False, True):
        step_bias(args.scene, args.y, args.x0, args.x1, args.steps, ground_normals)
    if args.drive:
        drive(args.scene, args.seed, FusionSettings(odometry_bias=("yaw", "scale"), attitude=args.attitude))


if __name__ == "__main__":
    main()
