"""Does registering each scan to a keyframe, rather than to the scan before, cut the drift that the
registration's own bias a step leaves on a navigation route?

The planner's route of one bypass variant is walked on the true pose (scans at an instant, no
fusion), and the scans and the leg odometry's increments are kept. Then ICP alone is chained along
it: each scan registered to the scan before from identity (as the fusion does), or to the last
keyframe, from the chain's own estimate of the pose since the keyframe advanced by the odometry's
increment (the fine stage of its
matching only), with a new keyframe every K steps. For each, the chained pose's error at the end (along
and across the final heading, and of heading), against the path's length.

Run: python studies/keyframe_drift.py --scene bypass-100 [--every 1,5,10,20]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from l3e_env.core.transforms import inverse, nearest_rigid, yaw_of
from l3e_env.envs import NavigationEnv
from l3e_env.localizability.registration import PreparedTarget, RegistrationConfig, register
from l3e_env.sim.avoidance import FreeHeadings
from policies.context import scene_context
from policies.evaluation import MapSource, make_controller


def walk(scene: str, seed: int) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], np.ndarray]:
    """The planner's route on the true pose: true body poses, scans (sensor frame) and odometry
    increments (body frame), one per step, and the sensor's mounting T_b_s."""
    env = NavigationEnv(scene=scene, lidar={"sweep": False})
    ctx = scene_context(scene, "learned", None, build=False)
    steer, _ = make_controller("planner", MapSource(scene), 50.0, env.config.odometry, ctx, FreeHeadings())
    _, info = env.reset(seed=seed)
    poses, scans, odometry = [info["T_w_b"]], [env.scan.points.copy()], [np.eye(4)]
    done, odom = False, info["odom_T_w_b"]
    while not done:
        obstacles = FreeHeadings.obstacles(env.scan.points, env.robot.T_b_s, env.config.robot)
        _, _, terminated, truncated, info = env.step(steer(info["T_w_b"], env.steps, obstacles))
        done = terminated or truncated
        poses.append(info["T_w_b"])
        scans.append(env.scan.points.copy())
        odometry.append(inverse(odom) @ info["odom_T_w_b"])
        odom = info["odom_T_w_b"]
    T_b_s = env.robot.T_b_s
    env.close()
    return poses, scans, odometry, T_b_s


def chain(
    poses: list[np.ndarray], scans: list[np.ndarray], odometry: list[np.ndarray], T_b_s: np.ndarray, every: int
) -> list[np.ndarray]:
    """ICP chained along the walk with a keyframe every `every` steps (1: scan to scan, from identity)."""
    config = RegistrationConfig()
    # from a guess the coarse stage's 2 m matches pull a weakly held axis into another basin: the
    # fine stage alone (its matches within 0.5 m) from the guess
    matching = config if every == 1 else dataclasses.replace(config, max_correspondence_distance=(0.5,))
    estimate = [poses[0]]
    key, target = 0, PreparedTarget(scans[0], config)
    for k in range(1, len(scans)):
        if every == 1:
            guess = np.eye(4)
        else:  # the chain's pose since the keyframe, advanced by the legs' step, in the sensor's frame
            body = inverse(estimate[key]) @ estimate[k - 1] @ odometry[k]
            guess = inverse(T_b_s) @ body @ T_b_s
        result = register(scans[k], target, matching, init_T_target_source=guess, with_hessian=False)
        step = (
            T_b_s @ result.T_target_source @ inverse(T_b_s)
            if result.converged
            else inverse(estimate[key]) @ (estimate[k - 1] @ odometry[k])
        )
        estimate.append(nearest_rigid(estimate[key] @ step))
        if k - key >= every:
            key, target = k, PreparedTarget(scans[k], config)
    return estimate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bypass-100")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--every", default="1,5,10,20", help="keyframe spacings in steps, comma-separated")
    args = parser.parse_args()
    poses, scans, odometry, T_b_s = walk(args.scene, args.seed)
    length = sum(np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in zip(poses[:-1], poses[1:]))
    print(f"{args.scene}: {len(poses) - 1} steps, {length:.1f} m walked")
    for every in (int(e) for e in args.every.split(",")):
        end = chain(poses, scans, odometry, T_b_s, every)[-1]
        error = inverse(poses[-1]) @ end
        along, across, up = error[:3, 3]
        print(
            f"keyframe every {every:3d} steps: end {np.linalg.norm(error[:3, 3]):.2f} m off "
            f"({100 * np.linalg.norm(error[:3, 3]) / length:.2f}% of the path): along {along:.2f}, "
            f"across {across:.2f}, height {up:.2f} m, heading {np.degrees(yaw_of(error)):.2f} deg"
        )


if __name__ == "__main__":
    main()
