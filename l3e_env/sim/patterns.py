"""Beam patterns of spinning LiDARs: the built-in ones, user files (own YAML/JSON, or an Ouster
sensor's metadata JSON), and a pattern recognised or fitted from a scan's own points, so that a
recorded scan of another sensor can be read back onto its beams and columns."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml


class PatternError(ValueError):
    """A beam pattern file or a scan that cannot give a beam pattern."""


@dataclass(frozen=True)
class BeamPattern:
    """Elevation angles (deg) of the beams and azimuth steps per revolution. Ouster-style sensors
    also shift each beam's azimuth by a constant (`azimuth_offsets_deg`) and fire from a point
    `beam_origin_offset` metres out from the axis, in the column's direction. A Velodyne's beams
    leave from points `beam_vertical_offsets` metres from the axis across the beam, upwards in its
    vertical plane (its calibration's `vert_offset_correction`, which its driver adds to each
    return), so near returns lie off their beam's elevation as seen from the axis."""

    name: str
    elevations_deg: tuple[float, ...]
    n_azimuth: int
    max_range: float
    min_range: float
    image_width: int  # default width of the range image in observations
    azimuth_offsets_deg: tuple[float, ...] = ()  # per beam; empty: none
    beam_origin_offset: float = 0.0
    clockwise: bool = True  # the spin seen from above (a Velodyne's); False: counter-clockwise
    scan_start_deg: float = 180.0  # the azimuth at which a revolution begins (straight behind)
    time_field: str = "time"  # each point's time in a bag, as the sensor's driver names it (TIME_FIELDS)
    beam_vertical_offsets: tuple[float, ...] = ()  # per beam, metres; empty: none
    # an Ouster's lidar_to_sensor_transform (4x4 row-major, metres): its SDK's clouds come in the
    # sensor frame, this pattern's beams in the lidar frame; empty: the two are one
    lidar_to_sensor: tuple[float, ...] = ()

    def from_sensor_frame(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points of the SDK's sensor frame in this pattern's lidar frame (as given where the
        two are one)."""
        if not self.lidar_to_sensor:
            return np.asarray(points)
        to_sensor = np.asarray(self.lidar_to_sensor, dtype=np.float64).reshape(4, 4)
        return (np.asarray(points, dtype=np.float64) - to_sensor[:3, 3]) @ to_sensor[:3, :3]

    @property
    def n_beams(self) -> int:
        return len(self.elevations_deg)

    def _column_azimuths(self) -> np.ndarray:
        return 2 * np.pi * np.arange(self.n_azimuth) / self.n_azimuth

    def _beam_azimuth_offsets(self) -> np.ndarray:
        return np.deg2rad(np.asarray(self.azimuth_offsets_deg or (0.0,) * self.n_beams))

    def directions(self) -> np.ndarray:
        """Unit ray directions (B*A, 3) in the sensor frame, beam-major."""
        el = np.deg2rad(np.asarray(self.elevations_deg))[:, None]
        az = self._column_azimuths()[None, :] + self._beam_azimuth_offsets()[:, None]
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], axis=-1)
        return d.reshape(-1, 3).astype(np.float32)

    def origins(self) -> np.ndarray | None:
        """Where each ray starts (B*A, 3) in the sensor frame, beam-major; None: all at the origin."""
        if not self.beam_origin_offset and not self.beam_vertical_offsets:
            return None
        el = np.deg2rad(np.asarray(self.elevations_deg))[:, None]
        az = self._column_azimuths()[None, :] + self._beam_azimuth_offsets()[:, None]
        offsets = self._vertical_offsets()[:, None]
        out = self.beam_origin_offset - offsets * np.sin(el)  # horizontal part
        up = offsets * np.cos(el) * np.ones_like(az)
        origins = np.stack([out * np.cos(az), out * np.sin(az), up], axis=-1)
        return origins.reshape(-1, 3).astype(np.float32)

    def _vertical_offsets(self) -> np.ndarray:
        return np.asarray(self.beam_vertical_offsets or (0.0,) * self.n_beams, dtype=np.float64)

    def firing_share(self, points: np.ndarray) -> np.ndarray:
        """The share of a revolution at which a ray through each point fires, from the point's own
        azimuth (off-axis beam origins move it by a few tenths of a degree at most)."""
        azimuth = np.arctan2(points[:, 1].astype(np.float64), points[:, 0].astype(np.float64))
        turned = (np.deg2rad(self.scan_start_deg) - azimuth) * (1.0 if self.clockwise else -1.0)
        return np.mod(turned, 2.0 * np.pi) / (2.0 * np.pi)

    def spacing_deg(self) -> float:
        """The smallest angle between two beams."""
        beams = np.sort(np.asarray(self.elevations_deg))
        return float(np.diff(beams).min()) if len(beams) > 1 else 1.0

    def locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The beam and column of each point (N, 3) in the sensor frame, and how far (deg) its
        elevation lies from that beam's: range noise moves a return along its ray only."""
        points = np.asarray(points, dtype=np.float64)
        horizontal = np.hypot(points[:, 0], points[:, 1])
        azimuth = np.arctan2(points[:, 1], points[:, 0])
        if self.beam_origin_offset:  # the ray's own horizontal run starts at the beam's origin
            horizontal = horizontal - self.beam_origin_offset
        elevation = np.degrees(np.arctan2(points[:, 2], horizontal))
        beams = np.asarray(self.elevations_deg)
        beam = _nearest(beams, elevation)
        if self.beam_vertical_offsets and len(points):
            # seen from its beam's own origin; the beam first found is off by at most one near the sensor
            offsets = self._vertical_offsets()
            for _ in range(2):
                el = np.deg2rad(beams[beam])
                dz = offsets[beam]
                elevation = np.degrees(np.arctan2(points[:, 2] - dz * np.cos(el), horizontal + dz * np.sin(el)))
                beam = _nearest(beams, elevation)
        step = 2 * np.pi / self.n_azimuth
        azimuth = azimuth - self._beam_azimuth_offsets()[beam]
        column = np.round((azimuth % (2 * np.pi)) / step).astype(np.int64) % self.n_azimuth
        return beam, column, np.abs(elevation - beams[beam])


def _nearest(values: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The index into `values` of the one nearest each of `x` (the lower of two as near), by a binary
    search over the sorted values: memory of a few arrays of len(x), where comparing every x with
    every value takes len(x) x len(values)."""
    order = np.argsort(values, kind="stable")
    ordered = values[order]
    right = np.clip(np.searchsorted(ordered, x), 1, len(ordered) - 1) if len(ordered) > 1 else np.zeros(len(x), int)
    left = np.maximum(right - 1, 0)
    nearer_left = np.abs(x - ordered[left]) <= np.abs(ordered[right] - x)
    return order[np.where(nearer_left, left, right)].astype(np.int64)


# The per-point time field of a sensor's ROS driver, as LIO-SAM and FAST-LIO read it, since the
# revolution began: its words, numpy format and units a second. Velodyne's `time` is float32
# seconds, Ouster's `t` uint32 nanoseconds.
TIME_FIELDS = {"time": ("float32 seconds", "<f4", 1.0), "t": ("uint32 nanoseconds", "<u4", 1e9)}


def _image_width(n_azimuth: int) -> int:
    """The widest divisor of the column count up to 360: the observations' range-image width."""
    return max(w for w in range(1, min(n_azimuth, 360) + 1) if n_azimuth % w == 0)


PATTERNS: dict[str, BeamPattern] = {
    # Velodyne VLP-16: 16 beams over +-15 deg, 0.2 deg azimuth at 10 Hz, 100 m, every beam from the axis.
    "vlp16": BeamPattern("vlp16", tuple(np.linspace(-15, 15, 16)), 1800, 100.0, 0.5, 360),
    # Ouster OS0-128: 128 beams over +-45 deg, 1024 columns at 10 Hz, 50 m (datasheet, 80 % targets).
    # Its encoder angle runs 2 pi (1 - count / 90112) from the connector at the back (Ouster's
    # software manual), so it spins clockwise seen from above from straight behind, as a Velodyne.
    "os0-128": BeamPattern("os0-128", tuple(np.linspace(-45, 45, 128)), 1024, 50.0, 0.3, 256, time_field="t"),
}
# The VLP-16 as its calibration has it (the ROS driver's VLP16db.yaml, vert_offset_correction, which
# the driver adds to every return): its beams leave from 11.2 mm above the axis (the lowest, -15 deg)
# to 11.2 mm below it (the highest). The simulation's `vlp16` stays on the axis, as every figure of
# the README was measured with it (its scans differ by at most 11 mm); a real VLP-16's cloud is
# recognised as whichever of the two its near returns lie on.
PATTERNS["vlp16-calibrated"] = replace(
    PATTERNS["vlp16"],
    name="vlp16-calibrated",
    beam_vertical_offsets=(
        0.0112,
        0.0097,
        0.0081,
        0.0066,
        0.0051,
        0.0037,
        0.0022,
        0.0007,
        -0.0007,
        -0.0022,
        -0.0037,
        -0.0051,
        -0.0066,
        -0.0081,
        -0.0097,
        -0.0112,
    ),
)


def _with_width(pattern: BeamPattern) -> BeamPattern:
    return replace(pattern, image_width=_image_width(pattern.n_azimuth))


# The common spinning LiDARs, from their datasheets and their drivers' default calibrations, at 10 Hz.
# Velodyne HDL-32E: 32 beams every 4/3 deg from -30.67 to +10.67 deg, a firing cycle every 46.08 us
# (2170 columns a revolution), 100 m.
PATTERNS["hdl32e"] = _with_width(BeamPattern("hdl32e", tuple(np.linspace(-30.67, 10.67, 32)), 2170, 100.0, 1.0, 1))
# Velodyne VLP-32C (Ultra Puck): 32 beams from -25 to +15 deg, bunched round the horizon; the driver's
# calibration (VeloView-VLP-32C.yaml) turns each beam by +-1.4 or +-4.2 deg (rot_correction, listed
# by laser id), which shifts its returns' azimuth by the same; 0.2 deg azimuth, 200 m.
_VLP32C = (
    (-25.0, 1.4),
    (-1.0, -4.2),
    (-1.667, 1.4),
    (-15.639, -1.4),
    (-11.31, 1.4),
    (0.0, -1.4),
    (-0.667, 4.2),
    (-8.843, -1.4),
    (-7.254, 1.4),
    (0.333, -4.2),
    (-0.333, 1.4),
    (-6.148, -1.4),
    (-5.333, 4.2),
    (1.333, -1.4),
    (0.667, 4.2),
    (-4.0, -1.4),
    (-4.667, 1.4),
    (1.667, -4.2),
    (1.0, 1.4),
    (-3.667, -4.2),
    (-3.333, 4.2),
    (3.333, -1.4),
    (2.333, 1.4),
    (-2.667, -1.4),
    (-3.0, 1.4),
    (7.0, -1.4),
    (4.667, 1.4),
    (-2.333, -4.2),
    (-2.0, 4.2),
    (15.0, -1.4),
    (10.333, 1.4),
    (-1.333, -1.4),
)
_VLP32C_SORTED = sorted(_VLP32C)
PATTERNS["vlp32c"] = _with_width(
    BeamPattern(
        "vlp32c",
        tuple(e for e, _ in _VLP32C_SORTED),
        1800,
        200.0,
        0.5,
        1,
        azimuth_offsets_deg=tuple(a for _, a in _VLP32C_SORTED),
    )
)
# Ouster OS0, OS1 and OS2 with 32, 64 or 128 beams spread evenly over their vertical fields (90, 45 and
# 22.5 deg), 1024 columns (their 512 and 2048 column modes are recognised from a scan as `@512`,
# `@2048`), ranges at 80 % reflectivity. As `os0-128` (the simulation's), every beam leaves from the
# axis at its nominal angle: a unit's own angles, stagger and beam origin are in its metadata JSON,
# which `--sensor` reads.
for _line, _field, (_far, _near) in (
    ("os0", 90.0, (50.0, 0.3)),
    ("os1", 45.0, (120.0, 0.5)),
    ("os2", 22.5, (240.0, 0.8)),
):
    for _beams in (32, 64, 128):
        _name = f"{_line}-{_beams}"
        if _name not in PATTERNS:
            PATTERNS[_name] = BeamPattern(
                _name, tuple(np.linspace(-_field / 2, _field / 2, _beams)), 1024, _far, _near, 256, time_field="t"
            )
# Hesai PandarXT-32: 32 beams every degree from -16 to +15 deg, 0.18 deg azimuth (2000 columns), 120 m.
PATTERNS["xt32"] = _with_width(BeamPattern("xt32", tuple(float(e) for e in range(-16, 16)), 2000, 120.0, 0.05, 1))
# Hesai Pandar64: 64 beams from -25 to +15 deg, 0.167 deg apart between -6 and +2 deg, each turned by
# one of +-1.042, +-3.125, +-5.208 deg in azimuth (the user manual's nominal angle correction, by
# channel from the top), 0.2 deg azimuth, 200 m.
_PANDAR64_ELEVATIONS = (
    14.882,
    11.032,
    8.059,
    5.057,
    3.04,
    2.028,
    1.86,
    1.688,
    1.522,
    1.351,
    1.184,
    1.013,
    0.846,
    0.675,
    0.508,
    0.337,
    0.169,
    0.0,
    -0.169,
    -0.337,
    -0.508,
    -0.675,
    -0.845,
    -1.013,
    -1.184,
    -1.351,
    -1.522,
    -1.688,
    -1.86,
    -2.028,
    -2.198,
    -2.365,
    -2.536,
    -2.7,
    -2.873,
    -3.04,
    -3.21,
    -3.375,
    -3.548,
    -3.712,
    -3.884,
    -4.05,
    -4.221,
    -4.385,
    -4.558,
    -4.72,
    -4.892,
    -5.057,
    -5.229,
    -5.391,
    -5.565,
    -5.726,
    -5.898,
    -6.061,
    -7.063,
    -8.059,
    -9.06,
    -9.885,
    -11.032,
    -12.006,
    -12.974,
    -13.93,
    -18.889,
    -24.897,
)
_PANDAR64_AZIMUTHS = (-1.042,) * 6 + (1.042, 3.125, 5.208, -5.208, -3.125, -1.042) * 8 + (-1.042,) * 10
PATTERNS["pandar64"] = _with_width(
    BeamPattern(
        "pandar64", _PANDAR64_ELEVATIONS[::-1], 1800, 200.0, 0.3, 1, azimuth_offsets_deg=_PANDAR64_AZIMUTHS[::-1]
    )
)
BUILT_IN_SENSORS = tuple(PATTERNS)
PATTERN_FILES = (".yaml", ".yml", ".json")
BEAM_TOLERANCE = 0.25  # a return lies on a beam within this share of the beams' spacing


MAX_BEAMS, MAX_COLUMNS = 512, 8192  # beyond any spinning LiDAR's datasheet: a typo, refused before any array is made
OWN_KEYS = {
    "elevations_deg",
    "columns",
    "max_range",
    "min_range",
    "image_width",
    "azimuth_offsets_deg",
    "beam_origin_offset",
    "spin",
    "scan_start_deg",
    "time_field",
    "beam_vertical_offsets",
    "lidar_to_sensor",
}


def check_pattern(pattern: BeamPattern) -> None:
    """Raise PatternError naming what makes `pattern` unusable."""
    problem = None
    if pattern.n_beams < 1 or pattern.n_azimuth < 1 or not pattern.max_range > pattern.min_range >= 0:
        problem = (
            f"needs beams, columns and max_range > min_range >= 0 (got {pattern.n_beams} beams, "
            f"{pattern.n_azimuth} columns, range {pattern.min_range}-{pattern.max_range} m)"
        )
    elif not np.isfinite(pattern.elevations_deg).all() or not np.isfinite(pattern.azimuth_offsets_deg).all():
        problem = "holds an angle that is not a finite number"
    elif pattern.n_beams > MAX_BEAMS or pattern.n_azimuth > MAX_COLUMNS:
        problem = (
            f"has {pattern.n_beams} beams and {pattern.n_azimuth} columns; spinning LiDARs have at most "
            f"{MAX_BEAMS} beams and {MAX_COLUMNS} columns"
        )
    elif np.abs(pattern.elevations_deg).max() >= 90:
        problem = f"has a beam at {np.abs(pattern.elevations_deg).max():g} deg elevation; beams lie within +-90 deg"
    elif len(set(pattern.elevations_deg)) < pattern.n_beams and not pattern.azimuth_offsets_deg:
        problem = "has two beams at the same elevation and no azimuth offsets to tell them apart"
    elif np.abs(pattern.azimuth_offsets_deg).max(initial=0.0) > 180:
        problem = "has an azimuth offset beyond +-180 deg"
    elif pattern.azimuth_offsets_deg and len(pattern.azimuth_offsets_deg) != pattern.n_beams:
        problem = f"has {len(pattern.azimuth_offsets_deg)} azimuth offsets for {pattern.n_beams} beams"
    elif pattern.beam_vertical_offsets and len(pattern.beam_vertical_offsets) != pattern.n_beams:
        problem = f"has {len(pattern.beam_vertical_offsets)} vertical offsets for {pattern.n_beams} beams"
    elif not np.isfinite(pattern.beam_vertical_offsets).all() or not np.isfinite(pattern.beam_origin_offset):
        problem = "holds a beam origin offset that is not a finite number"
    elif pattern.lidar_to_sensor and not _rigid(pattern.lidar_to_sensor):
        problem = "has a lidar_to_sensor transform that is not a rigid 4x4 matrix (16 numbers, a rotation and a shift)"
    elif not np.isfinite(pattern.scan_start_deg):
        problem = f"has a scan start of {pattern.scan_start_deg} deg"
    elif pattern.time_field not in TIME_FIELDS:
        problem = f"has time_field {pattern.time_field!r}; it is one of {sorted(TIME_FIELDS)}"
    elif pattern.image_width < 1 or pattern.n_azimuth % pattern.image_width:
        problem = f"has image_width {pattern.image_width}, which does not divide its {pattern.n_azimuth} columns"
    if problem:
        raise PatternError(f"beam pattern {pattern.name} {problem}")


def _rigid(values: tuple[float, ...]) -> bool:
    if len(values) != 16 or not np.isfinite(values).all():
        return False
    m = np.asarray(values, dtype=np.float64).reshape(4, 4)
    return bool(np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-6) and np.allclose(m[3], [0, 0, 0, 1]))


def register_pattern(pattern: BeamPattern) -> None:
    """Add a user-defined beam pattern, usable by name in LidarConfig.model."""
    check_pattern(pattern)
    PATTERNS[pattern.name] = pattern


def get_pattern(name: str) -> BeamPattern:
    """A registered pattern, or one read from a pattern file whose path is `name` (kept under that
    name, so that a worker process given the same name reads the same file)."""
    if name not in PATTERNS and name.lower().endswith(PATTERN_FILES):
        register_pattern(load_pattern(name))
    if name not in PATTERNS:
        raise ValueError(
            f"unknown LiDAR model '{name}'; known: {sorted(PATTERNS)}, or a pattern file ({', '.join(PATTERN_FILES)})"
        )
    return PATTERNS[name]


# Ouster product lines: range (m) at 80 % reflectivity and the least range, from the datasheets.
_OUSTER_RANGES = {"OS-0": (50.0, 0.3), "OS-1": (120.0, 0.5), "OS-2": (240.0, 0.8), "OS-DOME": (45.0, 0.3)}


def _find(tree: dict, key: str):
    """A key's value anywhere in nested dicts (Ouster moved its metadata keys between firmwares)."""
    if key in tree:
        return tree[key]
    for value in tree.values():
        if isinstance(value, dict) and (found := _find(value, key)) is not None:
            return found
    return None


def _angles(name: str, key: str, value: object, limit: float, count: int | None = None) -> tuple[float, ...]:
    """A metadata field of beam angles: a list of 1 to MAX_BEAMS finite degrees within +-limit (and
    `count` of them where given), or PatternError naming the field."""
    if not isinstance(value, list) or not 1 <= len(value) <= MAX_BEAMS:
        raise PatternError(
            f"{name}: the Ouster metadata's {key} is a list of 1 to {MAX_BEAMS} angles, got {value!r:.80}"
        )
    if count is not None and len(value) != count:
        raise PatternError(f"{name}: the Ouster metadata has {count} beam_altitude_angles and {len(value)} {key}")
    if not all(isinstance(a, (int, float)) and not isinstance(a, bool) and abs(a) <= limit for a in value):
        bad = next(
            a for a in value if not (isinstance(a, (int, float)) and not isinstance(a, bool) and abs(a) <= limit)
        )
        raise PatternError(f"{name}: the Ouster metadata's {key} holds {bad!r}, not an angle within +-{limit:g} deg")
    return tuple(float(a) for a in value)


OUSTER_COLUMNS = (512, 1024, 2048, 4096)  # the lidar modes' columns (Ouster's software manual)


def _ouster_columns(name: str, meta: dict) -> int:
    """The columns a revolution of an Ouster's metadata has: columns_per_frame and lidar_mode
    ('1024x10') agree where both are given, and are one of the sensor's modes."""
    columns, mode = _find(meta, "columns_per_frame"), _find(meta, "lidar_mode")
    from_mode = None
    if mode is not None:
        head = str(mode).split("x")[0]
        if not isinstance(mode, str) or not head.isdigit() or int(head) not in OUSTER_COLUMNS:
            raise PatternError(
                f"{name}: the Ouster metadata's lidar_mode is {mode!r}, not one of 512x10, 1024x10, 2048x10, ..."
            )
        from_mode = int(head)
    if columns is None:
        if from_mode is None:
            raise PatternError(f"{name}: Ouster metadata without columns_per_frame or lidar_mode")
        return from_mode
    if isinstance(columns, bool) or not isinstance(columns, int) or columns not in OUSTER_COLUMNS:
        raise PatternError(
            f"{name}: the Ouster metadata's columns_per_frame is {columns!r}, not one of {OUSTER_COLUMNS}"
        )
    if from_mode is not None and from_mode != columns:
        raise PatternError(
            f"{name}: the Ouster metadata's lidar_mode {mode!r} disagrees with its columns_per_frame {columns}"
        )
    return columns


def _ouster_transform(name: str, value: object) -> tuple[float, ...]:
    """lidar_to_sensor_transform: 16 finite numbers, a rigid 4x4 (translation in mm, at most 1 m), in metres."""
    numbers = np.asarray(value if isinstance(value, list) else [], dtype=object).ravel()
    if len(numbers) != 16 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers):
        raise PatternError(
            f"{name}: the Ouster metadata's lidar_to_sensor_transform is 16 numbers (a 4x4), got {value!r:.80}"
        )
    matrix = numbers.astype(np.float64).reshape(4, 4)
    rotation = matrix[:3, :3]
    if (
        not np.isfinite(matrix).all()
        or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3)
        or not np.allclose(matrix[3], [0, 0, 0, 1])
        or np.abs(matrix[:3, 3]).max() > 1000.0
    ):
        raise PatternError(
            f"{name}: the Ouster metadata's lidar_to_sensor_transform is not a rigid transform with its "
            "translation in millimetres (at most 1 m)"
        )
    matrix[:3, 3] /= 1e3  # Ouster writes the translation in millimetres
    return tuple(float(v) for v in matrix.ravel())


