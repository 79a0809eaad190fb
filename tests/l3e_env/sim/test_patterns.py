"""Beam patterns: Ouster-style offsets simulated and read back, pattern files, and the sensor
recognised from a scan's own points, as `l3e judge` does for scans of another LiDAR."""

import dataclasses
import json
import re

import numpy as np
import pytest
import trimesh

from l3e_env.cli.main import main
from l3e_env.config import LidarConfig
from l3e_env.core.transforms import pose_to_matrix
from l3e_env.experiments.judge import JudgeOptions, format_judgement, judge_scans, recognise_sensor
from l3e_env.localizability.scan_mc import range_image_mesh
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.patterns import (
    BUILT_IN_SENSORS,
    PATTERNS,
    BeamPattern,
    PatternError,
    describe_pattern,
    fit_pattern,
    get_pattern,
    load_pattern,
    save_pattern,
)
from l3e_env.sim.raycast import EmbreeCaster, PyBulletCaster

# a 64-beam Ouster-like sensor: beams on the OS0-128's grid spacing, staggered azimuths, beams
# leaving 27 mm out from the axis
OUSTER_LIKE = BeamPattern(
    "ouster-like",
    tuple(np.linspace(-22.5, 22.5, 64)),
    512,
    60.0,
    0.3,
    256,
    tuple(np.tile([-4.2, -1.4, 1.4, 4.2], 16)),
    0.027,
)
POSE = pose_to_matrix(np.array([40.0, 0.3, 0.85, 0.05, -0.03, 0.1]))


@pytest.fixture(autouse=True)
def _registered_patterns_restored():
    """Patterns fitted or read in one test are not known to the next (as in separate runs)."""
    before = dict(PATTERNS)
    yield
    PATTERNS.clear()
    PATTERNS.update(before)


def _scan(mesh, pattern: BeamPattern, pose=POSE, rng=None, caster=EmbreeCaster):
    """A scan of `pattern`, registered only while it is cast."""
    PATTERNS[pattern.name] = pattern
    try:
        return Lidar(caster(mesh), LidarConfig(model=pattern.name)).scan(pose, rng)
    finally:
        del PATTERNS[pattern.name]


def test_offset_beams_are_cast_from_their_own_origins_and_read_back_onto_their_beams():
    room = trimesh.creation.box(extents=(10.0, 6.0, 4.0))
    for caster in (EmbreeCaster, PyBulletCaster.for_mesh):
        scan = _scan(room, OUSTER_LIKE, np.eye(4), caster=caster)
        p = np.abs(scan.points.astype(np.float64))
        assert np.isclose(p[:, 0], 5, atol=1e-3).sum() > 1000
        assert (np.isclose(p, [5, 3, 2], atol=1e-3).any(axis=1)).all()  # on the box's faces
        # the return of beam b, column c lies on the ray from 27 mm out along column c's azimuth
        az = 2 * np.pi * scan.column / OUSTER_LIKE.n_azimuth
        ray = scan.points - 0.027 * np.c_[np.cos(az), np.sin(az), np.zeros_like(az)]
        el = np.degrees(np.arctan2(ray[:, 2], np.hypot(ray[:, 0], ray[:, 1])))
        np.testing.assert_allclose(el, np.asarray(OUSTER_LIKE.elevations_deg)[scan.beam], atol=1e-3)
        beam, column, off = OUSTER_LIKE.locate(scan.points)
        assert (beam == scan.beam).all() and (column == scan.column).all() and off.max() < 1e-3
    # without the offsets the same points would not read back: the beam origin is 27 mm out
    bare = BeamPattern("bare", OUSTER_LIKE.elevations_deg, 512, 60.0, 0.3, 256)
    assert bare.locate(scan.points)[2].max() > 0.25 * bare.spacing_deg()


