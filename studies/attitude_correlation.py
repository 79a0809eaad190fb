"""Whether the fusion should weigh the IMU's attitude as the correlated readings they are.

The nine-axis unit's orientation error is a Gauss-Markov process that forgets itself over 30 s
(`ImuConfig.orientation_time`), and the fusion takes a reading once a second (ATTITUDE_EVERY steps).
In a long average such a reading is worth 1/60 of an independent one (the AR(1) factor
(1 + phi) / (1 - phi), phi = exp(-1 / 30)), so `imu.attitude_sigmas` gives each the error's sigma
times sqrt(60) = 7.74. The mine's drives are fused with those sigmas times each factor (1: as the
fusion weighs them with the ground; 0.129 = 1 / 7.74: each reading as if its error were its own, as
without it), "tilt" and
"full", the learned detector and full ICP, with and without the ground (`--ground`), the same
registrations (onto keyframes, as `l3e ate`) and readings for every factor.

Run: python studies/attitude_correlation.py [--seeds 0,1,2,3,4] [--factors 0.129,1] [--ground plane]
     (per drive and row the ATE in metres, then the means)
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from unittest import mock

import numpy as np

from l3e_env.config import GROUND_MODES, FusionSettings, LidarConfig, OdometryConfig
from l3e_env.detection import pipeline
from l3e_env.detection.detectors import make_detector
from l3e_env.detection.pipeline import Keyframes
from l3e_env.experiments import drive, fuse, recast
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.imu import attitude_sigmas
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.odometry import odometry_fusion_config
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def drive_ates(seed: int, factors: list[float], scene, lidar: Lidar, ground: str) -> dict[str, float]:
    """ATE (m) per row of one drive: without the attitude, then per mode and factor."""
    rec = drive.deskewed(drive.record_run("mine", drive.DriveOptions(seed=seed), False, scene_object=scene), "gyro")
    default = FusionSettings(ground=ground)
    keyframes = Keyframes(distance=default.keyframe_distance or 0.0)
    regs = drive.register_sequence(rec, RegistrationConfig(), False, keyframes)
    fusion = odometry_fusion_config(OdometryConfig(), default)
    detectors = [make_detector("learned", lidar, seed), make_detector("none", lidar, seed)]
    ates = {"odometry only": fuse.odometry_only(rec).ate}
    none = replace(default, attitude="none")
    for r in fuse.fuse_recording(rec, detectors, regs, fusion=fusion, progress=False, settings=none):
        ates[f"{r.name}, no attitude"] = r.ate
    for mode in ("tilt", "full"):
        for factor in factors:

            def scaled(m: str, config=None, factor: float = factor, **_: object) -> np.ndarray | None:
                sigmas = attitude_sigmas(m, config, correlated=True)  # whatever the ground
                return None if sigmas is None else sigmas * factor

            with mock.patch.object(pipeline, "attitude_sigmas", scaled):  # where the fusion reads them
                rows = fuse.fuse_recording(
                    rec,
                    [recast.OdometryAttitude(), *detectors],
                    regs,
                    fusion=fusion,
                    progress=False,
                    settings=replace(default, attitude=mode),
                )
            for r in rows:
                ates[f"{r.name}, {mode} x{factor:g}"] = r.ate
    return ates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="0,1,2,3,4")
    parser.add_argument("--factors", default="0.129,1")
    parser.add_argument("--ground", default=FusionSettings().ground, choices=GROUND_MODES)
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    factors = [float(f) for f in args.factors.split(",")]
    scene = make_scene("mine")
    lidar = Lidar(EmbreeCaster(scene.mesh), LidarConfig(model="vlp16"))
    runs = [drive_ates(seed, factors, scene, lidar, args.ground) for seed in seeds]
    print(f"{'row':34s}" + "".join(f"{'seed ' + str(s):>9s}" for s in seeds) + f"{'mean':>9s}")
    for name in runs[0]:
        values = [run[name] for run in runs]
        print(f"{name:34s}" + "".join(f"{v:9.3f}" for v in values) + f"{np.mean(values):9.3f}")


if __name__ == "__main__":
    main()
