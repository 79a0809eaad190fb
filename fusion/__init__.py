"""Estimation only (gtsam, filterpy, numpy): factor graph, localizability masks, leg-bias states, ground
patches, ATE/RPE/drift.

Imports nothing from the rest of the project. Axis order in every public array is the
project's (x, y, z, roll, pitch, yaw); `fusion.tangent` is the one place that converts to
GTSAM's rotation-first tangent order.
"""

from .bias import BIAS_AXES
from .ekf import EKFFusion
from .graph import FusionError, FusionGraph
from .ground import plane_in_frame
from .metrics import MetricError, ate, ate_aligned, rpe, rpe_pairs, stretch_drift, umeyama, write_kitti, write_tum
from .steps import ICP_COVARIANCES, FusionConfig, StepReport, check_config, icp_information
from .tangent import to_gtsam_order, to_project_order

BACKENDS: dict[str, type[FusionGraph] | type[EKFFusion]] = {"graph": FusionGraph, "ekf": EKFFusion}


def check_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"unknown fusion backend '{backend}' ({', '.join(BACKENDS)})")
    return backend


def make_fusion(backend: str, T_w_0, config: FusionConfig | None = None) -> FusionGraph | EKFFusion:
    """'graph' (iSAM2 smoother) or 'ekf' (filterpy filter): the same add_step interface."""
    return BACKENDS[check_backend(backend)](T_w_0, config)


__all__ = [
    "BACKENDS",
    "BIAS_AXES",
    "ICP_COVARIANCES",
    "check_config",
    "icp_information",
    "check_backend",
    "make_fusion",
    "EKFFusion",
    "FusionConfig",
    "FusionError",
    "FusionGraph",
    "plane_in_frame",
    "StepReport",
    "MetricError",
    "ate",
    "ate_aligned",
    "rpe",
    "rpe_pairs",
    "stretch_drift",
    "umeyama",
    "write_kitti",
    "write_tum",
    "to_gtsam_order",
    "to_project_order",
]