def _driver_points(distance: np.ndarray, pattern: BeamPattern, offsets_m: list[float]) -> np.ndarray:
    """A Velodyne cloud as its ROS driver computes it from the calibration's vert_offset_correction:
    horizontal run d cos(el) - dz sin(el), height d sin(el) + dz cos(el)."""
    el = np.deg2rad(np.asarray(pattern.elevations_deg))[:, None]
    az = 2 * np.pi * np.arange(pattern.n_azimuth)[None, :] / pattern.n_azimuth
    dz = np.asarray(offsets_m)[:, None]
    run = distance * np.cos(el) - dz * np.sin(el)
    return np.stack([run * np.cos(az), run * np.sin(az), distance * np.sin(el) + dz * np.cos(el)], -1).reshape(-1, 3)


def test_a_vlp16s_cloud_is_recognised_with_or_without_its_calibrations_vertical_offsets():
    """The driver's VLP16db.yaml puts the -15 deg beam 11.2 mm above the axis and the +15 deg one
    11.2 mm below, and adds that to every return. Near returns (a leg at 0.8 m) then lie 0.8 deg
    off their beams as seen from the axis, yet the cloud is recognised as a VLP-16
    (`vlp16-calibrated`), read back onto its beams, and cast again from where the driver says each
    beam leaves; a cloud from the axis (the simulation's `vlp16`) stays `vlp16`."""
    calibrated = PATTERNS["vlp16-calibrated"]
    offsets = [11.2, 9.7, 8.1, 6.6, 5.1, 3.7, 2.2, 0.7, -0.7, -2.2, -3.7, -5.1, -6.6, -8.1, -9.7, -11.2]
    distance = np.full((16, 1800), 6.0)
    distance[:, :25] = 0.8
    points = _driver_points(distance, calibrated, [z / 1e3 for z in offsets])
    pattern, how = fit_pattern(points)
    assert pattern is calibrated and how.startswith("vlp16-calibrated: every return")
    beam, column, off = calibrated.locate(points)
    assert (beam == np.repeat(np.arange(16), 1800)).all() and (column == np.tile(np.arange(1800), 16)).all()
    assert off.max() < 1e-4
    np.testing.assert_allclose(
        calibrated.origins() + 6.0 * calibrated.directions(),
        _driver_points(np.full((16, 1800), 6.0), calibrated, [z / 1e3 for z in offsets]),
        atol=1e-5,
    )
    # from the axis, the leg's returns on the outer beams lie 0.8 deg off: more than the quarter spacing
    assert PATTERNS["vlp16"].locate(points)[2].max() > 0.25 * PATTERNS["vlp16"].spacing_deg()
    assert fit_pattern(_driver_points(distance, calibrated, [0.0] * 16))[0] is PATTERNS["vlp16"]
    # with no near return both fit; the one whose beams the returns lie on is taken
    assert (
        fit_pattern(_driver_points(np.full((16, 1800), 6.0), calibrated, [z / 1e3 for z in offsets]))[0] is calibrated
    )
    assert "-11.2 to +11.2 mm from the axis, across the beam" in describe_pattern(calibrated)


@pytest.mark.parametrize("model", [m for m in BUILT_IN_SENSORS if m != "vlp16-calibrated"])
def test_a_scan_of_a_built_in_sensor_is_recognised_as_it(mine, model):
    scan = Lidar(EmbreeCaster(mine.mesh), LidarConfig(model=model)).scan(POSE, np.random.default_rng(0))
    for rings in (None, scan.beam):
        pattern, how = fit_pattern(scan.points, rings)
        assert pattern is PATTERNS[model] and how.startswith(model)
    # every other column: the same beams at half the columns (a VLP-16 spinning at 20 Hz)
    half = scan.column % 2 == 0
    pattern, how = fit_pattern(scan.points[half])
    assert pattern.name == f"{model}@{PATTERNS[model].n_azimuth // 2}"
    assert pattern.elevations_deg == PATTERNS[model].elevations_deg


