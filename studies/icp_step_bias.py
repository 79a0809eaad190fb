"""How far scan-to-scan ICP (identity start) under-estimates one 0.1 m step forward, at level
poses of the fork: in its smooth corridor, between the corridor and the pillars, and on the
pillared route. A bias here accumulates into the fused estimate wherever ICP is trusted on x.

The shipped settings are measured against the earlier 0.3 m voxel / 10-neighbour setting as
the reference, in the same run, and once more with the source's ground points (more than
0.6 m below the sensor, which is 0.85 m above the floor) left out: the ground's rings move with
the sensor, and where a ring's normals lean off vertical they hold ICP to zero motion.

The last rows find the cause. The same point-to-plane ICP, written out in numpy (same voxels,
source thinning and stages), is run on the same scans with four sets of target normals: estimated
from 20 neighbours as small_gicp does; with each target voxel's true normal, that of the mesh face
its ray hits; with the ground's voxels (within 5 cm of the plane fitted to the low returns) given
that plane's normal; and voted: each voxel takes the normal, among its 20 neighbours' own, that
the most of those neighbours lie on (within 2 cm), so that a neighbourhood reaching across a corner
keeps the surface the voxel is on. With the true normals the bias is gone; the estimated ones lean
where a neighbourhood reaches across a corner (the ground beside a wall's foot).

Run: python studies/icp_step_bias.py [--steps 10]
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
import small_gicp
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import make_caster
from l3e_env.localizability.registration import RegistrationConfig, prepare_source, register
from l3e_env.core.transforms import matrix_to_pose, planar_pose
from scenes import make_scene

GROUND_BELOW = -0.6  # m in the sensor frame
PLACES = {"corridor (y = 0)": 0.0, "beside the corridor (y = 5)": 5.0, "pillared route (y = 10)": 10.0}
SETTINGS = {  # title: (config, drop the source's ground points)
    "reference: 0.3 m voxels, 10 neighbours": (dataclasses.replace(
        RegistrationConfig(), downsampling_resolution=0.3, num_neighbors=10), False),
    "shipped default": (RegistrationConfig(), False),
    "shipped default, source without ground": (RegistrationConfig(), True),
}


def estimated_normals(points: np.ndarray, neighbours: int) -> np.ndarray:
    """Each point's normal from its neighbours' scatter (smallest eigenvector), as small_gicp does."""
    _, idx = cKDTree(points).query(points, neighbours)
    centred = points[idx] - points[idx].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))[1][:, :, 0]


def ground_plane_normals(points: np.ndarray, normals: np.ndarray, band: float = 0.05) -> np.ndarray:
    """`normals` with those of the voxels within `band` of the ground plane replaced by its normal: the
    plane z = a x + b y + c fitted by least squares to the returns more than 0.5 m below the sensor,
    refitted three times to those within `band` of it."""
    low = points[points[:, 2] < -0.5]
    fit = low[np.abs(low[:, 2] - np.median(low[:, 2])) < 0.2]
    for _ in range(3):
        coef = np.linalg.lstsq(np.c_[fit[:, :2], np.ones(len(fit))], fit[:, 2], rcond=None)[0]
        fit = low[np.abs(low[:, 2] - np.c_[low[:, :2], np.ones(len(low))] @ coef) < band]
    normal = np.array([-coef[0], -coef[1], 1.0]) / np.linalg.norm([-coef[0], -coef[1], 1.0])
    out = normals.copy()
    out[np.abs(points[:, 2] - np.c_[points[:, :2], np.ones(len(points))] @ coef) < band] = normal
    return out


def voted_normals(points: np.ndarray, neighbours: int, tolerance: float = 0.02) -> np.ndarray:
    """Each voxel's normal: of its neighbours' estimated normals, the one whose plane through the
    voxel holds the most of the neighbours within `tolerance` (m)."""
    _, idx = cKDTree(points).query(points, neighbours)
    candidates = estimated_normals(points, neighbours)[idx]  # (N, k, 3)
    offsets = points[idx] - points[:, None, :]
    votes = (np.abs(np.einsum("nci,nki->nck", candidates, offsets)) < tolerance).sum(axis=2)
    return candidates[np.arange(len(points)), votes.argmax(axis=1)]


def mesh_normals(mesh, origin: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The normal of the face each sensor-frame point's ray hits (the sensor is level, so only shifted)."""
    faces = mesh.ray.intersects_first(np.repeat(origin[None], len(points), 0),
                                      points / np.linalg.norm(points, axis=1, keepdims=True))
    return mesh.face_normals[np.maximum(faces, 0)]


def plane_icp(source: np.ndarray, target: np.ndarray, normals: np.ndarray, config: RegistrationConfig) -> float:
    """Gauss-Newton point-to-plane ICP from identity with given target normals; returns the x step.
    Hand-written because small_gicp estimates its own normals and cannot be handed others."""
    tree, T = cKDTree(target), np.eye(4)
    for distance in config.max_correspondence_distance:
        for _ in range(config.max_iterations):
            moved = source @ T[:3, :3].T + T[:3, 3]
            gap, idx = tree.query(moved)
            near = gap < distance
            n, p = normals[idx[near]], moved[near]
            r = np.sum(n * (p - target[idx[near]]), axis=1)
            J = np.hstack([np.cross(p, n), n])
            delta = np.linalg.lstsq(J, -r, rcond=1e-9)[0]  # a degenerate axis (the corridor's x) stays put
            step = np.eye(4)
            step[:3, :3], step[:3, 3] = Rotation.from_rotvec(delta[:3]).as_matrix(), delta[3:]
            T = step @ T
            if np.linalg.norm(delta) < 1e-5:
                break
    return float(T[0, 3])


def normals_rows(scene, lidar: Lidar, steps: int) -> None:
    config = RegistrationConfig()
    print("\nthe same ICP in numpy, ratio of ICP step to true step (std) with each set of target normals")
    kinds = ["estimated", "true (mesh)", "ground plane", "voted"]
    print(f"{'place':30s}" + "".join(f"{k:>16s}" for k in kinds))
    for place, y in PLACES.items():
        rng, steps_by = np.random.default_rng(0), []
        for k in range(steps):
            x = 12.0 + 3.1 * k
            before, after = planar_pose(x, y, 0.85, 0.0), planar_pose(x + 0.1, y, 0.85, 0.0)
            target = np.asarray(small_gicp.voxelgrid_sampling(
                lidar.scan(before, rng).points.astype(np.float64), config.downsampling_resolution).points())[:, :3]
            source = np.asarray(prepare_source(lidar.scan(after, rng).points, config).points())[:, :3]
            estimated = estimated_normals(target, config.num_neighbors)
            normals = [estimated, mesh_normals(scene.mesh, before[:3, 3], target),
                       ground_plane_normals(target, estimated), voted_normals(target, config.num_neighbors)]
            steps_by.append([plane_icp(source, target, n, config) / 0.1 for n in normals])
        ratios = np.array(steps_by)
        print(f"{place:30s}" + "".join(f"{m:10.3f} ({s:.3f})" for m, s in zip(ratios.mean(0), ratios.std(0))))


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
    normals_rows(scene, lidar, args.steps)


if __name__ == "__main__":
    main()
