"""What a swept revolution costs scan-to-scan ICP, step by step, and what deskewing gives back.

The sensor walks through the mine's yard towards the portal along two scripted paths: a steady one
(straight on at 0.5 m/s, as most of the mine route) and a weaving one whose yaw rate swings between
+-1 rad/s every 3 s while its speed swings between 0.1 and 0.9 m/s. At every step each pair of
consecutive revolutions is registered (identity start, the shipped settings) and the result
compared with the true step:

- static: each revolution taken at one pose (the labels' and datasets' scans);
- swept, as they are: each ray cast from the pose at its firing time, not deskewed;
- deskewed with the step's leg odometry;
- deskewed with the odometry averaged over the last steps (`lidar.deskew_motion`);
- deskewed with the gyro's rotation over the step and that averaged odometry's translation (what
  `l3e ate` and the environment's fusion do by default, as LiDAR-inertial odometry does);
- deskewed with the true motion (the best any deskewing can do).

Swept scans register to the motion between the middles of the two revolutions, so on a steady
path their error is small and, while the motion changes, large but cancelling from step to step:
the middles are half a revolution behind the ends at every step alike, so the summed yaw is off
by about the half revolution's turn at the path's ends, not by the sum of the steps' errors.

Run: python studies/deskew_step_error.py [--steps 300]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from l3e_env.core.transforms import inverse, matrix_to_pose, planar_pose
from l3e_env.localizability.registration import RegistrationConfig, register
from l3e_env.sim.imu import StepGyro
from l3e_env.sim.lidar import DESKEW_STEPS, Lidar, deskew, deskew_motion
from l3e_env.sim.odometry import LegOdometry
from l3e_env.sim.raycast import make_caster
from scenes import make_scene

DT = 0.1  # s, one revolution a step
SENSOR_HEIGHT = 0.85  # m above the start's ground


def scripted_path(start: np.ndarray, steps: int, weaving: bool) -> list[np.ndarray]:
    """Sensor poses every DT along a steady or a weaving walk from `start` (x, y, yaw)."""
    t = DT * np.arange(steps + 1)
    yaw_rate = np.cos(2 * np.pi * t / 3.0) if weaving else np.zeros_like(t)  # heading weaves about the start's
    speed = 0.5 + 0.4 * np.sin(2 * np.pi * t / 5.0) if weaving else np.full_like(t, 0.5)
    x, y, yaw = (float(v) for v in start)
    poses = []
    for k in range(steps + 1):
        poses.append(planar_pose(x, y, SENSOR_HEIGHT, yaw))
        x, y, yaw = x + speed[k] * DT * np.cos(yaw), y + speed[k] * DT * np.sin(yaw), yaw + yaw_rate[k] * DT
    return poses


def step_errors(scans: list[np.ndarray], truth: list[np.ndarray], config: RegistrationConfig) -> np.ndarray:
    """ICP step - true step of every consecutive pair, (steps, 6) in project order."""
    return np.array(
        [
            matrix_to_pose(inverse(step) @ register(after, before, config).T_target_source)
            for before, after, step in zip(scans, scans[1:], truth)
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="steps along each path")
    args = parser.parse_args()
    scene = make_scene("mine-0")
    lidar, config = Lidar(make_caster("embree", scene.mesh)), RegistrationConfig()
    for weaving in (False, True):
        t0 = time.perf_counter()
        poses = scripted_path(np.asarray(scene.start), args.steps, weaving)
        rng, odometry = np.random.default_rng(0), LegOdometry(rng=np.random.default_rng(1))
        truth = [inverse(a) @ b for a, b in zip(poses, poses[1:])]
        odo = [odometry.measure(a, b) for a, b in zip(poses, poses[1:])]
        static = [lidar.scan(T, rng).points for T in poses]
        swept = [lidar.scan(poses[0], rng, start=poses[0]).points]  # the first revolution standing
        swept += [lidar.scan(after, rng, start=before).points for before, after in zip(poses, poses[1:])]
        recent = [odo[max(0, k + 1 - DESKEW_STEPS) : k + 1] for k in range(len(odo))]  # each step's last steps
        averaged = [deskew_motion(steps) for steps in recent]
        gyro = StepGyro(rng=np.random.default_rng(2))  # the sensor's own rotation: no mounting to turn it by
        inertial = [
            deskew_motion(steps, gyro.measure(a[:3, :3], b[:3, :3], DT))
            for steps, a, b in zip(recent, poses, poses[1:])
        ]
        cases = {"static": static, "swept, as they are": swept}
        for name, motions in (
            ("deskewed, the step's odometry", odo),
            (f"deskewed, odometry of {DESKEW_STEPS} steps", averaged),
            ("deskewed, gyro and odometry", inertial),
            ("deskewed, the true motion", truth),
        ):
            cases[name] = swept[:1] + [deskew(s, m, lidar.pattern) for s, m in zip(swept[1:], motions)]
        print(f"\n{'weaving' if weaving else 'steady'} path, {args.steps} steps: mean |ICP step - true step|")
        print(
            f"{'scans':34s} {'x mm':>6s} {'y mm':>6s} {'z mm':>6s} {'roll':>6s} {'pitch':>6s} {'yaw mdeg':>8s} "
            f"{'summed yaw':>12s}"
        )
        for name, scans in cases.items():
            errors = step_errors(scans, truth, config)
            size = np.abs(errors).mean(axis=0)
            print(
                f"{name:34s} "
                + " ".join(f"{1e3 * size[i]:6.2f}" for i in range(3))
                + " "
                + " ".join(f"{1e3 * np.degrees(size[i]):6.1f}" for i in (3, 4, 5))
                + f" {np.degrees(errors[:, 5].sum()):8.2f} deg",
                flush=True,
            )
        print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
