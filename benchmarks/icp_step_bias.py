"""How far scan-to-scan ICP (identity start) under-estimates one 0.1 m step forward, at level
poses of the fork: in its smooth corridor, between the corridor and the pillars, and on the
pillared route. A bias here accumulates into the fused estimate wherever ICP is trusted on x.

The shipped settings are measured against the earlier 0.3 m voxel / 10-neighbour setting as
the reference, in the same run, and once more with the source's ground points (more than
0.6 m below the sensor, which is 0.85 m above the floor) left out: the ground's rings move with
the sensor, and where a ring's normals lean off vertical they hold ICP to zero motion.

Run: python benchmarks/icp_step_bias.py [--steps 10]
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from l3e_env.lidar import Lidar
from l3e_env.raycast import make_caster
from l3e_env.registration import RegistrationConfig, register
from l3e_env.transforms import matrix_to_pose, planar_pose
from scenes import make_scene

GROUND_BELOW = -0.6  # m in the sensor frame
PLACES = {"corridor (y = 0)": 0.0, "beside the corridor (y = 5)": 5.0, "pillared route (y = 10)": 10.0}
SETTINGS = {  # title: (config, drop the source's ground points)
    "reference: 0.3 m voxels, 10 neighbours": (dataclasses.replace(
        RegistrationConfig(), downsampling_resolution=0.3, num_neighbors=10), False),
    "shipped default": (RegistrationConfig(), False),
    "shipped default, source without ground": (RegistrationConfig(), True),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10, help="steps measured per place")
    args = parser.parse_args()
    scene = make_scene("fork-0")
    lidar = Lidar(make_caster("embree", scene.mesh))
    for title, (config, no_ground) in SETTINGS.items():
        rng = np.random.default_rng(0)
        print(f"\n{title}")
        print(f"{'place':30s} {'true step':>10s} {'ICP step':>9s} {'ratio':>6s} {'std':>6s} {'ms/ICP':>7s}")
        for place, y in PLACES.items():
            est, seconds = [], 0.0
            for k in range(args.steps):
                x = 12.0 + 3.1 * k
                before, after = planar_pose(x, y, 0.85, 0.0), planar_pose(x + 0.1, y, 0.85, 0.0)
                target, source = lidar.scan(before, rng).points, lidar.scan(after, rng).points
                if no_ground:
                    source = source[source[:, 2] > GROUND_BELOW]
                t0 = time.perf_counter()
                res = register(source, target, config)
                seconds += time.perf_counter() - t0
                est.append(matrix_to_pose(res.T_target_source)[0])
            print(f"{place:30s} {0.1:10.3f} {np.mean(est):9.3f} {np.mean(est) / 0.1:6.2f} {np.std(est):6.3f} "
                  f"{seconds / args.steps * 1e3:7.1f}")


if __name__ == "__main__":
    main()