def test_the_common_sensors_are_built_in_from_their_datasheets():
    for model in ("hdl32e", "vlp32c", "xt32", "pandar64", *(f"os{k}-{n}" for k in range(3) for n in (32, 64, 128))):
        assert model in BUILT_IN_SENSORS
    assert PATTERNS["os1-64"].n_beams == 64 and max(PATTERNS["os1-64"].elevations_deg) == pytest.approx(22.5)
    assert min(PATTERNS["vlp32c"].elevations_deg) == -25 and max(PATTERNS["vlp32c"].elevations_deg) == 15
    # the VLP-32C bunches its beams at the horizon, 1/3 deg apart, and turns each by +-1.4 or +-4.2 deg
    assert PATTERNS["vlp32c"].spacing_deg() == pytest.approx(1 / 3, abs=1e-3)
    assert {abs(a) for a in PATTERNS["vlp32c"].azimuth_offsets_deg} == {1.4, 4.2}
    assert PATTERNS["pandar64"].spacing_deg() == pytest.approx(0.16, abs=0.01)


@pytest.mark.parametrize("columns", [512, 2048])
def test_an_ousters_column_modes_are_recognised(mine, columns):
    mode = dataclasses.replace(PATTERNS["os1-64"], name="os1-64-mode", n_azimuth=columns)
    pattern, how = fit_pattern(_scan(mine.mesh, mode, rng=np.random.default_rng(5)).points)
    assert pattern.name == f"os1-64@{columns}" and how == f"os1-64's beams at {columns} columns a revolution"


def test_a_built_in_sensor_whose_columns_start_off_its_grid_keeps_the_scans_phase(mine):
    turned = dataclasses.replace(PATTERNS["hdl32e"], name="hdl32e-turned", azimuth_offsets_deg=(0.05,) * 32)
    scan = _scan(mine.mesh, turned, rng=np.random.default_rng(6))
    pattern, how = fit_pattern(scan.points)
    assert pattern.name == "hdl32e-phased" and "columns +0.05 deg from the x axis" in how
    beam, column, _ = pattern.locate(scan.points)
    assert (beam == scan.beam).all() and (column == scan.column).all()


def _phase_error(fitted: BeamPattern, true: BeamPattern) -> float:
    """The largest difference (deg) between fitted and true beam azimuth offsets, modulo a column."""
    step = 360.0 / true.n_azimuth
    got, want = (np.asarray(p.azimuth_offsets_deg or (0.0,) * p.n_beams) for p in (fitted, true))
    return float(np.abs((got - want + step / 2) % step - step / 2).max())


def test_another_sensor_is_fitted_from_its_scan_not_taken_for_one_whose_beam_grid_it_shares(mine):
    """The Ouster-like beams lie within a quarter spacing of the OS0-128's, but both of that
    sensor's end beams (+-45 deg) would have returns in the mine: it is fitted instead, with the
    origin its beams leave from and their stagger, with or without the ring field."""
    scan = _scan(mine.mesh, OUSTER_LIKE, rng=np.random.default_rng(1))
    for rings in (None, scan.beam):
        pattern, how = fit_pattern(scan.points, rings)
        assert pattern.name == "fitted-64x512" and re.search(r"64 beams over -22\.\d to 22\.\d deg", how), how
        assert ("ring field" in how) == (rings is not None)
        # seen from the axis, not the beam's origin 27 mm out, a beam's returns on the floor 2 m away
        # would lie up to 0.3 deg nearer the horizon: the origin is where they bunch onto their beams
        assert pattern.beam_origin_offset == pytest.approx(0.027, abs=3e-4) and "27.0 mm" in how
        np.testing.assert_allclose(pattern.elevations_deg, OUSTER_LIKE.elevations_deg, atol=0.005)
        # -4.2, -1.4, 1.4 and 4.2 deg are +0.019, +0.006, -0.006 and -0.019 deg off the 0.703 deg columns
        assert _phase_error(pattern, OUSTER_LIKE) < 0.002 and "staggered in azimuth by -0.02 to 0.02 deg" in how
        beam, _, _ = pattern.locate(scan.points)
        assert (beam == scan.beam).all()


