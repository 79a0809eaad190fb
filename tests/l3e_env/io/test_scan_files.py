"""Scan files whose headers disagree with their data, or whose values are no coordinates: refused by
name, for any count the header may claim (hypothesis), never read as some other cloud."""

from __future__ import annotations

import json
import re
import warnings

import numpy as np
import pytest
import trimesh

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from l3e_env.io.scan_files import ScanFileError, read_scan  # noqa: E402
from l3e_env.sim.patterns import PatternError, ouster_pattern  # noqa: E402

POINTS = np.arange(60, dtype=np.float32).reshape(20, 3)
ANY = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _pcd(points: np.ndarray, binary: bool, **header: str) -> bytes:
    lines = {
        "VERSION": "0.7",
        "FIELDS": "x y z",
        "SIZE": "4 4 4",
        "TYPE": "F F F",
        "COUNT": "1 1 1",
        "WIDTH": str(len(points)),
        "HEIGHT": "1",
        "POINTS": str(len(points)),
    }
    lines.update(header)
    text = "".join(f"{k} {v}\n" for k, v in lines.items() if v is not None)
    text += f"DATA {'binary' if binary else 'ascii'}\n"
    body = points.astype("<f4").tobytes() if binary else "".join(" ".join(map(str, p)) + "\n" for p in points).encode()
    return text.encode() + body


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_a_pcd_as_its_header_says_reads_and_the_file_read_back_is_the_cloud(tmp_path, binary):
    path = tmp_path / "scan.pcd"
    path.write_bytes(_pcd(POINTS, binary))
    assert np.array_equal(read_scan(path), POINTS)
    path.write_bytes(_pcd(POINTS, binary) + b"\n")  # a writer's closing newline
    assert np.array_equal(read_scan(path), POINTS)
    path.write_bytes(_pcd(POINTS[:0], binary))  # an empty cloud reads as one, ascii as binary (issue 98)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_scan(path).shape == (0, 3)


@ANY
@given(claimed=st.integers(0, 10**13), binary=st.booleans())
def test_a_pcd_whose_points_disagree_with_its_data_is_refused_for_any_count(tmp_path, claimed, binary):
    path = tmp_path / "scan.pcd"
    path.write_bytes(_pcd(POINTS, binary, POINTS=str(claimed), WIDTH=str(claimed)))
    if claimed == len(POINTS):
        assert len(read_scan(path)) == len(POINTS)
        return
    with pytest.raises(ScanFileError, match=rf"{path}: the PCD (header says|is cut short)"):
        read_scan(path)


@pytest.mark.parametrize(
    ("header", "named"),
    [
        ({"POINTS": None, "WIDTH": None}, "has no POINTS"),
        ({"POINTS": "-5", "WIDTH": "-5"}, "POINTS is -5"),
        ({"POINTS": "four"}, "POINTS is four"),
        ({"COUNT": "0 1 1"}, "COUNT is 0 1 1"),
        ({"SIZE": None}, "SIZE is missing"),
        ({"TYPE": None}, "TYPE names 0 types"),
        ({"SIZE": "4 4"}, "SIZE is 4 4"),
        ({"WIDTH": "7"}, r"WIDTH x HEIGHT \(7 x 1\) disagrees with its POINTS 20"),
        ({"COUNT": "2 1 1"}, "(cut short|numbers a point)"),
    ],
)
@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_a_pcd_header_line_that_is_missing_or_wrong_is_named(tmp_path, header, named, binary):
    path = tmp_path / "scan.pcd"
    path.write_bytes(_pcd(POINTS, binary, **header))
    with pytest.raises(ScanFileError, match=rf"{path}: .*{named}"):
        read_scan(path)


def _ply(tmp_path, binary: bool, **change: str):
    path = tmp_path / "scan.ply"
    path.write_bytes(
        trimesh.PointCloud(POINTS.astype(np.float64)).export(file_type="ply", encoding="binary" if binary else "ascii")
    )
    if change:
        text = path.read_bytes()
        for old, new in change.items():
            text = text.replace(old.encode(), new.encode(), 1)
        path.write_bytes(text)
    return path


@ANY
@given(claimed=st.integers(-10, 10**9), binary=st.booleans())
def test_a_ply_whose_vertex_count_disagrees_with_its_data_is_refused_for_any_count(tmp_path, claimed, binary):
    path = _ply(tmp_path, binary, **{"element vertex 20": f"element vertex {claimed}"})
    if claimed == len(POINTS):
        assert np.allclose(read_scan(path), POINTS)
        return
    with pytest.raises(ScanFileError, match=rf"{path}: .*(disagrees with the data|must name an element and a count)"):
        read_scan(path)


