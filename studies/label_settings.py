"""How the ICP settings shape the labels: mean absolute error and labels at fixed poses.

Run: python studies/label_settings.py [--children 40]
Each row registers M children to one parent with one registration setting and prints the mean
error (m, deg), the labels (1 = not localizable), ICP time per child and non-converged runs.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from l3e_env.core.transforms import pose_to_matrix
from l3e_env.localizability.labels import LabelConfig, registration_error
from l3e_env.localizability.registration import PreparedTarget, RegistrationConfig, register
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene

POSES = [
    ("tunnel-0", (50, 0, 0.85, 0, 0, 0), "tunnel axis x"),
    ("office-0", (5, 0, 0.85, 0, 0, 0.3), "nothing"),
    ("field-0", (40, 0, 0.85, 0, 0, 0), "x, y, yaw"),
    ("mine-0", (-30, 0.5, 0.85, 0, 0, 0), "yard: nothing"),
    ("mine-0", (50, 0, 0.85, 0, 0, 0), "tunnel: x"),
    ("mine-0", (115, 0, 0.85, 0, 0, 0), "quarry"),
]
SETTINGS = {
    "single 1.0 m, 30 it, 0.25 m voxels, all points": dict(
        max_correspondence_distance=(1.0,),
        max_iterations=30,
        downsampling_resolution=0.25,
        max_source_points=0,
        num_neighbors=10,
    ),
    "coarse-to-fine 2.0/0.5 m, 15 it, 0.3 m, 10 nb": dict(downsampling_resolution=0.3, num_neighbors=10),
    "coarse-to-fine 2.0/0.5 m, 15 it, 0.15 m, 10 nb": dict(num_neighbors=10),
    "default: 2.0/0.5 m, 15 it, 0.15 m, 20 nb, 1000 pts": dict(),
    "coarse-to-fine 5.0/1.0/0.3 m, 10 it": dict(max_correspondence_distance=(5.0, 1.0, 0.3), max_iterations=10),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--children", type=int, default=40)
    args = parser.parse_args()
    labels = LabelConfig()
    sigma, thr = labels.sigma_vector("child"), labels.threshold_vector()
    lidars = {name: Lidar(EmbreeCaster(make_scene(name).mesh, threads=1)) for name in {p[0] for p in POSES}}
    for frame in ("parent", "child"):
        for title, overrides in SETTINGS.items():
            if frame == "child" and not title.startswith("default"):
                continue
            cfg = RegistrationConfig(**{**RegistrationConfig().__dict__, **overrides})
            print(f"\n{title}; error in the {frame} frame")
            for scene, pose, expected in POSES:
                rng = np.random.default_rng(0)
                T_p = pose_to_matrix(np.array(pose, dtype=float))
                target = PreparedTarget(lidars[scene].scan(T_p, rng).points, cfg)
                errs, t, bad = [], 0.0, 0
                for _ in range(args.children):
                    T_pc = pose_to_matrix(rng.normal(0, 1, 6) * sigma)
                    child = lidars[scene].scan(T_p @ T_pc, rng).points
                    t0 = time.perf_counter()
                    res = register(child, target, cfg, with_hessian=False)
                    t += time.perf_counter() - t0
                    bad += not res.converged
                    errs.append(registration_error(res.T_target_source, T_pc, frame))
                e = np.mean(errs, axis=0)
                shown = np.concatenate([e[:3], np.degrees(e[3:])])
                print(
                    f"  {scene:9s} x={pose[0]:5.0f}  error {np.array2string(shown, precision=2, floatmode='fixed')}  "
                    f"labels {(e > thr).astype(int)}  (expected {expected})  {t / args.children * 1e3:5.1f} ms/ICP  "
                    f"{bad} not converged"
                )


if __name__ == "__main__":
    main()
