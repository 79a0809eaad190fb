"""Is the default estimate never worse than its parts, in every scene family?

Every family's drives (seeds 0-2 by default, scene <family>-<seed>) recorded once and fused as
odometry alone, the legs and the IMU (`odometry + attitude`), unmasked ICP (`none`), the learned mask
(the default), `eigen:30`, `dcreg:10` and, on seed 0, the oracle; per family each row's mean and worst
ATE, and whether the default ends at most 1.1x the smaller of the parts' means and on each drive at
most 1.5x that drive's smaller part (or within 2 cm of it). Resumable: recordings are kept under
OUT/drives, each fusion under a key of its settings, so a stopped run resumes and a changed setting
fuses again without driving. Writes OUT/families.json, families.md (the table) and families.png.

Run: python studies/families.py [--out runs/families] [--workers 2] [--family tunnel --family yard]
     [--seeds 3] [--set mode=gate] [--backend ray --ray-address ADDRESS]
"""

from __future__ import annotations

import argparse
import sys

import yaml

from l3e_env.config import FusionSettings, from_dict
from l3e_env.experiments.families import DEFAULT_DETECTORS, FamiliesOptions, run_families


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/families")
    parser.add_argument("--family", action="append", default=[], help="repeat; default: every family")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--oracle-seeds", type=int, default=1)
    parser.add_argument("--detector", action="append", default=[], help=f"repeat; default: {DEFAULT_DETECTORS}")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a fusion setting")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--backend", choices=("local", "ray"), default="local")
    parser.add_argument("--ray-address")
    args = parser.parse_args()
    settings = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            parser.error(f"--set takes KEY=VALUE, got {item!r}")
        settings[key] = yaml.safe_load(value)
    options = FamiliesOptions(
        families=tuple(args.family),
        seeds=args.seeds,
        detectors=tuple(args.detector) or DEFAULT_DETECTORS,
        oracle_seeds=args.oracle_seeds,
        settings=from_dict(FusionSettings, settings),
        workers=args.workers,
        backend=args.backend,
        ray_address=args.ray_address,
    )
    run = run_families(args.out, options)
    print(run.table())
    print(f"never worse than its parts in every family: {'yes' if run.never_worse else 'no'}")
    print("written:", ", ".join(str(p) for p in run.written))
    return 0


if __name__ == "__main__":
    sys.exit(main())