def test_an_ouster_cloud_without_a_ring_field_and_a_grid_off_the_x_axis_are_read_back(mine):
    """A 128-beam Ouster's cloud without its ring field: beams 15.2 mm out, staggered by +-1.4 and
    +-4.2 deg, fitted as from the metadata; a 32-beam sensor (an XT32's beams at 1800 columns) whose
    columns start 0.07 deg round."""
    ouster = BeamPattern(
        "ouster",
        tuple(np.linspace(-45, 45, 128)),
        1024,
        50.0,
        0.3,
        256,
        tuple(np.tile([4.23, 1.41, -1.41, -4.23], 32)),
        0.0152,
    )
    pattern, how = fit_pattern(_scan(mine.mesh, ouster, rng=np.random.default_rng(2)).points)
    assert pattern.name == "fitted-128x1024" and "15.2 mm" in how, how
    np.testing.assert_allclose(pattern.elevations_deg, ouster.elevations_deg, atol=0.005)
    assert _phase_error(pattern, ouster) < 0.002
    grid = BeamPattern("grid", tuple(np.linspace(-16, 15, 32)), 1800, 100.0, 0.3, 360, (0.07,) * 32)
    scan = _scan(mine.mesh, grid, rng=np.random.default_rng(3))
    pattern, how = fit_pattern(scan.points)
    assert pattern.beam_origin_offset == 0 and "mm out" not in how
    assert _phase_error(pattern, grid) < 1e-3 and "columns +0.07 deg from the x axis" in how
    beam, column, _ = pattern.locate(scan.points)
    assert (beam == scan.beam).all() and (column == scan.column).all()


def test_clouds_that_are_not_one_revolution_are_refused(rng, mine):
    scan = Lidar(EmbreeCaster(mine.mesh), LidarConfig()).scan(POSE, rng)
    sampled = scan.points[rng.choice(len(scan), 4000, replace=False)]  # as a classifier's input is
    with pytest.raises(PatternError, match="thinned or sampled"):
        fit_pattern(sampled)
    with pytest.raises(PatternError, match="too few"):
        fit_pattern(np.full((500, 3), np.nan))
    with pytest.raises(PatternError, match="not on a few beams"):
        fit_pattern(rng.normal(size=(5000, 3)) * 10)
    with pytest.raises(PatternError, match="3 ring numbers for 200 points"):
        fit_pattern(rng.normal(size=(200, 3)), np.arange(3))


def test_pattern_files_in_the_projects_own_keys_and_as_ouster_metadata(tmp_path):
    own = tmp_path / "xt32.yaml"
    own.write_text("elevations_deg: {from: -16, to: 15, beams: 32}\ncolumns: 2000\nmax_range: 120\nmin_range: 0.05\n")
    pattern = load_pattern(own)
    assert pattern.name == str(own) and pattern.n_beams == 32 and pattern.elevations_deg[-1] == 15.0
    assert pattern.n_azimuth == 2000 and pattern.image_width == 250 and pattern.beam_origin_offset == 0
    listed = tmp_path / "listed.json"
    listed.write_text(
        json.dumps(
            {
                "elevations_deg": [-10, 0, 10],
                "columns": 360,
                "max_range": 30,
                "azimuth_offsets_deg": [1, 0, -1],
                "beam_origin_offset": 0.01,
            }
        )
    )
    assert load_pattern(listed).azimuth_offsets_deg == (1.0, 0.0, -1.0)
    velodyne = tmp_path / "velodyne.yaml"
    velodyne.write_text(
        "elevations_deg: [-10, 0, 10]\ncolumns: 360\nmax_range: 30\nbeam_vertical_offsets: [0.01, 0, -0.01]\n"
    )
    assert load_pattern(velodyne).beam_vertical_offsets == (0.01, 0.0, -0.01)
    calibrated = PATTERNS["vlp16-calibrated"]
    assert (
        load_pattern(save_pattern(calibrated, tmp_path / "vlp16.yaml")).beam_vertical_offsets
        == calibrated.beam_vertical_offsets
    )
    altitudes, azimuths = list(np.linspace(21.1, -21.1, 64)), [3.1, 0.9, -1.2, -3.3] * 16
    legacy = {
        "prod_line": "OS-1-64",
        "lidar_mode": "2048x10",
        "beam_altitude_angles": altitudes,
        "beam_azimuth_angles": azimuths,
        "lidar_origin_to_beam_origin_mm": 15.806,
    }
    nested = {
        "sensor_info": {"prod_line": "OS-1-64"},
        "config_params": {"lidar_mode": "2048x10"},  # agreeing with its columns (disagreeing: refused)
        "lidar_data_format": {"columns_per_frame": 2048},
        "beam_intrinsics": {
            "beam_altitude_angles": altitudes,
            "beam_azimuth_angles": azimuths,
            "lidar_origin_to_beam_origin_mm": 15.806,
        },
    }
    for i, meta in enumerate((legacy, nested)):
        path = tmp_path / f"os1-{i}.json"
        path.write_text(json.dumps(meta))
        os1 = get_pattern(str(path))  # registered under its path, for worker processes to read alike
        assert PATTERNS[str(path)] is os1 and os1.n_beams == 64 and os1.n_azimuth == 2048
        assert os1.max_range == 120.0 and os1.beam_origin_offset == pytest.approx(0.015806)
        assert os1.azimuth_offsets_deg[:2] == (-3.1, -0.9)  # Ouster's azimuths turn the other way
        assert os1.time_field == "t" and os1.clockwise  # a bag carries Ouster's own per-point time
        del PATTERNS[str(path)]


