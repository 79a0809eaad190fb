"""Parents labelled per second with M children, against the straightforward pipeline.

Run: python benchmarks/bench_labels.py [--parents 8] [--children 200] [--workers 2]
Reference (same run): one process, for each child ray-cast then register it to the raw parent
scan with `register(child, parent)`, which prepares the parent (downsampling, normals, k-d tree)
again for every child. Measured: the dataset generator (parent prepared once, strided source,
worker processes). Peak memory is the largest resident set of a worker.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time

import numpy as np

from l3e_env.core.transforms import pose_to_matrix
from l3e_env.data.generation import config_for, generate
from l3e_env.localizability.labels import LabelConfig, sample_parent_pose
from l3e_env.localizability.registration import register
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene

SCENES = ["tunnel-0", "office-0", "field-0", "mine-0"]


def straightforward(parents: int, children: int) -> float:
    """Seconds per parent of the plain pipeline."""
    cfg = LabelConfig(children=children)
    sigma = cfg.sigma_vector("child")
    t0 = time.perf_counter()
    for k in range(parents):
        scene = make_scene(SCENES[k % len(SCENES)])
        caster = EmbreeCaster(scene.mesh, threads=1)
        lidar = Lidar(caster)
        rng = np.random.default_rng(k)
        T = sample_parent_pose(scene, caster, rng, cfg)
        parent = lidar.scan(T, rng).points
        for _ in range(children):
            T_pc = pose_to_matrix(rng.normal(0, 1, 6) * sigma)
            register(lidar.scan(T @ T_pc, rng).points, parent)
    return (time.perf_counter() - t0) / parents


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parents", type=int, default=8, help="parents for the generator (spread over 4 scenes)")
    parser.add_argument("--reference-parents", type=int, default=2)
    parser.add_argument("--children", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    ref = straightforward(args.reference_parents, args.children)
    cfg = config_for(
        None,
        scenes=SCENES,
        parents_per_scene=max(1, args.parents // len(SCENES)),
        shard_size=1,
        labels={"children": args.children},
    )
    n = cfg.parents_per_scene * len(SCENES)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        generate(tmp, cfg, workers=args.workers, progress=False)
        fast = (time.perf_counter() - t0) / n
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(
        f"M = {args.children}: straightforward {1 / ref:.2f} parents/s ({ref:.2f} s each, 1 process); "
        f"generator {1 / fast:.2f} parents/s with {args.workers} workers over {n} parents; "
        f"speed-up {ref / fast:.2f}x; peak worker memory {peak_mb:.0f} MB"
    )


if __name__ == "__main__":
    main()
