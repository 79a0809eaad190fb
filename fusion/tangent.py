"""The one place where the project's axis order meets GTSAM's.

Project order: (x, y, z, roll, pitch, yaw). GTSAM Pose3 tangent order: (rx, ry, rz, tx, ty, tz).
"""

from __future__ import annotations

import numpy as np

# index i of the GTSAM vector takes project axis GTSAM_FROM_PROJECT[i]
GTSAM_FROM_PROJECT = np.array([3, 4, 5, 0, 1, 2])
PROJECT_FROM_GTSAM = np.argsort(GTSAM_FROM_PROJECT)


def _reorder(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if v.shape == (6,):
        return v[index]
    if v.shape == (6, 6):
        return v[np.ix_(index, index)]
    raise ValueError(f"expected a 6-vector or a 6x6 matrix, got shape {v.shape}")


def to_gtsam_order(values: np.ndarray) -> np.ndarray:
    """Reorder a 6-vector (or the rows and columns of a 6x6 matrix) from project to GTSAM order."""
    return _reorder(values, GTSAM_FROM_PROJECT)


def to_project_order(values: np.ndarray) -> np.ndarray:
    """Inverse of `to_gtsam_order`."""
    return _reorder(values, PROJECT_FROM_GTSAM)
