"""What writing a drive as a Rerun recording costs: the demo's drive (the mine, 1 575 steps with the
shipped model) run twice in this process, without a recording (the reference) and with one, and the
recording's share of the drive's time and its size printed. Target: at most 10% of the drive's time
and 100 MB.

Run: python benchmarks/bench_rerun.py [--scene mine] [--max-steps N] [--out runs/bench-rerun]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from l3e_env.experiments.demo import run_demo
from l3e_env.experiments.drive import DriveOptions


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="mine")
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--out", default="runs/bench-rerun")
    args = parser.parse_args()
    out = Path(args.out)
    options = DriveOptions(max_steps=args.max_steps)
    seconds = {}
    for name, rerun in (("without", None), ("with", out / "with" / "drive.rrd")):
        t0 = time.perf_counter()
        summary = run_demo(out / name, args.scene, options, progress=False, rerun=rerun)
        seconds[name] = time.perf_counter() - t0
        print(f"{name:8s} a recording: {seconds[name]:6.1f} s ({summary['steps']} steps)")
    size = (out / "with" / "drive.rrd").stat().st_size
    extra = seconds["with"] - seconds["without"]
    print(f"the recording: {extra:+.1f} s, {extra / seconds['without']:+.1%} of the drive's time; {size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
