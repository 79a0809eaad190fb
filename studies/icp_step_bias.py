"""How truly scan-to-scan ICP (identity start) reads one 0.1 m step forward, along every scene
family's route: the ratio of ICP's step to the true one. A bias here accumulates into the fused
estimate wherever ICP is trusted along the step.

The sensor is level at its height over the route, facing along it; the child scan is cast 0.1 m
ahead. Steps along a free axis (a tunnel's, an open plane's) say nothing of bias: a step is left out
where ICP handed the mesh's true normals reads it more than 10% off, and the
table counts them.

Each row set runs the same numpy point-to-plane ICP (the registration's own stages, thinning and
guard) with other target normals:
- `neighbours`: from the 20 nearest voxels, as small_gicp estimates them;
- `ground`: the ground's voxels given the normal of the plane fitted to the low returns;
- `true`: each voxel's mesh face normal (the face its ray hits): the reference.
and the registration as configured (`RegistrationConfig()`, the default).

Run: python studies/icp_step_bias.py [--steps 12] [--families tunnel,mine,...]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from l3e_env.core.transforms import matrix_to_pose, planar_pose
from l3e_env.localizability.registration import (
    PreparedTarget,
    RegistrationConfig,
    _plane_icp,
    ground_plane,
    ground_voxels,
    prepare_source,
    register,
)
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import make_caster
from scenes import make_scene

FAMILIES = (
    "office",
    "cave",
    "mine",
    "fork",
    "gallery",
    "yard",
    "chamber",
    "piperack",
    "layout",
    "bypass",
    "field",
    "tunnel",
    "primitives-1",
    "primitives-2",
    "primitives-3",
    "primitives-4",
)
KINDS = ("neighbours", "ground", "true", "default")


def mesh_normals(mesh, origin: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The normal of the face each (level, shifted) sensor-frame point's ray hits."""
    directions = points / np.linalg.norm(points, axis=1, keepdims=True)
    faces = mesh.ray.intersects_first(np.repeat(origin[None], len(points), 0), directions)
    normals = mesh.face_normals[np.maximum(faces, 0)]
    return normals * np.where(np.einsum("ij,ij->i", normals, directions) > 0, -1.0, 1.0)[:, None]


def step_poses(route: np.ndarray, steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(before, after) sensor poses at `steps` places spread along the route, a 0.1 m step forward."""
    seg = np.linalg.norm(np.diff(route[:, :2], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    out = []
    for d in np.linspace(0.05, 0.95, steps) * s[-1]:
        k = min(int(np.searchsorted(s, d, side="right")) - 1, len(route) - 2)
        heading = np.arctan2(*(route[k + 1, 1::-1] - route[k, 1::-1]))
        p = np.array([np.interp(d, s, route[:, i]) for i in range(3)])
        before = planar_pose(p[0], p[1], p[2] + 0.85, heading)
        out.append((before, before @ planar_pose(0.1, 0.0, 0.0, 0.0)))
    return out


def normals_of(kind: str, target: PreparedTarget, config: RegistrationConfig, mesh, origin: np.ndarray) -> np.ndarray:
    base = np.asarray(target.cloud.normals())[:, :3] if hasattr(target.cloud, "normals") else target.normals
    if kind == "true":
        return mesh_normals(mesh, origin, target.points)
    normals = base.copy()
    if kind == "ground":
        plane = ground_plane(target.points, normals)
        if plane is not None:
            normals[ground_voxels(target.points, plane)] = plane[:3]
    return normals


def measure(name: str, lidar: Lidar, steps: int) -> dict[str, list[float]]:
    scene = make_scene(name)
    lidar = Lidar(make_caster("embree", scene.mesh))
    rng = np.random.default_rng(0)
    plain = RegistrationConfig(ground_normals=False)
    default = RegistrationConfig()
    ratios: dict[str, list[float]] = {k: [] for k in KINDS}
    for before, after in step_poses(scene.route, steps):
        t, s = lidar.scan(before, rng).points, lidar.scan(after, rng).points
        target = PreparedTarget(t, plain)
        source = np.asarray(prepare_source(s, plain).points())[:, :3]
        row = {}
        for kind in KINDS[:-1]:
            target.normals = normals_of(kind, target, plain, scene.mesh, before[:3, 3])
            T = np.eye(4)
            for distance in plain.max_correspondence_distance:
                T = _plane_icp(source, target, T, distance, plain)[0]
            row[kind] = matrix_to_pose(T)[0] / 0.1
        row["default"] = matrix_to_pose(register(s, t, default, with_hessian=False).T_target_source)[0] / 0.1
        if 0.9 < row["true"] < 1.1:
            for k, v in row.items():
                ratios[k].append(v)
    return ratios


def timing(lidar_scene: str = "mine", repeats: int = 10) -> None:
    scene = make_scene(lidar_scene)
    lidar = Lidar(make_caster("embree", scene.mesh))
    rng = np.random.default_rng(1)
    before, after = step_poses(scene.route, 1)[0]
    t, s = lidar.scan(before, rng).points, lidar.scan(after, rng).points
    plain = RegistrationConfig(ground_normals=False)
    for title, config in (("small_gicp, neighbours' normals", plain), ("default", RegistrationConfig())):
        start = time.perf_counter()
        for _ in range(repeats):
            register(s, t, config)
        ms = (time.perf_counter() - start) / repeats * 1e3
        print(f"{title:34s} {ms:6.1f} ms a registration (target, source, ICP, Hessian)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=12, help="steps measured along each route")
    parser.add_argument("--families", default=",".join(FAMILIES), help="scenes, comma-separated")
    args = parser.parse_args()
    print(f"{'scene':14s} {'n':>3s}" + "".join(f"{k:>14s}" for k in KINDS) + "   (ratio of ICP's step to 0.1 m, mean)")
    for name in args.families.split(","):
        ratios = measure(name, None, args.steps)
        n = len(ratios["true"])
        cells = "".join(f"{np.mean(ratios[k]):14.3f}" if n else f"{'-':>14s}" for k in KINDS)
        print(f"{name:14s} {n:3d}{cells}", flush=True)
    timing()


if __name__ == "__main__":
    main()
