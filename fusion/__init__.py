"""Estimation only (gtsam, filterpy, numpy): factor graph, localizability masks, ATE/RPE.

Imports nothing from the rest of the project. Axis order in every public array is the
project's (x, y, z, roll, pitch, yaw); `fusion.tangent` is the one place that converts to
GTSAM's rotation-first tangent order.
"""
from .ekf import EKFFusion
from .graph import FusionConfig, FusionGraph
from .steps import StepReport
from .metrics import MetricError, ate, ate_aligned, rpe, rpe_pairs, umeyama, write_tum
from .tangent import to_gtsam_order, to_project_order

__all__ = ["EKFFusion", "FusionConfig", "FusionGraph", "StepReport", "MetricError", "ate", "ate_aligned", "rpe",
           "rpe_pairs", "umeyama", "write_tum", "to_gtsam_order", "to_project_order"]
