"""Plausibility checks of point clouds that every reader of scans shares."""
from __future__ import annotations

import numpy as np

# No LiDAR of the kinds judged here returns from a kilometre away: points beyond it are a scan in
# millimetres or one not in the sensor's frame (map or UTM coordinates), which a detector would judge
# with confidence.
MAX_SCAN_RANGE_M = 1000.0


def out_of_reach(points: np.ndarray) -> str | None:
    """Why finite points (N, 3) cannot be a scan in its sensor's frame (some beyond MAX_SCAN_RANGE_M),
    or None; the classifier and `l3e judge` say it alike."""
    reach = float(np.sqrt(np.einsum("ij,ij->i", points, points).max())) if len(points) else 0.0
    if reach <= MAX_SCAN_RANGE_M:
        return None
    return (f"its points reach {reach:.0f} m from the sensor, beyond {MAX_SCAN_RANGE_M:.0f} m "
            f"(a scan in millimetres, or not in the sensor's frame?)")
