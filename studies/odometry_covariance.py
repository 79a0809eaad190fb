"""How well the covariance written with /odom (`DeadReckoningCovariance`) states the leg odometry's drift.

Run: python studies/odometry_covariance.py [--runs 400] [--steps 1000]

A 10 Hz walk at 1 m/s, straight and on a 5 m circle, is dead-reckoned by `LegOdometry` with
`--runs` seeds; the spread of the end pose's error (position in the odometry frame, rotation about
its axes) is the reference the propagated standard deviations are printed against, beside a model
that takes each step's noise (`odometry_sigmas`) as white.
"""

from __future__ import annotations

import argparse

import numpy as np

from l3e_env.config import OdometryConfig
from l3e_env.core.transforms import adjoint, inverse, matrix_to_pose, planar_pose
from l3e_env.sim.odometry import DeadReckoningCovariance, LegOdometry, odometry_sigmas


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=400)
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    print(f"{'walk':12s} {'':22s}" + "".join(f"{a:>8s}" for a in ("x", "y", "z", "roll", "pitch", "yaw")))
    for name, step in (("straight", planar_pose(0.1, 0, 0, 0)), ("5 m circle", planar_pose(0.1, 0, 0, 0.02))):
        covariance, white, truth = DeadReckoningCovariance(), np.zeros((6, 6)), np.eye(4)
        for _ in range(args.steps):
            truth = truth @ step
            P, _ = covariance.step(step, truth, 0.1)
            back = adjoint(inverse(step))
            white = back @ white @ back.T + np.diag(odometry_sigmas(step, OdometryConfig()) ** 2)
        rotate = np.kron(np.eye(2), truth[:3, :3])
        ends = []
        for run in range(args.runs):
            odometry, T_odom, T_true = LegOdometry(rng=np.random.default_rng(run)), np.eye(4), np.eye(4)
            for _ in range(args.steps):
                T_odom, T_true = T_odom @ odometry.measure(T_true, T_true @ step), T_true @ step
            error = np.eye(4)
            error[:3, :3] = T_odom[:3, :3] @ T_true[:3, :3].T
            ends.append(np.r_[T_odom[:3, 3] - T_true[:3, 3], matrix_to_pose(error)[3:]])
        rows = (
            ("drift's spread", np.std(ends, axis=0)),
            ("propagated", np.sqrt(np.diag(P))),
            ("white steps only", np.sqrt(np.diag(rotate @ white @ rotate.T))),
        )
        for label, values in rows:
            print(f"{name:12s} {label:22s}" + "".join(f"{v:8.3f}" for v in values))


if __name__ == "__main__":
    main()
