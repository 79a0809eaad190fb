"""The same children's errors written in the parent sensor's frame and in its level frame (label
protocol 3), at single parents of a scene tilted by given roll and pitch: what the sensor's tilt does
to a tunnel's labels in each frame.

Each child is drawn along the level frame's axes (as protocol 3 draws them), registered to its parent
with the default registration, and its error transform written both ways; the table gives the mean
absolute translation errors (cm) and the labels (0.04 m, 2 deg) in each frame.

Run: python studies/level_frame_labels.py [--scene tunnel-0] [--children 40] [--tilts 0,0 0,3 0,8 10,10]
"""

from __future__ import annotations

import argparse

import numpy as np

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import level_rotation_of, pose_to_matrix
from l3e_env.localizability.labels import AXES, LabelConfig, child_offset, registration_error
from l3e_env.localizability.registration import (
    PreparedTarget,
    RegistrationConfig,
    RegistrationError,
    prepare_source,
    register,
)
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def errors_both_ways(lidar: Lidar, T_w_p: np.ndarray, children: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean absolute errors (6,) of the same children in the sensor's frame and in the level frame."""
    config, registration = LabelConfig(children=children), RegistrationConfig()
    rng = np.random.default_rng(seed)
    target = PreparedTarget(lidar.scan(T_w_p, rng).points, registration)
    R_l_s, sigma = level_rotation_of(T_w_p), config.sigma_vector("child")
    sensor, level = [], []
    for _ in range(children):
        T_p_c = child_offset(rng, sigma, R_l_s)
        try:
            found = register(prepare_source(lidar.scan(T_w_p @ T_p_c, rng).points, registration), target, registration)
        except RegistrationError:
            continue
        sensor.append(registration_error(found.T_target_source, T_p_c))
        level.append(registration_error(found.T_target_source, T_p_c, R_l_s=R_l_s))
    return np.mean(sensor, axis=0), np.mean(level, axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="tunnel-0")
    parser.add_argument("--children", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tilts", nargs="+", default=["0,0", "0,3", "0,8", "10,10"], help="roll,pitch in degrees")
    args = parser.parse_args()
    scene = make_scene(args.scene)
    lidar = Lidar(EmbreeCaster(scene.mesh, threads=1), LidarConfig())
    path = scene.sampling_paths[0]
    ground = path[len(path) // 2]
    heading = float(np.arctan2(*(path[-1, 1::-1] - path[0, 1::-1])))  # along the path
    thresholds = LabelConfig().threshold_vector()
    print(f"{args.scene}, {args.children} children, heading along the path; errors in cm")
    header = f"{'sensor frame x / y / z':>24s} {'labels':>12s} | {'level frame x / y / z':>24s} labels"
    print(f"{'roll, pitch':>12s} | {header}")
    for tilt in args.tilts:
        roll, pitch = (np.radians(float(v)) for v in tilt.split(","))
        T = pose_to_matrix([*ground[:2], ground[2] + LabelConfig().sensor_height, roll, pitch, heading])
        sensor, level = errors_both_ways(lidar, T, args.children, args.seed)
        cells = []
        for e in (sensor, level):
            flagged = ", ".join(a for a, f in zip(AXES, e > thresholds) if f) or "none"
            cells.append(f"{' / '.join(f'{100 * v:.1f}' for v in e[:3]):>24s} {flagged:>12s}")
        print(f"{tilt:>12s} | {cells[0]} | {cells[1]}")


if __name__ == "__main__":
    main()