@pytest.mark.parametrize(
    "text,problem",
    [
        ("columns: 10\nmax_range: 5\n", "lacks 'elevations_deg'"),
        ("elevations_deg: [0, 1]\ncolumns: ten\nmax_range: 5\n", "columns is a whole number from 1 to 8192, got .ten."),
        (
            "elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\nazimuth_offsets_deg: [1]\n",
            "1 azimuth offsets for 2 beams",
        ),
        ("elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\nimage_width: 3\n", "does not divide its 10 columns"),
        (
            "elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\nbeam_vertical_offsets: [0.01]\n",
            "1 vertical offsets for 2 beams",
        ),
        (
            "elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\nbeam_vertical_offsets: [0.01, .nan]\n",
            "beam origin offset that is not a finite number",
        ),
        ("elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 0\n", "max_range > min_range"),
        ("elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\nspin: sideways\n", "spin is 'clockwise' or"),
        ("elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\nscan_start_deg: .nan\n", "scan start of nan deg"),
        ("elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\ntime_field: stamp\n", "time_field 'stamp'; it is one of"),
        (
            "elevations_deg: [0, 1]\ncolumns: 100000000\nmax_range: 5\n",
            "columns is a whole number from 1 to 8192, got 100000000",
        ),
        (
            "elevations_deg: {from: -10, to: 10, beams: 2000000000}\ncolumns: 10\nmax_range: 5\n",
            "beams is a whole number from 1 to 512, got 2000000000",  # refused before 16 GB of angles are made
        ),
        ("elevations_deg: [0, 1]\ncolumns: 0\nmax_range: 5\n", "columns is a whole number from 1 to 8192, got 0"),
        ("elevations_deg: [0, 1]\ncolumns: 10.5\nmax_range: 5\n", "columns is a whole number from 1 to 8192, got 10.5"),
        ("elevations_deg: 5\ncolumns: 10\nmax_range: 5\n", "elevations_deg is a list of 1 to 512 angles"),
        ("elevations_deg: [0, 200]\ncolumns: 10\nmax_range: 5\n", "a beam at 200 deg elevation"),
        ("elevations_deg: [0, 1, 1]\ncolumns: 10\nmax_range: 5\n", "two beams at the same elevation"),
        (
            "elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\nazimuth_offsets_deg: [0, 400]\n",
            "has an azimuth offset beyond",
        ),
        ("elevations_deg: [0, 1]\ncolums: 10\ncolumns: 10\nmax_range: 5\n", "unknown keys ['colums']"),
        (
            "elevations_deg: [0, 1]\ncolumns: 10\nmax_range: 5\n"
            "lidar_to_sensor: [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n",
            "not a rigid 4x4 matrix",
        ),
        ("- 1\n- 2\n", "mapping of keys, not list"),
        ("elevations_deg: [0, 1\n", "not a readable YAML file"),
    ],
)
def test_a_broken_pattern_file_is_refused_naming_the_problem(tmp_path, text, problem):
    path = tmp_path / "sensor.yaml"
    path.write_text(text)
    with pytest.raises(PatternError, match=problem.replace("(", r"\(").replace("[", r"\[")):
        load_pattern(path)
    with pytest.raises(PatternError, match="cannot read"):
        load_pattern(tmp_path / "missing.yaml")


