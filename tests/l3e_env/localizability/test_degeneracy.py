"""X-ICP's and DRPM's degeneracy tests on scans whose degeneracy the geometry gives."""

from __future__ import annotations

import numpy as np
import pytest

from l3e_env.config import LidarConfig
from l3e_env.config.detector_spec import parse_detector
from l3e_env.core.transforms import pose_to_matrix
from l3e_env.detection.detectors import DRPMDetector, XICPDetector, make_detector
from l3e_env.localizability.degeneracy import (
    PlaneRows,
    drpm_mask,
    drpm_probabilities,
    scan_rows,
    xicp_localizability,
    xicp_mask,
)
from l3e_env.localizability.registration import scan_hessian
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def _scan(name: str, pose: list[float]) -> np.ndarray:
    scene = make_scene(name)
    lidar = Lidar(EmbreeCaster(scene.mesh, threads=1), LidarConfig())
    return lidar.scan(pose_to_matrix(np.array(pose)), np.random.default_rng(0)).points


PRIMITIVES = [
    ("primitives-0", [0, 0, 0.85, 0, 0, 0], [1, 1, 0, 0, 0, 1]),  # an open plane: x, y, yaw slide
    ("primitives-1", [0, 0, 0.85, 0, 0, 0], [1, 0, 0, 0, 0, 0]),  # two parallel walls: the axis along them
    ("primitives-2", [0, 0, 0.85, 0, 0, 0.3], [0, 0, 0, 0, 0, 0]),  # a closed room
    ("primitives-3", [0, 0, 0.85, 0, 0, 0], [0, 0, 0, 0, 0, 1]),  # a round room: yaw
]


@pytest.mark.parametrize("name, pose, free", PRIMITIVES)
def test_both_tests_flag_the_axes_the_primitives_leave_free(name, pose, free):
    rows = scan_rows(_scan(name, pose))
    assert drpm_mask(rows)[1].astype(int).tolist() == free
    # the published 300 counts correspondences of full-resolution scans; this registration thins a scan
    # to 1000 points, where a third of that separates the primitives' free axes from the held ones
    assert xicp_mask(rows, 100.0)[1].astype(int).tolist() == free
    for scores, mask in (drpm_mask(rows), xicp_mask(rows, 100.0)):
        assert ((scores > 0.5) == mask).all() and ((scores >= 0) & (scores <= 1)).all()


def test_the_rows_are_the_scans_own_hessian_and_a_quarter_turn_swaps_x_and_y():
    scan = _scan("primitives-1", [0, 0, 0.85, 0, 0, 0])
    rows = scan_rows(scan)
    J = rows.jacobian
    assert np.allclose(J.T @ J, scan_hessian(scan), rtol=1e-9, atol=1e-9)
    assert np.allclose(np.linalg.norm(rows.normals, axis=1), 1.0)
    assert np.allclose(np.einsum("nij,nj->ni", rows.normal_spread, rows.normals), 0.0, atol=1e-9)  # no spread along n
    turn = pose_to_matrix(np.array([0, 0, 0, 0, 0, np.pi / 2]))[:3, :3]  # the sensor turned: the walls run along y
    turned = scan_rows(scan @ turn.T)
    swap = [1, 0, 2, 4, 3, 5]
    assert xicp_mask(turned, 100.0)[1].tolist() == xicp_mask(rows, 100.0)[1][swap].tolist()
    assert drpm_mask(turned)[1].tolist() == drpm_mask(rows)[1][swap].tolist()
    assert np.allclose(xicp_localizability(turned), xicp_localizability(rows)[swap], rtol=0.05, atol=2.0)


def test_drpm_flags_more_as_the_noise_grows_and_xicp_as_its_threshold_does():
    rows = scan_rows(_scan("office-0", [5, 0, 0.85, 0, 0, 0.3]))
    quiet, noisy = drpm_probabilities(rows, 10.0, 0.01)[0], drpm_probabilities(rows, 10.0, 1.0)[0]
    assert (quiet >= noisy - 1e-12).all() and noisy.min() < 0.5 < quiet.min()
    flagged = [int(xicp_mask(rows, enough)[1].sum()) for enough in (10, 100, 300, 1000, 10_000)]
    assert flagged == sorted(flagged) and flagged[0] == 0 and flagged[-1] == 6


def test_bad_thresholds_and_too_few_rows_are_refused_and_a_tiny_scan_is_unknown():
    rows = scan_rows(_scan("primitives-2", [0, 0, 0.85, 0, 0, 0.3]))
    with pytest.raises(ValueError, match="positive"):
        xicp_mask(rows, 0.0)
    with pytest.raises(ValueError, match="positive signal-to-noise factor"):
        drpm_mask(rows, snr=-1.0)
    few = PlaneRows(rows.points[:3], rows.normals[:3], rows.normal_spread[:3])
    with pytest.raises(ValueError, match="at least 6 correspondences"):
        drpm_mask(few)
    for detector in (XICPDetector(300.0), DRPMDetector(10.0)):
        assert not detector.predict(np.zeros((20, 3))).known
        assert detector.predict(_scan("primitives-2", [0, 0, 0.85, 0, 0, 0.3])).known


@pytest.mark.parametrize(
    "spec, value", [("xicp", 300.0), ("xicp:120", 120.0), ("drpm", 10.0), ("drpm:5", 5.0), ("eigen:30", 30.0)]
)
def test_specs_name_the_published_defaults_and_make_the_detectors(spec, value):
    assert parse_detector(spec).tau == value
    assert make_detector(spec).name.endswith(f":{value:g}")


@pytest.mark.parametrize(
    "spec, message",
    [
        ("xicp:-1", "must be positive"),
        ("drpm:inf", "must be positive"),
        ("drpm:many", "drpm:<s>"),
        ("dcreg:1", "must exceed 1"),
        ("eigen:", "eigen:<tau>"),
    ],
)
def test_bad_specs_name_the_form(spec, message):
    with pytest.raises(ValueError, match=message):
        parse_detector(spec)