def ouster_pattern(name: str, meta: dict) -> BeamPattern:
    """The beam pattern an Ouster sensor's metadata (its JSON, as a dict) describes; a field that
    disagrees with another or lies outside the sensor's physics raises PatternError naming it."""
    altitudes = _angles(name, "beam_altitude_angles", _find(meta, "beam_altitude_angles"), 90.0)
    found = _find(meta, "beam_azimuth_angles")
    azimuths = (
        (0.0,) * len(altitudes) if found is None else _angles(name, "beam_azimuth_angles", found, 360.0, len(altitudes))
    )
    columns = _ouster_columns(name, meta)
    rows = _find(meta, "pixels_per_column")
    if rows is not None and rows != len(altitudes):
        raise PatternError(
            f"{name}: the Ouster metadata has {len(altitudes)} beam angles and pixels_per_column {rows!r}"
        )
    product = str(_find(meta, "prod_line") or "").upper()
    far, near = next((r for p, r in _OUSTER_RANGES.items() if product.startswith(p)), (100.0, 0.3))
    # Ouster counts azimuth clockwise from the encoder angle: a beam's offset is the negative
    origin_mm = _find(meta, "lidar_origin_to_beam_origin_mm") or 0.0
    if isinstance(origin_mm, bool) or not isinstance(origin_mm, (int, float)) or not abs(origin_mm) <= 100.0:
        raise PatternError(
            f"{name}: the Ouster metadata's lidar_origin_to_beam_origin_mm is {origin_mm!r}, not within 100 mm"
        )
    to_sensor = _find(meta, "lidar_to_sensor_transform")
    return BeamPattern(
        name,
        altitudes,
        columns,
        far,
        near,
        _image_width(columns),
        tuple(-a for a in azimuths),
        float(origin_mm) / 1e3,
        time_field="t",
        lidar_to_sensor=() if to_sensor is None else _ouster_transform(name, to_sensor),
    )


