"""How far each scan-to-scan ICP step is off the true step, per axis, where the eigenvalue
detector trusts the axis, next to the leg odometry's own per-step sigmas, which the graph weighs
against the ICP's; and the residual variance that turns the registration's Hessian into the ICP
factor's information (`FusionConfig.icp_residual_variance`): the mean of e' H e / 6 over the
steps where no axis is flagged, e the step's error and H its Hessian in the body frame.

The route of each scene (training families only, so that the mine and the caves stay unseen) is
driven once with separate noise streams, consecutive scans are registered as `l3e ate` does, and
on every step that eigen:TAU leaves an axis unflagged the ICP step's error on that axis (in the
body frame, the fusion's) is collected. On the steps with no axis flagged, each axis's squared
error over the variance that the fusion's information gives it (the diagonal of
icp_residual_variance x H^-1) says where that covariance is calibrated: 1 where it is right, above
1 where it flatters ICP, below where it under-sells it. The error's RMS, pooled over the scenes, carries its bias
too (ICP under-estimates a step where normals lean across corners), since a per-step bias adds
up along a route as the graph's sigmas assume noise does not. Printed per scene and pooled, with
the defaults beside them. The pooled RMS is not a good constant: where the detector trusts a
weakly held axis (the field's yaw) its error is ten times that of a well held one (the tunnel's),
which is why the fusion weighs each step by its Hessian instead.

Run: python studies/icp_step_errors.py [--scenes tunnel-0,office-0,fork-0,field-0] [--tau 110] [--neighbours-normals]
"""

from __future__ import annotations

import argparse

import numpy as np

from fusion import FusionConfig
from l3e_env.config import OdometryConfig
from l3e_env.core.transforms import inverse, matrix_to_pose
from l3e_env.detection.detectors import EigenvalueDetector
from l3e_env.experiments.drive import DriveOptions, record_run, register_sequence
from l3e_env.localizability.labels import AXES
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.odometry import odometry_sigmas


def step_errors(scene: str, tau: float, seed: int, registration: RegistrationConfig) -> tuple[np.ndarray, ...]:
    """(errors, trusted, odometry sigmas) per registered step of the scene's route, (K, 6) each,
    e' H e / 6 per step (K), and e_i^2 / (v H^-1)_ii per axis (K, 6; NaN where an axis is flagged),
    v the default residual variance."""
    rec = record_run(scene, DriveOptions(seed=seed), progress=False)
    registrations = register_sequence(rec, registration, progress=False)
    detector, T_b_s = EigenvalueDetector(tau), rec.T_b_s
    errors, trusted, sigmas, quadratic, calibration = [], [], [], [], []
    variance = FusionConfig().icp_residual_variance
    for k, reg in enumerate(registrations):
        if reg is None or not reg.converged:
            continue
        truth = inverse(rec.ground_truth[k]) @ rec.ground_truth[k + 1]
        icp, hessian = reg.in_frame(T_b_s)
        errors.append(matrix_to_pose(inverse(truth) @ icp))
        trusted.append(~detector.predict(rec.scans[k + 1], reg).mask)
        sigmas.append(odometry_sigmas(rec.odometry[k], OdometryConfig()))
        quadratic.append(errors[-1] @ hessian @ errors[-1] / 6.0)
        covariance = variance * np.linalg.inv(hessian) if trusted[-1].all() else np.full((6, 6), np.nan)
        calibration.append(errors[-1] ** 2 / np.diag(covariance))
    return tuple(map(np.array, (errors, trusted, sigmas, quadratic, calibration)))


def row(name: str, values: np.ndarray) -> str:
    return f"{name:34s}" + "".join("       -" if not np.isfinite(v) else f"{v:8.1e}" for v in values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="tunnel-0,office-0,fork-0,field-0")
    parser.add_argument("--tau", type=float, default=110.0, help="eigenvalue threshold that decides trust")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--neighbours-normals",
        action="store_true",
        help="register with small_gicp's neighbours' normals on the ground too (ground_normals off)",
    )
    args = parser.parse_args()
    registration = RegistrationConfig(ground_normals=not args.neighbours_normals)
    print(f"{'':34s}" + "".join(f"{a:>8s}" for a in AXES))
    pooled_sq, pooled_n, fits = np.zeros(6), np.zeros(6), []
    for scene in args.scenes.split(","):
        errors, trusted, sigmas, quadratic, calibration = step_errors(scene, args.tau, args.seed, registration)
        fits.append(quadratic[trusted.all(axis=1)])
        n = trusted.sum(axis=0)
        squares = np.where(trusted, errors**2, 0.0).sum(axis=0)
        pooled_sq, pooled_n = pooled_sq + squares, pooled_n + n
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(trusted, errors, 0.0).sum(axis=0) / n
            print(f"{scene} ({len(errors)} steps; trusted share " + " ".join(f"{s:.2f}" for s in n / len(errors)) + ")")
            print(row("  ICP step error, mean", mean))
            print(row("  ICP step error, RMS", np.sqrt(squares / n)))
        print(row("  leg odometry sigma, median", np.median(sigmas, axis=0)))
        if len(fits[-1]):
            print(f"  e' H e / 6 on the {len(fits[-1])} steps with no axis flagged: mean {fits[-1].mean():.4f}")
            print(row("  there, e_i^2 / (v H^-1)_ii, mean", np.nanmean(calibration[trusted.all(axis=1)], axis=0)))
    print(row("pooled ICP step error, RMS", np.sqrt(pooled_sq / np.maximum(pooled_n, 1))))
    print(row("FusionConfig.icp_sigmas (fixed)", np.asarray(FusionConfig().icp_sigmas)))
    pooled = np.concatenate(fits)
    used = FusionConfig().icp_residual_variance
    print(
        f"icp_residual_variance: the pooled mean of e' H e / 6 over {len(pooled)} steps is {pooled.mean():.4f} m^2 "
        f"(the fusion's: {used})"
    )


if __name__ == "__main__":
    main()
