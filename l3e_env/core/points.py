"""Plausibility checks of point clouds that every reader of scans shares."""

from __future__ import annotations

import numpy as np

# No LiDAR of the kinds judged here returns from a kilometre away: points beyond it are a scan in
# millimetres or one not in the sensor's frame (map or UTM coordinates), which a detector would judge
# with confidence.
MAX_SCAN_RANGE_M = 1000.0
# Twice the most a spinning LiDAR returns in one revolution (128 beams x 2048 columns, two returns a
# ray, is 524,288): a cloud beyond it is an accumulated map or several revolutions, which no detector
# here judges; refused before its points are worked on, so that its size bounds nothing.
MAX_REVOLUTION_POINTS = 1 << 20


def too_many_points(count: int) -> str | None:
    """Why a cloud of `count` points cannot be one revolution (more than MAX_REVOLUTION_POINTS), or None."""
    if count <= MAX_REVOLUTION_POINTS:
        return None
    return (
        f"it holds {count:,} points, more than any spinning LiDAR returns in one revolution (at most "
        f"{MAX_REVOLUTION_POINTS:,} are judged): an accumulated map or several revolutions; give one "
        "revolution in the sensor's frame"
    )


def out_of_reach(points: np.ndarray) -> str | None:
    """Why finite points (N, 3) cannot be a scan in its sensor's frame (some beyond MAX_SCAN_RANGE_M),
    or None; the classifier and `l3e judge` say it alike."""
    reach = float(np.sqrt(np.einsum("ij,ij->i", points, points).max())) if len(points) else 0.0
    if reach <= MAX_SCAN_RANGE_M:
        return None
    return (
        f"its points reach {reach:.0f} m from the sensor, beyond {MAX_SCAN_RANGE_M:.0f} m "
        f"(a scan in millimetres, or not in the sensor's frame?)"
    )


def random_subset(points: np.ndarray, most: int, rng: np.random.Generator) -> np.ndarray:
    """At most `most` of the points' rows, a random subset kept in their order (all where fewer)."""
    if len(points) <= most:
        return points
    return points[np.sort(rng.choice(len(points), most, replace=False))]
