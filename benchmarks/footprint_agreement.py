"""How often the fast environment's footprint (policies.footprint) disagrees with the simulated
robot's own PyBullet collision check, at random poses near obstacles.

    python benchmarks/footprint_agreement.py --scene fork-0 --scene fork-104 --poses 3000

Prints, per scene, the share of poses the footprint lets through although the base box collides
(it should be 0) and the share it refuses although the box fits (the raster's margin).
"""
from __future__ import annotations

import argparse

import numpy as np

from l3e_env.config import RobotConfig
from l3e_env.world import World
from policies.context import free_space
from policies.footprint import build_footprint
from scenes import make_scene


def agreement(scene_name: str, poses: int, near: float, seed: int) -> tuple[int, float, float]:
    """(poses drawn with ground under them, share let through colliding, share refused fitting)."""
    scene = make_scene(scene_name)
    space = free_space(scene)
    footprint = build_footprint(scene, space)
    cells = np.argwhere(space.free & (space.clearance <= near))
    rng = np.random.default_rng(seed)
    world = World(scene, RobotConfig())
    through = refused = n = 0
    try:
        for _ in range(poses):
            x, y = space.center(cells[rng.integers(len(cells))]) + rng.uniform(-0.25, 0.25, 2)
            yaw = rng.uniform(-np.pi, np.pi)
            T = world.ground_pose(x, y, yaw, float(scene.route[0, 2]))
            if T is None:
                continue
            collides, blocked = world.in_collision(T), footprint.collides(x, y, yaw)
            n += 1
            through += collides and not blocked
            refused += blocked and not collides
    finally:
        world.close()
    return n, through / max(n, 1), refused / max(n, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", action="append", help="scenes (default: fork-0 and fork-104)")
    parser.add_argument("--poses", type=int, default=3000)
    parser.add_argument("--near", type=float, default=1.0, help="largest clearance (m) of the cells drawn")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for name in args.scene or ["fork-0", "fork-104"]:
        n, through, refused = agreement(name, args.poses, args.near, args.seed)
        print(f"{name}: {n} poses; let through colliding {through:.2%}; refused fitting {refused:.2%}")


if __name__ == "__main__":
    main()