def test_a_ply_of_a_format_that_is_not_read_is_named(tmp_path):
    path = _ply(tmp_path, True, binary_little_endian="binary_middle_endian")
    with pytest.raises(ScanFileError, match="PLY format 'binary_middle_endian' is not read"):
        read_scan(path)


@pytest.mark.parametrize(
    "header, named",
    [
        ("property quux x\nproperty float y\nproperty float z\n", "'property quux x' is no property"),
        ("property float x\nproperty float y\n", r"vertices have the properties \['x', 'y'\], not x, y and z"),
    ],
)
def test_a_ply_property_of_no_ply_type_or_without_z_is_named(tmp_path, header, named):
    """Issue 98: before, "cannot be read as PLY: 'quux'" and "'z'"."""
    path = tmp_path / "scan.ply"
    path.write_text(f"ply\nformat ascii 1.0\nelement vertex 2\n{header}end_header\n1 2 3\n4 5 6\n")
    with pytest.raises(ScanFileError, match=named):
        read_scan(path)


@pytest.mark.parametrize(
    "values",
    [np.ones((5, 3), bool), np.ones((5, 3), complex), np.array([["2026-01-01"] * 3] * 5, dtype="datetime64[D]")],
    ids=["bool", "complex", "datetime"],
)
def test_a_npy_of_values_that_are_no_coordinates_is_refused_by_name(tmp_path, values):
    path = tmp_path / "scan.npy"
    np.save(path, values)
    with pytest.raises(ScanFileError, match=re.escape(f"{path}: holds {values.dtype} values, not real numbers")):
        read_scan(path)


def test_a_structured_npy_with_x_y_z_fields_reads_as_its_points(tmp_path):
    cloud = np.zeros(20, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    for i, axis in enumerate("xyz"):
        cloud[axis] = POINTS[:, i]
    np.save(tmp_path / "scan.npy", cloud)
    assert np.array_equal(read_scan(tmp_path / "scan.npy"), POINTS)


def _metadata() -> dict:
    return {
        "beam_altitude_angles": list(np.linspace(-45, 45, 128)),
        "beam_azimuth_angles": [0.0] * 128,
        "lidar_mode": "1024x10",
        "data_format": {"columns_per_frame": 1024, "pixels_per_column": 128},
        "lidar_origin_to_beam_origin_mm": 27.67,
        "lidar_to_sensor_transform": [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1],
        "prod_line": "OS-0-128",
    }


@pytest.mark.parametrize(
    ("change", "named"),
    [
        ({"beam_altitude_angles": [1e30] + [0.0] * 127}, "beam_altitude_angles holds 1e\\+30"),
        ({"beam_azimuth_angles": [0.0] * 12}, "128 beam_altitude_angles and 12 beam_azimuth_angles"),
        ({"lidar_to_sensor_transform": [1, 2, 3]}, "lidar_to_sensor_transform is 16 numbers"),
        ({"lidar_to_sensor_transform": [2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1]}, "not a rigid transform"),
        ({"lidar_mode": "2048x10"}, "lidar_mode '2048x10' disagrees with its columns_per_frame 1024"),
        ({"data_format": {"columns_per_frame": 10**12}}, "columns_per_frame is 1000000000000"),
        ({"data_format": {"columns_per_frame": 1024, "pixels_per_column": 64}}, "pixels_per_column 64"),
        ({"beam_altitude_angles": [float("nan")] * 128}, "beam_altitude_angles holds nan"),
        ({"lidar_mode": None, "data_format": {}}, "without columns_per_frame or lidar_mode"),
    ],
)
def test_ouster_metadata_outside_the_sensors_physics_is_refused_by_field(change, named):
    meta = _metadata()
    meta.update(change)
    meta = {k: v for k, v in meta.items() if v is not None}
    assert ouster_pattern("good", _metadata()).n_azimuth == 1024
    with pytest.raises(PatternError, match=named):
        ouster_pattern("meta", meta)


def test_a_pcap_metadata_that_is_nan_or_nested_too_deep_is_named_before_the_sdk_reads_it(tmp_path):
    from l3e_env.io.ouster import CaptureError, _check_metadata

    capture = tmp_path / "capture.pcap"
    capture.write_bytes(b"\0" * 64)
    meta = tmp_path / "capture.json"
    meta.write_text(json.dumps(_metadata()).replace("27.67", "NaN"))
    with pytest.raises(CaptureError, match="capture.json: the metadata of capture.pcap is not readable JSON.*NaN"):
        _check_metadata(capture, None)
    meta.write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(CaptureError, match="nested too deep"):
        _check_metadata(capture, None)
    meta.write_text(json.dumps(_metadata() | {"lidar_mode": "1024x10", "data_format": {"columns_per_frame": 10**12}}))
    with pytest.raises(CaptureError, match="does not describe a sensor: .*columns_per_frame"):
        _check_metadata(capture, meta)