def _own_pattern(name: str, spec: dict) -> BeamPattern:
    if unknown := set(spec) - OWN_KEYS:
        raise PatternError(f"{name}: unknown keys {sorted(unknown)} (a beam pattern file's keys: {sorted(OWN_KEYS)})")
    elevations = spec["elevations_deg"]
    if isinstance(elevations, dict):  # evenly spaced: {from, to, beams}
        beams = _count(name, "elevations_deg.beams", elevations["beams"], MAX_BEAMS)
        elevations = np.linspace(float(elevations["from"]), float(elevations["to"]), beams)
    elif not isinstance(elevations, list) or not 1 <= len(elevations) <= MAX_BEAMS:
        raise PatternError(f"{name}: elevations_deg is a list of 1 to {MAX_BEAMS} angles or {{from, to, beams}}")
    columns = _count(name, "columns", spec["columns"], MAX_COLUMNS)
    return BeamPattern(
        name,
        tuple(float(e) for e in elevations),
        columns,
        float(spec["max_range"]),
        float(spec.get("min_range", 0.0)),
        int(spec.get("image_width", _image_width(columns))),
        tuple(float(a) for a in spec.get("azimuth_offsets_deg", ())),
        float(spec.get("beam_origin_offset", 0.0)),
        _spin(spec.get("spin", "clockwise")),
        float(spec.get("scan_start_deg", 180.0)),
        str(spec.get("time_field", "time")),
        tuple(float(z) for z in spec.get("beam_vertical_offsets", ())),
        tuple(float(v) for v in np.ravel(spec.get("lidar_to_sensor", ()))),
    )