def _ouster_metadata(path, pattern: BeamPattern) -> None:
    """An Ouster metadata JSON (firmware 2.x keys) for `pattern`, with the SDK's sensor frame as
    its OS1s have it: the lidar frame turned 180 deg about z and lifted 36.18 mm."""
    path.write_text(
        json.dumps(
            {
                "beam_altitude_angles": list(pattern.elevations_deg),
                "lidar_mode": f"{pattern.n_azimuth}x10",
                "beam_azimuth_angles": [-a for a in pattern.azimuth_offsets_deg] or [0.0] * pattern.n_beams,
                "lidar_origin_to_beam_origin_mm": 1e3 * pattern.beam_origin_offset,
                "prod_line": "OS-1-64",
                "lidar_to_sensor_transform": [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1],
            }
        )
    )


def test_an_ouster_cloud_is_judged_alike_in_its_lidar_and_its_sdks_sensor_frame(tmp_path, mine, capsys):
    meta = tmp_path / "os1-meta.json"
    _ouster_metadata(meta, OUSTER_LIKE)
    pattern = load_pattern(meta)
    assert "turned +180 deg about z and shifted +36.2 mm in z" in describe_pattern(pattern)
    lidar = _scan(mine.mesh, pattern, rng=np.random.default_rng(7)).points
    to_sensor = np.asarray(pattern.lidar_to_sensor).reshape(4, 4)
    np.save(tmp_path / "lidar.npy", lidar)
    np.save(tmp_path / "sensor.npy", (lidar @ to_sensor[:3, :3].T + to_sensor[:3, 3]).astype(np.float32))
    np.save(tmp_path / "neither.npy", lidar + np.float32([0.0, 0.0, 0.3]))
    specs = ["scanmc:4", "eigen:30"]
    # each alone, so that scanmc draws the same children for each (they are seeded by the place in the list)
    sensor = LidarConfig(model=str(meta))
    as_lidar, as_sensor, neither = (
        next(judge_scans([tmp_path / f"{n}.npy"], specs, sensor=sensor)) for n in ("lidar", "sensor", "neither")
    )
    assert as_lidar.frame is None and as_sensor.frame == "read in the SDK's sensor frame, turned into the lidar frame"
    for spec in specs:
        assert as_lidar.predictions[spec].known
        np.testing.assert_array_equal(as_lidar.predictions[spec].mask, as_sensor.predictions[spec].mask)
        np.testing.assert_allclose(
            as_lidar.predictions[spec].probabilities, as_sensor.predictions[spec].probabilities, atol=1e-3
        )
    assert neither.error and "lie on" in neither.error and "sensor frame" in neither.error
    assert "turned into the lidar frame" in format_judgement(as_sensor)


