"""How scanmc meets a sensor with staggered beams (an Ouster's), against the labels.

Run: python studies/staggered_beams.py [--x 20,40,60] [--children 40] [--sensor FILE]

At each pose along the mine's tunnel a 64-beam Ouster-like sensor (beams +-21.1 deg, azimuths
staggered by up to 3.3 deg, beams leaving 15.8 mm out from the axis; or --sensor FILE) is
labelled in the world mesh (label_parent, the M = 200 children of the labels), then its scan is
estimated by scanmc with all `--children` drawn: with the sensor's exact pattern, with that
pattern unstaggered, and with the pattern `fit_pattern` recognises from the scan and its rings.
The label's mean error in the same run is the reference each estimate is read against.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import pose_to_matrix
from l3e_env.localizability.labels import AXES, LabelConfig, label_parent
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.localizability.scan_mc import ScanMCConfig, scan_errors
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.patterns import PATTERNS, fit_pattern, load_pattern, register_pattern
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene

OUSTER_LIKE = """elevations_deg: {from: -21.1, to: 21.1, beams: 64}
columns: 1024
max_range: 120
min_range: 0.5
azimuth_offsets_deg: %s
beam_origin_offset: 0.0158
""" % ([3.1, 0.9, -1.2, -3.3] * 16)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--x", default="20,40,60", help="sensor positions along the tunnel (m from the portal)")
    parser.add_argument("--children", type=int, default=40)
    parser.add_argument("--sensor", help="a beam pattern file (default: the Ouster-like sensor above)")
    args = parser.parse_args()
    if args.sensor is None:
        args.sensor = str(Path(tempfile.mkdtemp()) / "ouster-like.yaml")
        Path(args.sensor).write_text(OUSTER_LIKE)
    exact = load_pattern(args.sensor)
    unstaggered = replace(exact, name="unstaggered", azimuth_offsets_deg=())
    mesh, labels, registration = make_scene("mine").mesh, LabelConfig(), RegistrationConfig()
    config = ScanMCConfig(children=args.children, settle=0)
    print(f"{'x (m)':>6s} {'estimate':24s}" + "".join(f"{a:>8s}" for a in AXES))
    for x in (float(v) for v in args.x.split(",")):
        T = pose_to_matrix(np.array([x, 0.2, 0.85, 0.0, 0.0, 0.05]))
        register_pattern(exact)
        lidar = Lidar(EmbreeCaster(mesh), LidarConfig(model=exact.name))
        label = label_parent(lidar, T, np.random.default_rng(0), labels, registration)
        scan = lidar.scan(T, np.random.default_rng(1))
        PATTERNS.pop(exact.name)  # recognised as an unknown sensor would be
        PATTERNS.pop(unstaggered.name, None)
        fitted, how = fit_pattern(scan.points, scan.beam)
        for pattern in (exact, unstaggered, fitted):
            register_pattern(pattern)
        print(f"{x:6.0f} {'label (200 children)':24s}" + "".join(f"{e:8.3f}" for e in label.errors))
        for name, model in (
            ("exact pattern", exact.name),
            ("unstaggered", "unstaggered"),
            ("recognised from the scan", fitted.name),
        ):
            errors = scan_errors(
                scan.points.astype(np.float64),
                LidarConfig(model=model),
                registration,
                labels,
                config,
                np.random.default_rng(2),
            ).errors
            print(f"{'':6s} {name:24s}" + "".join(f"{e:8.3f}" for e in errors))
        print(f"{'':6s} (recognised: {how})")
        PATTERNS.pop(fitted.name)  # each pose's scan is recognised afresh


if __name__ == "__main__":
    main()
