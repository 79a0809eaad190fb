"""Why scan-to-scan ICP under-reads its steps in the simulated feature-rich places, and what removes
it: the ground. A perfect plane is no real ground: its rings lie where the sensor's height puts them
wherever the sensor is, so they hold no motion, and the normals that reach across a wall's foot
lean and hold the step back (studies/icp_step_bias.py). Gravel, dirt or worn asphalt has relief.

For each place (the fork's pillared route, the mine's yard, the bypass's way round) the same scene is
registered at steps of 0.1 m forward with its ground as built (a plane) and with the ground replaced
by relief of 3 cm and of 8 cm (scenes.geometry.relief_ground); the ratio of ICP's step to the true
one is printed, 1.00 being exact, with its standard deviation over the places.

Run: python studies/ground_relief.py [--steps 10]
"""
from __future__ import annotations

import argparse

import numpy as np
import trimesh

from l3e_env.core.transforms import matrix_to_pose, planar_pose
from l3e_env.localizability.registration import register
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene
from scenes.geometry import merge, relief_ground

# scene, first x, spacing, y of the walk (None: the scene's rich route at that x)
PLACES = {"fork-0, pillared route": ("fork-0", 12.0, 3.1, 10.0), "mine-0, yard": ("mine-0", -40.0, 3.0, 0.5)}
RELIEFS = {"plane (as built)": None, "relief 3 cm": 0.03, "relief 8 cm": 0.08}


def with_ground(mesh: trimesh.Trimesh, relief: float | None) -> trimesh.Trimesh:
    """The scene with its level ground at z = 0 replaced by relief of `relief` m (None: as built)."""
    if relief is None:
        return mesh
    level = (np.abs(mesh.vertices[mesh.faces][:, :, 2]) < 1e-6).all(axis=1) & (mesh.face_normals[:, 2] > 0.999)
    rest = mesh.submesh([np.flatnonzero(~level)], append=True)
    (x0, y0, _), (x1, y1, _) = mesh.bounds
    return merge([rest, relief_ground(x0, x1, y0, y1, relief, np.random.default_rng(7))])


def step_ratios(mesh: trimesh.Trimesh, x0: float, spacing: float, y: float, steps: int) -> np.ndarray:
    lidar = Lidar(EmbreeCaster(mesh))
    rng, ratios = np.random.default_rng(0), []
    for k in range(steps):
        x = x0 + spacing * k
        before, after = planar_pose(x, y, 0.85, 0.0), planar_pose(x + 0.1, y, 0.85, 0.0)
        result = register(lidar.scan(after, rng).points, lidar.scan(before, rng).points)
        ratios.append(matrix_to_pose(result.T_target_source)[0] / 0.1)
    return np.array(ratios)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10, help="steps measured per place")
    args = parser.parse_args()
    print(f"ICP step / true step, mean (std) over {args.steps} places 0.1 m apart in x")
    print(f"{'place':26s}" + "".join(f"{name:>20s}" for name in RELIEFS))
    for place, (name, x0, spacing, y) in PLACES.items():
        mesh = make_scene(name).mesh
        cells = []
        for relief in RELIEFS.values():
            r = step_ratios(with_ground(mesh, relief), x0, spacing, y, args.steps)
            cells.append(f"{r.mean():.3f} ({r.std():.3f})")
        print(f"{place:26s}" + "".join(f"{c:>20s}" for c in cells), flush=True)


if __name__ == "__main__":
    main()
