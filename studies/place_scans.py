"""Scans of one scene written as a folder of .npy files, drawn where the labels draw their parents
(`labels.sample_parent_pose`, the paper's spread or the level operating poses): what `l3e adapt
--scans DIR` reads, for adapting on one scene of a family and scoring on its others.

Run: python studies/place_scans.py --scene piperack-0 --count 200 --out runs/adapt/piperack-0-scans [--level]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

from l3e_env.config import LidarConfig
from l3e_env.data.generation import PRESETS
from l3e_env.localizability.labels import LabelConfig, sample_parent_pose
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", required=True)
    parser.add_argument("--count", type=int, default=200)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sensor", default="vlp16")
    parser.add_argument("--level", action="store_true", help="the level operating poses (preset level)")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    labels = LabelConfig(**PRESETS["level"]["labels"]) if args.level else LabelConfig()
    scene = make_scene(args.scene)
    caster = EmbreeCaster(scene.mesh)
    lidar = Lidar(caster, LidarConfig(model=args.sensor))
    rng = np.random.default_rng(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    for k in tqdm(range(args.count), desc=f"scans of {args.scene}"):
        T_w_s = sample_parent_pose(scene, caster, rng, labels)
        np.save(args.out / f"scan-{k:04d}.npy", lidar.scan(T_w_s, rng).points)
    print(f"written: {args.out} ({args.count} scans)")


if __name__ == "__main__":
    main()
