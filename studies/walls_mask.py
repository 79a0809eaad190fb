"""What masking the free axis adds between two parallel walls (primitives-1, x along the walls is free),
drive by drive: the unmasked and masked (eigenvalue test at the geometric mean of the two smallest
Hessian eigenvalues' medians, the first drive's) ATE of the default estimator, which weighs ICP by its
Hessian, and of the library's fixed ICP sigmas (the paper's protocol).

Run: python studies/walls_mask.py [--seeds 0,1,2,3,4] [--steps 0 (the whole route)]
"""

from __future__ import annotations

import argparse

import numpy as np

from fusion import FusionConfig
from l3e_env.detection.detectors import EigenvalueDetector, NoDetector
from l3e_env.experiments.drive import DriveOptions, record_run, register_sequence
from l3e_env.experiments.fuse import fuse_recording
from l3e_env.localizability.registration import RegistrationConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2,3,4")
    parser.add_argument("--steps", type=int, default=0, help="steps a drive (0: the whole route)")
    args = parser.parse_args()
    tau = None
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        rec = record_run("primitives-1", DriveOptions(seed=seed, max_steps=args.steps or None), progress=False)
        regs = register_sequence(rec, RegistrationConfig(), progress=False)
        if tau is None:
            w = np.array([np.linalg.eigvalsh(r.hessian)[:2] for r in regs if r is not None])
            tau = float(np.sqrt(np.median(w[:, 0]) * np.median(w[:, 1])))
        detectors = [NoDetector(), EigenvalueDetector(tau)]
        weighed = fuse_recording(rec, detectors, regs, progress=False)
        fixed = fuse_recording(rec, detectors, regs, fusion=FusionConfig(icp_covariance="fixed"), progress=False)
        rows.append([r.ate for r in (*weighed, *fixed)])
        print(f"seed {seed} ({len(rec.scans) - 1} steps): " + " ".join(f"{a:.3f}" for a in rows[-1]), flush=True)
    ate = np.array(rows)
    print(f"tau {tau:.2f}; columns: Hessian unmasked, masked; fixed sigmas unmasked, masked")
    print("mean " + " ".join(f"{a:.3f}" for a in ate.mean(axis=0)))
    print(f"masked better than unmasked (Hessian): {int((ate[:, 1] < ate[:, 0]).sum())} of {len(ate)} drives")


if __name__ == "__main__":
    main()
