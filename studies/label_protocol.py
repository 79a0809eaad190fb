"""How many labels the label protocol's change turns, per scene family, and why.

At the same parents and the same children (the paper's sampling), each child is registered twice:
with small_gicp's neighbours' normals (protocol 1's registration) and with the ground plane's
normals (protocol 2's, the default). Three label sets follow from the mean absolute errors:
  p1: the neighbours' normals and the paper's thresholds (0.1 m, 2 deg);
  thr: the neighbours' normals and this protocol's thresholds (0.04 m, 2 deg);
  p2: the ground plane's normals and this protocol's thresholds.
The table counts, per axis, the positives under p1 and p2 and how many labels the threshold turned
(p1 -> thr) and how many the registration turned after it (thr -> p2).

Run: python studies/label_protocol.py [--parents 8] [--children 60] [--scenes tunnel-0,...]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from l3e_env.core.transforms import pose_to_matrix
from l3e_env.localizability.labels import AXES, LabelConfig, registration_error, sample_parent_pose
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

SCENES = (
    "tunnel-0",
    "field-0",
    "office-0",
    "cave-0",
    "primitives-0",
    "primitives-1",
    "primitives-3",
    "primitives-4",
    "gallery-0",
    "chamber-0",
    "fork-0",
    "mine-0",
    "piperack-0",
)
PAPER = LabelConfig(thresholds=(0.1, 0.1, 0.1, 2.0, 2.0, 2.0))


def parent_errors(
    lidar: Lidar,
    T_w_p: np.ndarray,
    rng: np.random.Generator,
    config: LabelConfig,
    registrations: list[RegistrationConfig],
) -> np.ndarray:
    """(registrations, 6) mean absolute errors over the same children."""
    parent = lidar.scan(T_w_p, rng)
    targets = [PreparedTarget(parent.points, r) for r in registrations]
    sigma, errors = config.sigma_vector("child"), []
    for _ in range(config.children):
        T_p_c = pose_to_matrix(rng.normal(0, 1, 6) * sigma)
        child = lidar.scan(T_w_p @ T_p_c, rng)
        try:
            row = [
                registration_error(
                    register(prepare_source(child.points, r), t, r, with_hessian=False).T_target_source,
                    T_p_c,
                    config.error_frame,
                )
                for r, t in zip(registrations, targets)
            ]
        except RegistrationError:
            continue
        errors.append(row)
    return np.mean(errors, axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parents", type=int, default=8)
    parser.add_argument("--children", type=int, default=60)
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    config = dataclasses.replace(LabelConfig(), children=args.children)
    registrations = [RegistrationConfig(ground_normals=False), RegistrationConfig()]
    t1, t2 = PAPER.threshold_vector(), config.threshold_vector()
    print("per axis x/y/z/roll/pitch/yaw: positives p1 -> p2; labels turned by the threshold, then by the registration")
    total = np.zeros((4, 6), dtype=int)
    for name in args.scenes.split(","):
        scene = make_scene(name)
        caster = EmbreeCaster(scene.mesh)
        lidar = Lidar(caster)
        rng = np.random.default_rng(args.seed)
        p1, thr, p2 = [], [], []
        for _ in range(args.parents):
            T = sample_parent_pose(scene, caster, rng, config)
            neighbours, ground = parent_errors(lidar, T, rng, config, registrations)
            p1.append(neighbours > t1)
            thr.append(neighbours > t2)
            p2.append(ground > t2)
        p1, thr, p2 = (np.array(a) for a in (p1, thr, p2))
        counts = np.array([p1.sum(0), p2.sum(0), (p1 != thr).sum(0), (thr != p2).sum(0)])
        total += counts
        print(
            f"{name:14s} "
            + "  ".join(f"{AXES[i]} {counts[0, i]}->{counts[1, i]} ({counts[2, i]}, {counts[3, i]})" for i in range(6)),
            flush=True,
        )
    print(
        f"{'all':14s} "
        + "  ".join(f"{AXES[i]} {total[0, i]}->{total[1, i]} ({total[2, i]}, {total[3, i]})" for i in range(6))
    )


if __name__ == "__main__":
    main()
