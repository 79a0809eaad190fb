"""A recording read scan by scan, whichever kind it is: an Ouster capture (`.osf`, `.pcap`) or a
ROS bag."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from l3e_env.io.ouster import CaptureError, is_capture, read_capture
from l3e_env.io.recorded import RecordedScan, RecordingError
from l3e_env.io.rosbag import read_bag


def read_recording(
    path: str | Path,
    topic: str | None = None,
    every: int = 1,
    start: float | None = None,
    end: float | None = None,
    metadata: str | Path | None = None,
    sensor_index: int | None = None,
    one_sensor: bool = False,
) -> Iterator[RecordedScan]:
    """`read_capture` for an Ouster capture (with its `metadata` JSON where a .pcap needs one, the
    sensor `sensor_index` of several, `one_sensor` to refuse several without one; a topic is a bag's,
    and refused), else `read_bag`. RecordingError where it cannot be read."""
    if is_capture(path):
        if topic:
            raise CaptureError(f"{path}: an Ouster capture has no topics; --topic reads a ROS bag")
        return read_capture(path, metadata, every, start, end, sensor_index, one_sensor)
    if sensor_index is not None:
        raise RecordingError(f"{path}: --sensor-index picks a sensor of an Ouster capture; a bag's scans are a topic's")
    return read_bag(path, topic, every, start, end)