def test_judge_recognises_the_sensor_or_takes_a_pattern_file_for_scanmc(tmp_path, mine, capsys):
    scan = _scan(mine.mesh, OUSTER_LIKE, rng=np.random.default_rng(2))
    np.save(tmp_path / "scan.npy", scan.points)
    seen = []
    [auto] = judge_scans([tmp_path / "scan.npy"], ["scanmc:12"], on_sensor=lambda p, how: seen.append(p.name))
    assert seen == ["fitted-64x512"] and auto.predictions["scanmc:12"].known
    # the sensor's own file gives its exact beams: the same children see the same scan mesh but for
    # the staggered azimuths and beam origins, so the scores agree closely, not exactly (12 children:
    # with 4, one child's error swung an axis by itself)
    spec = tmp_path / "ouster.yaml"
    spec.write_text(
        f"elevations_deg: {[float(e) for e in OUSTER_LIKE.elevations_deg]}\ncolumns: 512\nmax_range: 60\n"
        f"min_range: 0.3\nazimuth_offsets_deg: {[float(a) for a in OUSTER_LIKE.azimuth_offsets_deg]}\n"
        "beam_origin_offset: 0.027\n"
    )
    [given] = judge_scans(
        [tmp_path / "scan.npy"], ["scanmc:12"], LidarConfig(model=str(spec)), options=JudgeOptions(workers=2)
    )
    a, b = auto.predictions["scanmc:12"].probabilities, given.predictions["scanmc:12"].probabilities
    assert given.predictions["scanmc:12"].known and np.abs(a - b).max() < 0.15
    out = tmp_path / "j.json"
    assert main(["judge", str(tmp_path / "scan.npy"), "--detector", "scanmc:4", "--json", str(out)]) == 0
    # fitted again, or found among the patterns already fitted in this process
    assert re.search(r"sensor: (fitted to the scan: 64 beams|fitted-64x512: every return)", capsys.readouterr().out)
    assert json.loads(out.read_text())[0]["sensor"] == "fitted-64x512"
    # a cloud that is no sensor's revolution: said so, and scanmc answers unknown, not a guess
    np.save(tmp_path / "blob.npy", np.random.default_rng(3).normal(size=(4000, 3)) * 5)
    blob = ["judge", str(tmp_path / "blob.npy"), "--detector", "scanmc:4", "--detector", "eigen:30"]
    assert main(blob) == 2  # no level surface under it to find up by: said so, with the option that gives it
    assert "no ground plane could be fitted" in capsys.readouterr().err
    assert main([*blob, "--gravity", "0,0,1"]) == 0
    printed = capsys.readouterr().out
    assert "sensor: not recognised from" in printed and "not on a few beams" in printed
    assert "scanmc:4: cannot judge this scan" in printed and "eigen:30: " in printed
    with pytest.raises(SystemExit):
        main(["judge", str(tmp_path / "scan.npy"), "--detector", "scanmc:4", "--sensor", "nope.yaml"])
    assert "nope.yaml: cannot read the beam pattern file" in capsys.readouterr().err


def test_a_first_scan_cut_short_is_passed_over_for_the_next_that_gives_the_sensor(tmp_path, mine):
    """A bag's first revolution may be cut short (a sampled cloud here): the sensor is recognised
    from the next readable scan, says which, and every scan is still judged in order."""
    scan = Lidar(EmbreeCaster(mine.mesh), LidarConfig(model="os0-128")).scan(POSE, np.random.default_rng(6))
    np.save(tmp_path / "a.npy", scan.points[np.random.default_rng(7).choice(len(scan), 5000, replace=False)])
    np.save(tmp_path / "b.npy", scan.points)
    files = [tmp_path / "a.npy", tmp_path / "b.npy"]
    _, pattern, how = recognise_sensor(iter(files))
    assert pattern is PATTERNS["os0-128"] and "from " + str(files[1]) in how and "thinned or sampled" in how, how
    judged = list(judge_scans(files, ["scanmc:4"], on_sensor=lambda p, h: None))
    assert [j.path for j in judged] == [str(f) for f in files]
    assert [j.predictions["scanmc:4"].known for j in judged] == [False, True]
    _, pattern, how = recognise_sensor(iter([files[0]] * 6))
    assert pattern is None and how.startswith("not recognised from any of the first 5 readable scans"), how


def test_a_staggered_scan_is_meshed_by_the_returns_own_azimuths():
    """Beams 2.8 deg apart in azimuth at one encoder column are not joined: the mesh's triangles
    span at most a column and a diagonal of the returns' own azimuths."""
    scan = _scan(trimesh.creation.box(extents=(10.0, 6.0, 4.0)), OUSTER_LIKE, np.eye(4))
    mesh = range_image_mesh(scan.points, OUSTER_LIKE)
    assert len(mesh.faces) > len(scan) // 2
    azimuth = np.arctan2(scan.points[:, 1], scan.points[:, 0])[mesh.faces]
    across = np.abs(np.angle(np.exp(1j * (azimuth - azimuth[:, :1])))).max(axis=1)
    assert across.max() < 1.5 * 2 * np.pi / OUSTER_LIKE.n_azimuth


