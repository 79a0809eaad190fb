"""Whether the fusion should weigh the IMU's attitude as if each reading's error were its own.

The nine-axis unit's orientation error is a Gauss-Markov process that forgets itself over 30 s
(`ImuConfig.orientation_time`), and the fusion takes a reading once a second (ATTITUDE_EVERY steps)
with the process's own sigma, as if the readings were independent. In a long average such a reading
is worth 1/60 of an independent one (the AR(1) factor (1 + phi) / (1 - phi), phi = exp(-1 / 30)),
so its sigma times sqrt(60) = 7.74 is the independent reading's equivalent. The mine's drives are
fused with the attitude's sigmas times each factor ("tilt" and "full"), the learned detector, full
ICP and the odometry with the attitude alone, the same registrations and readings for every factor.

Run: python studies/attitude_correlation.py [--seeds 0,1,2,3,4] [--factors 1,3,7.74]
     (13 min on 2 cores for the defaults; per drive and row the ATE in metres, then the means)
"""

from __future__ import annotations

import argparse
from unittest import mock

import numpy as np

from l3e_env.config import FusionSettings, LidarConfig, OdometryConfig
from l3e_env.detection.detectors import make_detector
from l3e_env.experiments import drive, fuse, recast
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.imu import attitude_sigmas
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.odometry import odometry_fusion_config
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def drive_ates(seed: int, factors: list[float], scene, lidar: Lidar) -> dict[str, float]:
    """ATE (m) per row of one drive: without the attitude, then per mode and factor."""
    rec = drive.deskewed(drive.record_run("mine", drive.DriveOptions(seed=seed), False, scene_object=scene), "gyro")
    regs = drive.register_sequence(rec, RegistrationConfig(), False)
    fusion = odometry_fusion_config(OdometryConfig(), FusionSettings())
    detectors = [make_detector("learned", lidar, seed), make_detector("none", lidar, seed)]
    ates = {"odometry only": fuse.odometry_only(rec).ate}
    for r in fuse.fuse_recording(rec, detectors, regs, fusion=fusion, progress=False):
        ates[f"{r.name}, no attitude"] = r.ate
    for mode in ("tilt", "full"):
        for factor in factors:

            def scaled(m: str, config=None, factor: float = factor) -> np.ndarray | None:
                sigmas = attitude_sigmas(m, config)
                return None if sigmas is None else sigmas * factor

            with mock.patch.object(fuse, "attitude_sigmas", scaled):
                rows = fuse.fuse_recording(
                    rec, [recast.OdometryAttitude(), *detectors], regs, fusion=fusion, progress=False, attitude=mode
                )
            for r in rows:
                ates[f"{r.name}, {mode} x{factor:g}"] = r.ate
    return ates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="0,1,2,3,4")
    parser.add_argument("--factors", default="1,3,7.74")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    factors = [float(f) for f in args.factors.split(",")]
    scene = make_scene("mine")
    lidar = Lidar(EmbreeCaster(scene.mesh), LidarConfig(model="vlp16"))
    runs = [drive_ates(seed, factors, scene, lidar) for seed in seeds]
    print(f"{'row':34s}" + "".join(f"{'seed ' + str(s):>9s}" for s in seeds) + f"{'mean':>9s}")
    for name in runs[0]:
        values = [run[name] for run in runs]
        print(f"{name:34s}" + "".join(f"{v:9.3f}" for v in values) + f"{np.mean(values):9.3f}")


if __name__ == "__main__":
    main()