def _count(name: str, key: str, value: object, most: int) -> int:
    """A whole number from 1 to `most` (checked before any array of that size is made)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= most:
        raise PatternError(f"{name}: {key} is a whole number from 1 to {most}, got {value!r}")
    return value


def _spin(text: str) -> bool:
    """True for 'clockwise', False for 'counterclockwise' (seen from above)."""
    spins = {"clockwise": True, "counterclockwise": False}
    if text not in spins:
        raise PatternError(f"spin is 'clockwise' or 'counterclockwise' (seen from above), not {text!r}")
    return spins[text]


def load_pattern(path: str | Path) -> BeamPattern:
    """A beam pattern file, named by its path: this project's own keys (`elevations_deg` as a list or
    {from, to, beams}, `columns`, `max_range`, optional `min_range`, `azimuth_offsets_deg`,
    `beam_origin_offset` in metres, `beam_vertical_offsets` (metres, one a beam, as a Velodyne's
    calibration has them), `image_width`, `spin` clockwise or counterclockwise seen from
    above and `scan_start_deg`, where a revolution begins: they time a swept revolution;
    `time_field`, the per-point time a recorded bag carries: `time` as Velodyne's driver writes it,
    `t` as Ouster's), or an Ouster sensor's metadata JSON."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise PatternError(f"{path}: cannot read the beam pattern file ({exc.strerror})") from exc
    try:
        spec = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise PatternError(f"{path}: not a readable {path.suffix[1:].upper()} file: {exc}") from exc
    if not isinstance(spec, dict):
        raise PatternError(f"{path}: a beam pattern file holds a mapping of keys, not {type(spec).__name__}")
    try:
        make = ouster_pattern if _find(spec, "beam_altitude_angles") else _own_pattern
        pattern = make(str(path), spec)
    except PatternError:
        raise
    except KeyError as exc:
        raise PatternError(
            f"{path}: the beam pattern lacks {exc}; it needs elevations_deg, columns and max_range, "
            "or is an Ouster metadata file with beam_altitude_angles"
        ) from exc
    except (TypeError, ValueError) as exc:
        raise PatternError(f"{path}: a beam pattern value is not a number: {exc}") from exc
    check_pattern(pattern)
    return pattern


