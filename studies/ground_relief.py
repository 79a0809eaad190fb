"""Why scan-to-scan ICP under-reads its steps in the simulated feature-rich places, and what removes
it: the ground. A perfect plane is no real ground: its rings lie where the sensor's height puts them
wherever the sensor is, so they hold no motion, and the normals that reach across a wall's foot
lean and hold the step back (studies/icp_step_bias.py). Gravel, dirt or worn asphalt has relief.

For each place (the fork's pillared route, the mine's yard, the bypass's way round) the same scene is
registered at steps of 0.1 m forward with its ground as built (a plane) and with the ground replaced
by relief of 3 cm and of 8 cm (`relief_ground`); the ratio of ICP's step to the true
one is printed, 1.00 being exact, with its standard deviation over the places.

The last table drives 40 m of the mine's yard (level poses 0.1 m apart along its route, one scan
each) and sums the steps that scan-to-scan ICP and KISS-ICP (its authors' defaults, needs
`pip install -e ".[baselines]"`) register, as a share of the true distance, over the plane and over
relief: whether the same ground handicaps the point-to-point registration too.

Run: python studies/ground_relief.py [--steps 10] [--yard-steps 400]
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
from scenes.geometry import ground_plane, merge, smooth_noise

# scene, first x, spacing, y of the walk (None: the scene's rich route at that x)
PLACES = {"fork-0, pillared route": ("fork-0", 12.0, 3.1, 10.0), "mine-0, yard": ("mine-0", -40.0, 3.0, 0.5)}
RELIEFS = {"plane (as built)": None, "relief 3 cm": 0.03, "relief 8 cm": 0.08}


def relief_ground(
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    amplitude: float,
    rng: np.random.Generator,
    wavelengths: tuple[float, float] = (0.5, 4.0),
    cell: float = 0.3,
) -> trimesh.Trimesh:
    """Ground with the relief of gravel, dirt or worn asphalt: a grid of `cell` m whose height is a
    smooth random field of `amplitude` m on `wavelengths` m."""
    ground = ground_plane(x0, x1, y0, y1, cell=cell)
    vertices = np.array(ground.vertices)
    vertices[:, 2] = smooth_noise(rng, amplitude, wavelengths=wavelengths, waves=24)(vertices)
    ground.vertices = vertices
    return ground


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


def yard_distance_ratios(mesh: trimesh.Trimesh, route: np.ndarray, steps: int) -> tuple[float, float]:
    """(scan-to-scan ICP, KISS-ICP): registered distance over true distance along `steps` poses of
    the route 0.1 m apart, heading along it."""
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    from scenes.geometry import resample_polyline

    xy = resample_polyline(route, 0.1)[: steps + 1, :2]
    heading = np.arctan2(np.gradient(xy[:, 1]), np.gradient(xy[:, 0]))
    poses = [planar_pose(x, y, 0.85, h) for (x, y), h in zip(xy, heading)]
    lidar = Lidar(EmbreeCaster(mesh))
    rng = np.random.default_rng(0)
    scans = [lidar.scan(T, rng).points for T in poses]
    true = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
    icp = sum(np.linalg.norm(register(b, a).T_target_source[:3, 3]) for a, b in zip(scans[:-1], scans[1:]))
    config = load_config(None)
    config.data.deskew, config.data.max_range = False, lidar.max_range
    config.mapping.voxel_size = lidar.max_range / 100.0
    kiss, walked = KissICP(config), []
    for scan in scans:
        kiss.register_frame(scan.astype(np.float64), np.zeros(len(scan)))
        walked.append(kiss.last_pose[:3, 3].copy())
    return icp / true, float(np.linalg.norm(np.diff(np.array(walked), axis=0), axis=1).sum()) / true


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10, help="steps measured per place")
    parser.add_argument("--yard-steps", type=int, default=400, help="steps of 0.1 m driven in the mine's yard")
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
    mine = make_scene("mine-0")
    print(f"\nregistered distance / true distance over {args.yard_steps / 10:.0f} m of the mine's yard")
    print(f"{'ground':20s} {'scan-to-scan ICP':>17s} {'KISS-ICP':>9s}")
    for name, relief in RELIEFS.items():
        icp, kiss = yard_distance_ratios(with_ground(mine.mesh, relief), mine.route, args.yard_steps)
        print(f"{name:20s} {icp:17.3f} {kiss:9.3f}", flush=True)


if __name__ == "__main__":
    main()