def test_a_recognised_sensor_is_saved_as_a_pattern_file_and_read_back(tmp_path, mine, capsys):
    """`l3e sensor SCAN --out F` writes the pattern found, to be given as --sensor F."""
    np.save(tmp_path / "scan.npy", _scan(mine.mesh, OUSTER_LIKE, rng=np.random.default_rng(4)).points)
    assert main(["sensor", str(tmp_path / "scan.npy"), "--out", str(tmp_path / "fitted.yaml")]) == 0
    assert re.search(r"64 beams over -22\.\d\d to 22\.\d\d deg", capsys.readouterr().out)
    fitted = load_pattern(tmp_path / "fitted.yaml")
    assert fitted.n_beams == 64 and fitted.n_azimuth == 512
    for suffix in ("yaml", "json"):
        back = load_pattern(save_pattern(OUSTER_LIKE, tmp_path / f"ouster.{suffix}"))
        np.testing.assert_allclose(back.elevations_deg, OUSTER_LIKE.elevations_deg, atol=1e-6)
        assert back.azimuth_offsets_deg == OUSTER_LIKE.azimuth_offsets_deg
        assert (back.n_azimuth, back.image_width, back.beam_origin_offset, back.max_range, back.min_range) == (
            512,
            256,
            0.027,
            60.0,
            0.3,
        )
        assert back.clockwise and back.scan_start_deg == 180.0  # a Velodyne's spin, from behind
        assert back.time_field == "time"
        spun = dataclasses.replace(OUSTER_LIKE, clockwise=False, scan_start_deg=90.0, time_field="t")
        again = load_pattern(save_pattern(spun, tmp_path / f"spun.{suffix}"))
        assert not again.clockwise and again.scan_start_deg == 90.0 and again.time_field == "t"
    assert main(["sensor", str(tmp_path / "ouster.yaml")]) == 0
    printed = capsys.readouterr().out
    assert "staggered in azimuth by -4.20 to 4.20 deg" in printed and "27.0 mm out from the axis" in printed
    assert "spins clockwise seen from above from 180 deg; a recorded bag's point time: time (float32" in printed
    with pytest.raises(PatternError, match="ends in"):
        save_pattern(OUSTER_LIKE, tmp_path / "ouster.txt")
    assert main(["sensor"]) == 2 and "one of them" in capsys.readouterr().err
    np.save(tmp_path / "blob.npy", np.random.default_rng(5).normal(size=(3000, 3)) * 5)
    assert main(["sensor", str(tmp_path / "blob.npy")]) == 2 and "not on a few beams" in capsys.readouterr().err


@pytest.mark.slow
def test_a_drive_recorded_with_a_pattern_file_is_judged_with_its_sensor_recognised(tmp_path, capsys):
    """`l3e record --sensor FILE` casts the staggered, offset beams and writes their rings; `l3e
    judge --bag` without --sensor recognises 64 beams and their origin offset from the ring field."""
    spec = tmp_path / "ouster.yaml"
    save_pattern(OUSTER_LIKE, spec)
    bag = tmp_path / "walls.bag"
    assert (
        main(
            [
                "record",
                "--scene",
                "primitives-1",
                "--sensor",
                str(spec),
                "--out",
                str(bag),
                "--imu-rate",
                "0",
                "--still",
                "0",
                "--max-steps",
                "301",
                "--quiet",
            ]
        )
        == 0
    )
    capsys.readouterr()
    PATTERNS.pop(str(spec))  # judged as in a process of its own, which has not read the file
    assert (
        main(
            ["judge", "--bag", str(bag), "--every", "300", "--detector", "scanmc:4", "--json", str(tmp_path / "j.json")]
        )
        == 0
    )
    printed = capsys.readouterr().out
    found = re.search(
        r"sensor: fitted to the scan: 64 beams over -22\.5 to 22\.5 deg, 512 columns, beams staggered in "
        r"azimuth by -0\.02 to 0\.02 deg, beams leaving "
        r"(\d+\.\d) mm out from the axis \(beams from the ring field\)",
        printed,
    )
    assert found and abs(float(found.group(1)) - 27.0) <= 0.5, printed[:400]
    judged = json.loads((tmp_path / "j.json").read_text())
    assert len(judged) == 2 and all(j["detectors"]["scanmc:4"]["known"] for j in judged)
