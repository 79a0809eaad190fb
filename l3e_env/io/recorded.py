"""A scan read from a recording (a ROS bag or an Ouster capture), and the error of a recording
that cannot be read at all."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from l3e_env.sim.patterns import BeamPattern


class RecordingError(ValueError):
    """A recording, or a topic of it, that cannot be read as LiDAR scans; the message says why."""


@dataclass
class RecordedScan:
    name: str  # "<recording> [<topic>] #<k>": the k-th scan read from `start`
    stamp: float | None  # seconds: the scan's own stamp, else when it was recorded
    points: np.ndarray | None  # (N, 3) float64, NaN kept (the judge drops them); None where `error`
    error: str | None = None  # the scan could not be read as points: why
    rings: np.ndarray | None = None  # (N,) the beam of each point, where the recording tells it
    pattern: BeamPattern | None = None  # the sensor's beams, where the recording carries its metadata
    frame: str | None = None  # how the points were turned into the sensor's lidar frame, where they were
    up: np.ndarray | None = None  # the up direction in the scan's frame, where the recording's IMU gives it
    up_source: str | None = None  # where `up` came from, or why the recording's IMU gave none