def _columns(points: np.ndarray, beam: np.ndarray) -> int:
    """Columns per revolution: 360 deg over the typical azimuth step between one beam's returns."""
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    order = np.lexsort((azimuth, beam))
    step = np.diff(azimuth[order])
    step = step[(np.diff(beam[order]) == 0) & (step > 1e-5)]
    if len(step) < 10:
        raise PatternError("the scan has too few returns beside each other on a beam to tell its columns")
    typical = float(np.median(step))
    regular = float(np.mean(np.abs(step / typical - 1) < 0.1))
    if regular < 0.5:  # a full revolution's returns follow each other one column apart, mostly
        raise PatternError(
            f"only {regular:.0%} of the steps between a beam's returns are its typical step: the scan "
            "is thinned or sampled, not every return of a revolution"
        )
    return int(round(2 * np.pi / typical))


def _elevations(points: np.ndarray, origin: float) -> np.ndarray:
    """Each return's elevation (deg) seen from a beam origin `origin` metres out from the axis."""
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]) - origin))


def _beam_origin(points: np.ndarray) -> float:
    """How far out from the axis the beams leave (an Ouster's lidar_origin_to_beam_origin, up to
    50 mm): the distance from which the returns' elevations bunch most tightly onto their beams.
    Range noise moves a return along its ray only, so seen from the right origin a beam's returns
    share one elevation; seen from the axis the near ones spread by up to a few tenths of a degree.
    Tightness is the mean log gap between neighbouring elevations, which needs no beam numbers."""
    horizontal = np.hypot(points[:, 0], points[:, 1])
    near = points[horizontal < 10.0] if (horizontal < 10.0).sum() >= 1000 else points  # far ones barely move
    near = near[:: max(1, len(near) // 40000)]  # enough to bunch, and quick to sort 120 times

    def looseness(origin: float) -> float:
        return float(np.mean(np.log(np.diff(np.sort(_elevations(near, origin))) + 1e-5)))

    coarse = min(np.arange(0.0, 0.0505, 0.001), key=looseness)
    fine = np.arange(max(coarse - 0.001, 0.0), coarse + 0.00105, 0.0001)
    return round(float(min(fine, key=looseness)), 4)


def _azimuth_offsets(points: np.ndarray, beam: np.ndarray, n_beams: int, columns: int) -> tuple[float, ...]:
    """Each beam's azimuth offset (deg) from the column grid, within half a column: the returns of a
    beam share one phase against the columns (an Ouster's staggered beams, or a grid that does not
    start on the x axis). Offsets that differ by whole columns cast the same rays, so the phase is
    all that a revolution's scan can tell and all that its simulation needs. A beam that leaves from
    off the axis shifts the azimuth of a return at horizontal distance h by its offset times
    (origin / h), so each beam's phase is fitted as a + b / h and `a` kept. Empty when the phases
    are not shared (returns not on an encoder's grid) or all zero."""
    step = 360.0 / columns
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    count = np.bincount(beam, minlength=n_beams).astype(float)
    if (count < 3).any():
        return ()
    turn = np.exp(2j * np.pi * azimuth / step)
    centre = np.angle(np.bincount(beam, turn.real, n_beams) + 1j * np.bincount(beam, turn.imag, n_beams))
    centre *= step / (2 * np.pi)
    phase = (azimuth - centre[beam] + step / 2) % step - step / 2  # about each beam's rough phase
    x = 1.0 / np.hypot(points[:, 0], points[:, 1])
    sx, sxx = np.bincount(beam, x, n_beams), np.bincount(beam, x * x, n_beams)
    sp, sxp = np.bincount(beam, phase, n_beams), np.bincount(beam, x * phase, n_beams)
    det = count * sxx - sx**2
    flat = det <= 1e-12 * count * sxx  # all returns at one distance: the mean phase
    slope = np.where(flat, 0.0, (count * sxp - sx * sp) / np.where(flat, 1.0, det))
    intercept = (sp - slope * sx) / count
    residual = phase - intercept[beam] - slope[beam] * x
    if np.sqrt(np.mean(residual**2)) > 0.1 * step:
        return ()
    offsets = (centre + intercept + step / 2) % step - step / 2
    return () if np.abs(offsets).max() < 1e-3 else tuple(round(float(o), 5) for o in offsets)


def _beams_of(elevation: np.ndarray, rings: np.ndarray | None) -> np.ndarray:
    """Each beam's elevation: the median of a ring's returns, else clusters of equal elevations."""
    if rings is not None:
        return np.array([np.median(elevation[rings == r]) for r in np.unique(rings)])
    ordered = np.sort(elevation)
    cut = np.flatnonzero(np.diff(ordered) > 0.05) + 1  # returns of one beam share its elevation
    return np.array([np.median(c) for c in np.split(ordered, cut)])


def fit_pattern(points: np.ndarray, rings: np.ndarray | None = None) -> tuple[BeamPattern, str]:
    """The beam pattern of one full revolution (N, 3) in its sensor's frame, and how it was found:
    the registered pattern with the fewest beams that every return lies on, with a return on its
    lowest or highest beam; of two with the same beams (`vlp16`, `vlp16-calibrated`), the one whose
    beams the returns lie closer to; its column count taken from the scan where that differs (a
    VLP-16 spinning at 20 Hz). Else one fitted to the scan: a beam per ring (`rings`, the cloud's ring
    field; the beams' origin offset fitted too) or per cluster of equal elevations."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    usable = np.isfinite(points).all(axis=1) & (np.linalg.norm(points, axis=1) > 0)
    if rings is not None:
        rings = np.asarray(rings).reshape(-1)
        if len(rings) != len(points):
            raise PatternError(f"{len(rings)} ring numbers for {len(points)} points")
        rings = rings[usable]
    points = points[usable]
    if len(points) < 100:
        raise PatternError(f"{len(points)} finite returns are too few to tell the sensor's beams")
    known = _known_pattern(points)
    return known if known is not None else _fitted_pattern(points, rings)


def _known_pattern(points: np.ndarray) -> tuple[BeamPattern, str] | None:
    """The registered pattern with the fewest beams that every return lies on, with a return on one of
    its end beams (of two with the same beams, the one the returns lie closer to), at the scan's column
    count and encoder phases; None where none fits."""
    fits: list[tuple] = []
    for known in PATTERNS.values():
        beam, _, off = known.locate(points)
        ends = {int(np.argmin(known.elevations_deg)), int(np.argmax(known.elevations_deg))}
        # a scan of another sensor with beams on this one's grid (an OS1-64 on the OS0-128's) leaves
        # both end beams empty; a scan of this sensor reaches the ground or the roof with one of them
        if off.max() <= BEAM_TOLERANCE * known.spacing_deg() and ends & set(np.unique(beam).tolist()):
            fits.append((known.n_beams, float(off.mean()), len(fits), known, beam))
    if not fits:
        return None
    _, _, _, known, beam = min(fits, key=lambda fit: fit[:3])
    columns = _columns(points, beam)
    pattern, how = known, f"{known.name}: every return lies on one of its beams"
    if abs(columns - known.n_azimuth) > 0.02 * known.n_azimuth:
        pattern = replace(known, name=f"{known.name}@{columns}", n_azimuth=columns, image_width=_image_width(columns))
        how = f"{known.name}'s beams at {columns} columns a revolution"
    phases = _own_phases(points, beam, pattern)
    if phases is not None:  # its columns lie off the datasheet's grid (a unit's own encoder offset)
        pattern = replace(pattern, name=f"{pattern.name}-phased", azimuth_offsets_deg=phases)
        how += ", " + _offset_words(phases)
    return pattern, how


def _fitted_pattern(points: np.ndarray, rings: np.ndarray | None) -> tuple[BeamPattern, str]:
    """A pattern fitted to the scan: a beam per ring (`rings`) or per cluster of equal elevations, the
    beams' origin offset, the columns and each beam's azimuth offset."""
    origin = _beam_origin(points)
    elevation = _elevations(points, origin)
    beams = np.sort(_beams_of(elevation, rings))
    if len(beams) > 512:
        raise PatternError(
            f"the returns lie at {len(beams)} elevations, not on a few beams: give one revolution of "
            "a spinning LiDAR in its own frame, not a map or a deskewed cloud"
        )
    r = np.linalg.norm(points, axis=1)
    fitted = BeamPattern(
        "fitted",
        tuple(float(b) for b in beams),
        1,
        float(np.ceil(r.max())),
        float(np.floor(10 * r.min()) / 10),
        1,
        beam_origin_offset=origin,
    )
    beam, _, off = fitted.locate(points)
    if off.max() > BEAM_TOLERANCE * fitted.spacing_deg():
        raise PatternError(
            f"a return lies {off.max():.2f} deg off its beam (beams {fitted.spacing_deg():.2f} deg "
            "apart)" + ("" if rings is not None else ", and the cloud has no ring field to sort the returns by beam")
        )
    columns = _columns(points, beam)
    fitted = replace(
        fitted,
        name=f"fitted-{len(beams)}x{columns}",
        n_azimuth=columns,
        image_width=_image_width(columns),
        azimuth_offsets_deg=_azimuth_offsets(points, beam, len(beams), columns),
    )
    check_pattern(fitted)
    how = f"fitted to the scan: {len(beams)} beams over {beams[0]:.1f} to {beams[-1]:.1f} deg, {columns} columns"
    if fitted.azimuth_offsets_deg:
        how += ", " + _offset_words(fitted.azimuth_offsets_deg)
    if origin:
        how += f", beams leaving {1e3 * origin:.1f} mm out from the axis"
    return fitted, how + (" (beams from the ring field)" if rings is not None else "")


ON_BEAMS = 0.9  # the share of a scan's returns that lie on the beams when it is read in the right frame


def in_lidar_frame(points: np.ndarray, pattern: BeamPattern) -> tuple[np.ndarray, str | None]:
    """A cloud of `pattern` in its lidar frame, the frame its beams are in, and a note where it came in
    another. An Ouster SDK's clouds (XYZLut) are in its sensor frame, the lidar frame turned 180 deg
    about z and lifted 36-38 mm (`lidar_to_sensor`, from the metadata): the frame whose returns lie
    closer to the beams is taken; a cloud that lies on them in neither is refused, naming both."""
    if not pattern.lidar_to_sensor:
        return points, None
    back = pattern.from_sensor_frame(points)
    tolerance = BEAM_TOLERANCE * pattern.spacing_deg()
    off = [pattern.locate(cloud)[2] for cloud in (points, back)]  # deg from the nearest beam
    shares = [float(np.mean(o <= tolerance)) for o in off]
    if max(shares) < ON_BEAMS:
        raise PatternError(
            f"{shares[0]:.0%} of the returns lie on {pattern.name}'s beams as given (its lidar frame) "
            f"and {shares[1]:.0%} turned back from its SDK's sensor frame: give one revolution of this "
            "sensor in either frame, or the metadata of the sensor that took it"
        )
    # the frames differ by a turn about z, which keeps every elevation, and a lift of a few cm, which
    # moves each a little: on beams far apart both lie within the tolerance, and the frame whose
    # returns lie closer to the beams is the lidar frame
    if np.median(off[1]) < np.median(off[0]):
        return back.astype(np.asarray(points).dtype), "read in the SDK's sensor frame, turned into the lidar frame"
    return points, None


def _own_phases(points: np.ndarray, beam: np.ndarray, pattern: BeamPattern) -> tuple[float, ...] | None:
    """The beams' azimuth phases read from the scan where they differ from the pattern's own by more
    than a twentieth of a column (else None): recognised by its beams, a sensor may still start its
    columns elsewhere, and the range image needs the phase its returns have."""
    step = 360.0 / pattern.n_azimuth
    read = np.asarray(_azimuth_offsets(points, beam, pattern.n_beams, pattern.n_azimuth) or (0.0,) * pattern.n_beams)
    own = np.asarray(pattern.azimuth_offsets_deg or (0.0,) * pattern.n_beams)
    apart = (read - own + step / 2) % step - step / 2
    if np.abs(apart).max() <= 0.05 * step:
        return None
    return tuple(round(float(o), 5) for o in own + apart)


def _offset_words(offsets: tuple[float, ...]) -> str:
    if max(offsets) - min(offsets) < 0.005:
        return f"columns {offsets[0]:+.2f} deg from the x axis"
    return f"beams staggered in azimuth by {min(offsets):.2f} to {max(offsets):.2f} deg"


def describe_pattern(pattern: BeamPattern) -> str:
    """A pattern in a few lines, as `l3e sensor` prints it."""
    beams = np.sort(pattern.elevations_deg)
    lines = [
        f"{pattern.name}: {pattern.n_beams} beams over {beams[0]:.2f} to {beams[-1]:.2f} deg "
        f"(closest {pattern.spacing_deg():.3f} deg apart), {pattern.n_azimuth} columns a revolution, "
        f"{pattern.min_range:g}-{pattern.max_range:g} m"
    ]
    if pattern.azimuth_offsets_deg:
        lines.append("  " + _offset_words(pattern.azimuth_offsets_deg))
    if pattern.beam_origin_offset:
        lines.append(f"  beams leave {1e3 * pattern.beam_origin_offset:.1f} mm out from the axis")
    if pattern.beam_vertical_offsets:
        lines.append(
            f"  beams leave {1e3 * min(pattern.beam_vertical_offsets):+.1f} to "
            f"{1e3 * max(pattern.beam_vertical_offsets):+.1f} mm from the axis, across the beam"
        )
    if pattern.lidar_to_sensor:
        m = np.asarray(pattern.lidar_to_sensor).reshape(4, 4)
        turn = np.degrees(np.arctan2(m[1, 0], m[0, 0]))
        lines.append(
            f"  its SDK's sensor frame: the lidar frame turned {turn:+.0f} deg about z and shifted "
            f"{1e3 * m[2, 3]:+.1f} mm in z (clouds in either frame are read)"
        )
    lines.append(
        f"  spins {'clockwise' if pattern.clockwise else 'counterclockwise'} seen from above from "
        f"{pattern.scan_start_deg:g} deg; a recorded bag's point time: {pattern.time_field} "
        f"({TIME_FIELDS[pattern.time_field][0]})"
    )
    return "\n".join(lines)


def save_pattern(pattern: BeamPattern, path: str | Path) -> Path:
    """Write `pattern` as a pattern file of this project's keys (YAML, or JSON by the suffix), to be
    given as `--sensor` again: a pattern fitted to a real scan, then simulated in one's own mesh."""
    path = Path(path)
    if not path.name.lower().endswith(PATTERN_FILES):
        raise PatternError(f"{path}: a beam pattern file ends in {', '.join(PATTERN_FILES)}")
    spec = {
        "elevations_deg": [round(float(e), 6) for e in pattern.elevations_deg],
        "columns": int(pattern.n_azimuth),
        "max_range": float(pattern.max_range),
        "min_range": float(pattern.min_range),
        "image_width": int(pattern.image_width),
    }
    if pattern.azimuth_offsets_deg:
        spec["azimuth_offsets_deg"] = [round(float(a), 6) for a in pattern.azimuth_offsets_deg]
    if pattern.beam_origin_offset:
        spec["beam_origin_offset"] = round(float(pattern.beam_origin_offset), 6)
    if pattern.beam_vertical_offsets:
        spec["beam_vertical_offsets"] = [round(float(z), 6) for z in pattern.beam_vertical_offsets]
    if not pattern.clockwise:
        spec["spin"] = "counterclockwise"
    if pattern.scan_start_deg != 180.0:
        spec["scan_start_deg"] = float(pattern.scan_start_deg)
    if pattern.time_field != "time":
        spec["time_field"] = pattern.time_field
    if pattern.lidar_to_sensor:
        spec["lidar_to_sensor"] = [round(float(v), 6) for v in pattern.lidar_to_sensor]
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".json":
        path.write_text(json.dumps(spec, indent=1) + "\n")
    else:
        path.write_text(f"# beam pattern {pattern.name}\n" + yaml.safe_dump(spec, sort_keys=False))
    return path
