"""`l3e judge` on clouds of any size: peak memory and time of the command on a 10-million-point .npy
(an accumulated map, refused by name) and on a 1-million-point one (at the bound of one revolution:
recognised or refused by the beam-pattern recogniser, then judged), against the same command on one
VLP-16 revolution as the reference, each in a process of its own (peak resident memory from the
kernel's accounting of that process and of any it started).

Run: python benchmarks/bench_big_cloud.py [--detector eigen:30]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHILD = """
import resource, sys, time
from l3e_env.cli.main import main
t0 = time.perf_counter()
code = main(sys.argv[1:])
peak = max(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
print("RESULT", code, time.perf_counter() - t0, peak / 1024)
"""


def _run(path: Path, detector: str) -> tuple[int, float, float]:
    """(exit code, seconds, peak MiB) of `l3e judge path --detector detector` in a fresh process."""
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", CHILD, "judge", str(path), "--detector", detector], capture_output=True, text=True
    )
    wall = time.perf_counter() - t0
    line = next((ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")), None)
    if line is None:
        raise RuntimeError(out.stderr[-2000:])
    _, code, _, peak = line.split()
    return int(code), wall, float(peak)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--detector", default="eigen:30")
    args = ap.parse_args()
    from l3e_env.core.transforms import planar_pose
    from l3e_env.sim.lidar import Lidar
    from l3e_env.sim.raycast import EmbreeCaster
    from scenes import make_scene

    scene = make_scene("mine")
    scan = Lidar(EmbreeCaster(scene.mesh)).scan(planar_pose(-20, 0.5, 0.85, 0.3), np.random.default_rng(0)).points
    rng = np.random.default_rng(1)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, points in (
            ("one VLP-16 revolution", scan),
            ("1 M points", np.tile(scan, (1_000_000 // len(scan) + 1, 1))[:1_000_000]),
            ("10 M points", rng.uniform(-60, 60, (10_000_000, 3)).astype(np.float32)),
        ):
            path = Path(tmp) / "cloud.npy"
            np.save(path, points.astype(np.float32))
            del points
            code, seconds, peak = _run(path, args.detector)
            rows[name] = {"exit": code, "seconds": round(seconds, 1), "peak_mib": round(peak)}
    reference = rows["one VLP-16 revolution"]
    for name, row in rows.items():
        print(
            f"{name:22s} exit {row['exit']}  {row['seconds']:6.1f} s ({row['seconds'] / reference['seconds']:.1f}x)  "
            f"peak {row['peak_mib']:6d} MiB ({row['peak_mib'] / reference['peak_mib']:.1f}x)"
        )
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
