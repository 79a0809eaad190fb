"""The scan's own estimate against the scene's Monte-Carlo labels along z, at one pose of a scene's
route at several sensor heights: where the scan's mesh ends and the scene's ground goes on (open
fields, yards, pipe racks), does `scanmc` lose the vertical axis that the scene's ground keeps?

Printed per scene and height: the mean z error over its threshold from the scene's children and from
the scan's own estimate, and the same for x beside it.

Run: python studies/scan_mc_open_ground.py [--scenes piperack-0,field-0,yard-0,fork-0] [--heights 0.5,0.85,1.2]
     [--ground-reach 0]
"""

from __future__ import annotations

import argparse

import numpy as np

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import level_rotation_of, pose_to_matrix
from l3e_env.localizability.labels import LabelConfig, label_parent
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.localizability.scan_mc import ScanMCConfig, scan_errors
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="piperack-0,piperack-3,field-0,yard-0,fork-0")
    parser.add_argument("--heights", default="0.5,0.85,1.2")
    parser.add_argument("--children", type=int, default=40)
    parser.add_argument(
        "--ground-reach", type=float, default=ScanMCConfig().ground_reach, help="0: the scan's mesh alone, as before"
    )
    args = parser.parse_args()
    thresholds = LabelConfig().threshold_vector()
    print("| scene | sensor height (m) | z: scene / scanmc (error over threshold) | x: scene / scanmc |")
    print("|---|---|---|---|")
    for name in args.scenes.split(","):
        scene = make_scene(name)
        lidar = Lidar(EmbreeCaster(scene.mesh), LidarConfig())
        at = scene.route[len(scene.route) // 2]
        for height in map(float, args.heights.split(",")):
            T_w_s = pose_to_matrix(np.array([at[0], at[1], at[2] + height, 0.0, 0.0, 0.2]))
            label = label_parent(
                lidar, T_w_s, np.random.default_rng(0), LabelConfig(children=args.children), RegistrationConfig()
            )
            own = scan_errors(
                label.points,
                LidarConfig(),
                RegistrationConfig(),
                LabelConfig(),
                ScanMCConfig(ground_reach=args.ground_reach),
                np.random.default_rng(0),
                level_rotation_of(T_w_s),
            ).errors
            ratio, mine = label.errors / thresholds, own / thresholds
            print(f"| {name} | {height:g} | {ratio[2]:.2f} / {mine[2]:.2f} | {ratio[0]:.2f} / {mine[0]:.2f} |")


if __name__ == "__main__":
    main()
