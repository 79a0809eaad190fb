"""External LiDAR odometries on a recorded drive: KISS-ICP and GenZ-ICP (the optional extra
`l3e[baselines]`), run on the drive's own scans as their authors ship them, for rows beside the
fusion's. Each returns the body's trajectory in the world frame of the ground truth.

Frames, once: an odometry estimates the sensor's pose in the frame of its first scan, P_k. The
body's pose is then T_w_b(k) = T_w_b(0) T_b_s P_k T_b_s^-1: the drive's true first pose, the
mounting carried through, as the fusion's rows start from the true first pose too.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from l3e_env.core.transforms import inverse
from l3e_env.localizability.registration import RegistrationResult
from l3e_env.sim.patterns import BeamPattern


class BaselineError(RuntimeError):
    """A baseline that cannot run here (its package is missing) or is unknown: the message says what to do."""


@dataclass
class BaselineRun:
    """One odometry over one drive: the body's trajectory (None where it failed), its settings, its
    seconds, and what went wrong (None where nothing did)."""

    name: str
    trajectory: np.ndarray | None
    config: dict[str, Any]
    seconds: float
    error: str | None = None
    sensor_poses: np.ndarray | None = None  # (N+1, 4, 4) the sensor in the frame of its first scan, as estimated

    def registrations(self, icp: list[RegistrationResult | None]) -> list[RegistrationResult]:
        """The odometry's step from each scan to the next as the LiDAR factor a front end hands the fusion:
        its relative motion with the information of the scan-to-scan ICP's Hessian on the same pair (the
        geometry's, whatever the motion estimate; NaN, and the fusion's fixed sigmas, where ICP failed).
        An external odometry reports no Hessian of its own, and its map-based estimate is at least as
        well held as one pair's, so the pair's information is a conservative weight; the detector then
        masks the axes the geometry does not hold, as for the ICP front end."""
        if self.sensor_poses is None:
            raise ValueError(f"{self.name} failed ({self.error}): it has no steps to hand the fusion")
        P = self.sensor_poses
        out = []
        for k, reg in enumerate(icp):
            hessian = reg.hessian if reg is not None and reg.converged else np.full((6, 6), np.nan)
            out.append(RegistrationResult(inverse(P[k]) @ P[k + 1], hessian, True, 0, 0, 0, 0.0))
        return out


def _kiss(deskew: bool, max_range: float) -> tuple[Any, dict[str, Any]]:
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    config = load_config(None)  # the authors' defaults: voxel max_range / 100, adaptive threshold
    config.data.deskew, config.data.max_range = deskew, max_range
    config.mapping.voxel_size = max_range / 100.0
    return KissICP(config), config.model_dump()


def _genz(deskew: bool, max_range: float) -> tuple[Any, dict[str, Any]]:
    from genz_icp.config import load_config
    from genz_icp.genz_icp import GenZICP

    config = load_config(None)
    config.data.deskew, config.data.max_range = deskew, max_range
    return GenZICP(config), config.model_dump()


# name -> (the module that must import, the odometry's maker)
BASELINES: dict[str, tuple[str, Callable[[bool, float], tuple[Any, dict[str, Any]]]]] = {
    "kiss-icp": ("kiss_icp", _kiss),
    "genz-icp": ("genz_icp", _genz),
}


def check_baselines(names: list[str]) -> list[str]:
    """The names if each is known and its package imports, else BaselineError naming the extra to
    install: a command checks this before it drives."""
    for name in names:
        if name not in BASELINES:
            raise BaselineError(f"unknown baseline '{name}' (choose from {', '.join(BASELINES)})")
        try:
            importlib.import_module(BASELINES[name][0])
        except ImportError as exc:
            raise BaselineError(
                f"baseline '{name}' needs its package ({exc}); install the extra: pip install 'l3e[baselines]'"
            ) from None
    return names


def run_baseline(
    name: str,
    scans: list[np.ndarray],
    ground_truth_0: np.ndarray,
    T_b_s: np.ndarray,
    pattern: BeamPattern | None,
    max_range: float = 100.0,
    progress: bool = True,
) -> BaselineRun:
    """`name` (BASELINES) over the drive's scans (sensor frame, one per step from the start's). `pattern`:
    the sensor's, for the per-point firing times of swept revolutions, which the odometry then deskews
    with its own motion model; None for scans taken at one instant (no deskewing). Whatever the
    odometry raises is caught into the run's `error`: one failing baseline leaves the other rows be."""
    check_baselines([name])
    odometry, config = BASELINES[name][1](pattern is not None, max_range)
    poses, t0 = [], time.perf_counter()
    try:
        for scan in tqdm(scans, desc=name, unit="scan", disable=not progress, leave=False):
            points = np.asarray(scan, dtype=np.float64)
            stamps = pattern.firing_share(points) if pattern is not None else np.zeros(0)
            odometry.register_frame(points, stamps)
            poses.append(np.array(odometry.last_pose, dtype=np.float64))
    except Exception as exc:  # a library's own failure: reported in its row, not raised
        return BaselineRun(name, None, config, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}")
    P = np.array(poses)
    if not np.isfinite(P).all():
        return BaselineRun(name, None, config, time.perf_counter() - t0, "non-finite poses (diverged)")
    trajectory = np.asarray(ground_truth_0) @ T_b_s @ P @ inverse(T_b_s)
    return BaselineRun(name, trajectory, config, time.perf_counter() - t0, sensor_poses=P)
