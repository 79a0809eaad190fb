import dataclasses

import numpy as np
import pytest
import trimesh

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import pose_to_matrix
from l3e_env.sim.lidar import BeamPattern, Lidar, get_pattern, register_pattern
from l3e_env.sim.raycast import PYBULLET_MAX_RAYS, EmbreeCaster, PyBulletCaster
from scenes import make_scene


def exact(model="vlp16"):
    return LidarConfig(model=model, range_noise_std=0.0)


@pytest.mark.parametrize(
    "scene_name,pose",
    [
        ("mine", (-30.0, 0.5, 0.85, 0.0, 0.0, 0.3)),
        ("mine", (40.0, 0.3, 0.85, 0.05, -0.03, 0.1)),
        ("office", (5.0, 0.0, 0.85, 0.0, 0.1, 1.0)),
    ],
)
def test_embree_and_pybullet_agree_to_a_tenth_of_a_millimetre(scene_name, pose):
    scene = make_scene(scene_name)
    T = pose_to_matrix(np.array(pose))
    for model in ("vlp16", "os0-128"):
        a = Lidar(EmbreeCaster(scene.mesh), exact(model)).scan(T)
        b = Lidar(PyBulletCaster.for_mesh(scene.mesh), exact(model)).scan(T)
        assert len(a.points) > 1000
        # the same rays hit; ranges agree
        key_a, key_b = a.beam.astype(np.int64) * 10000 + a.column, b.beam.astype(np.int64) * 10000 + b.column
        common, ia, ib = np.intersect1d(key_a, key_b, return_indices=True)
        assert len(common) >= 0.999 * max(len(a), len(b))
        diff = np.abs(a.points[ia] - b.points[ib]).max(axis=1)
        # rays that graze a shared triangle edge may slip through one engine's edge rule
        assert (diff < 1e-4).mean() >= 0.999, f"{(diff >= 1e-4).sum()} of {len(diff)} points differ"


def test_pybullet_backend_chunks_more_rays_than_one_call_allows(office):
    caster = PyBulletCaster.for_mesh(office.mesh)
    n = 2 * PYBULLET_MAX_RAYS + 17
    dirs = np.tile(np.array([[1.0, 0.0, 0.0]], dtype=np.float32), (n, 1))
    d = caster.cast(np.array([5.0, 0.0, 1.0]), dirs, 50.0)
    assert d.shape == (n,) and np.isfinite(d).all()
    assert np.ptp(d) < 1e-5


def test_ranges_match_geometry_in_a_box_room():
    room = trimesh.creation.box(extents=(10.0, 6.0, 4.0))
    lidar = Lidar(EmbreeCaster(room), exact())
    scan = lidar.scan(np.eye(4))
    assert scan.points.dtype == np.float32 and scan.points.shape[1] == 3
    horizontal = scan.points[np.abs(scan.points[:, 2]) < 1e-6]
    assert len(horizontal) == 0  # VLP-16 has no 0-degree beam
    ring = scan.beam == 7  # -1 degree
    forward = scan.points[ring & (scan.column == 0)][0]
    np.testing.assert_allclose(forward[0], 5.0, atol=1e-4)
    left = scan.points[ring & (scan.column == 450)][0]
    np.testing.assert_allclose(left[1], 3.0, atol=1e-4)
    # every point lies on the box surface
    p = np.abs(scan.points.astype(np.float64))
    on_face = np.isclose(p[:, 0], 5, atol=1e-3) | np.isclose(p[:, 1], 3, atol=1e-3) | np.isclose(p[:, 2], 2, atol=1e-3)
    assert on_face.all()


def test_a_miss_is_no_point(rng):
    plane = make_scene("primitives-0")  # a plane: upward beams never return
    scan = Lidar(EmbreeCaster(plane.mesh), LidarConfig()).scan(pose_to_matrix([0, 0, 0.85, 0, 0, 0]), rng)
    assert 0 < len(scan) <= 8 * 1800
    assert (scan.points[:, 2] < 0).all()
    assert np.linalg.norm(scan.points, axis=1).max() < 100.0


def test_noise_dropout_and_determinism(office):
    T = pose_to_matrix([5.0, 0.0, 0.85, 0, 0, 0])
    exact_scan = Lidar(EmbreeCaster(office.mesh), exact()).scan(T)
    lidar = Lidar(EmbreeCaster(office.mesh), LidarConfig(range_noise_std=0.03, dropout=0.2))
    s1, s2 = lidar.scan(T, np.random.default_rng(5)), lidar.scan(T, np.random.default_rng(5))
    np.testing.assert_array_equal(s1.points, s2.points)
    assert 0.75 < len(s1) / len(exact_scan) < 0.85
    key = lambda s: s.beam.astype(np.int64) * 10000 + s.column  # noqa: E731
    _, ia, ib = np.intersect1d(key(exact_scan), key(s1), return_indices=True)
    err = np.linalg.norm(s1.points[ib], axis=1) - np.linalg.norm(exact_scan.points[ia], axis=1)
    assert abs(err.std() - 0.03) < 0.003 and abs(err.mean()) < 0.002


def test_range_image_pools_nearest_return(office):
    scan = Lidar(EmbreeCaster(office.mesh), exact()).scan(pose_to_matrix([5.0, 0.0, 0.85, 0, 0, 0]))
    img = scan.range_image(360)
    assert img.shape == (16, 360)
    full = scan.range_image(1800)
    nearest = np.where(full > 0, full, np.inf).reshape(16, 360, 5).min(-1).clip(max=1e9)
    np.testing.assert_allclose(img, nearest * (img > 0))
    with pytest.raises(ValueError, match="must divide"):
        scan.range_image(7)


def test_user_defined_pattern_and_bad_inputs(office):
    register_pattern(BeamPattern("fan8", tuple(np.linspace(-5, 5, 8)), 360, 30.0, 0.2, 90))
    scan = Lidar(EmbreeCaster(office.mesh), LidarConfig(model="fan8")).scan(pose_to_matrix([5, 0, 0.85, 0, 0, 0]))
    assert scan.beam.max() < 8 and np.linalg.norm(scan.points, axis=1).max() < 30.0
    with pytest.raises(ValueError, match="unknown LiDAR model"):
        get_pattern("hdl-64")
    with pytest.raises(ValueError, match="finite 4x4"):
        Lidar(EmbreeCaster(office.mesh)).scan(np.full((4, 4), np.nan))


def _deskewed(scan, start: np.ndarray, end: np.ndarray, period: float) -> np.ndarray:
    """Each point of a swept scan in the world frame, by the pose at its own time."""
    from scipy.spatial.transform import Rotation

    share = scan.times.astype(np.float64) / period
    turn = Rotation.from_matrix(start[:3, :3].T @ end[:3, :3]).as_rotvec()
    at = Rotation.from_matrix(start[:3, :3]) * Rotation.from_rotvec(share[:, None] * turn)
    return at.apply(scan.points.astype(np.float64)) + start[:3, 3] + share[:, None] * (end[:3, 3] - start[:3, 3])


def _off_the_box(world: np.ndarray) -> np.ndarray:
    """How far each point of the 10 x 6 x 4 m room lies from its nearest wall, floor or ceiling."""
    return np.abs(np.abs(world) - [5.0, 3.0, 2.0]).min(axis=1)


def test_a_revolution_at_rest_fires_clockwise_from_behind():
    room = trimesh.creation.box(extents=(10.0, 6.0, 4.0))
    lidar = Lidar(EmbreeCaster(room), exact())
    still = lidar.scan(np.eye(4), start=np.eye(4), period=0.1)
    np.testing.assert_array_equal(still.points, lidar.scan(np.eye(4)).points)  # at rest, nothing moves
    assert lidar.scan(np.eye(4)).times is None and still.times.dtype == np.float32
    assert still.times.min() >= 0.0 and still.times.max() < 0.1
    ring = still.beam == 7
    # from behind (180 deg) through the left (90), the front (0) and the right (-90 deg: column 1350)
    for column, share in ((900, 0.0), (450, 0.25), (0, 0.5), (1350, 0.75)):
        assert still.times[ring & (still.column == column)][0] == pytest.approx(0.1 * share, abs=1e-6)


@pytest.mark.parametrize("model", ["vlp16", "os0-128", "os-staggered"])
def test_a_swept_revolution_lies_on_the_walls_once_each_point_is_put_where_it_was_taken(model):
    """Walking 0.1 m and turning 0.1 rad over the revolution: each point is in the sensor frame of
    its own firing time, so the poses at the points' times put every one on the room's surfaces,
    while the pose at the revolution's end puts some of them centimetres off. `os-staggered`: an
    OS0-128 whose beams fire 27 mm out from the axis, staggered in azimuth."""
    if model == "os-staggered":
        register_pattern(
            dataclasses.replace(
                get_pattern("os0-128"),
                name=model,
                beam_origin_offset=0.027,
                azimuth_offsets_deg=tuple(np.tile([-4.2, -1.4, 1.4, 4.2], 32)),
            )
        )
    room = trimesh.creation.box(extents=(10.0, 6.0, 4.0))
    lidar = Lidar(EmbreeCaster(room), exact(model))
    start = pose_to_matrix([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    end = pose_to_matrix([0.1, 0.02, 0.0, 0.0, 0.02, 0.1])
    swept = lidar.scan(end, start=start, period=0.1)
    assert len(swept) > 20000
    assert _off_the_box(_deskewed(swept, start, end, 0.1)).max() < 2e-3
    at_end = swept.points.astype(np.float64) @ end[:3, :3].T + end[:3, 3]
    assert _off_the_box(at_end).max() > 0.2  # a 0.1 rad turn moves a point on a wall 4 m away by 0.4 m
    with pytest.raises(ValueError, match="positive time"):
        lidar.scan(end, start=start, period=0.0)


@pytest.mark.parametrize("clockwise,start_deg", [(True, 180.0), (False, 90.0)])
def test_a_swept_revolution_deskewed_with_its_motion_lies_on_the_walls_seen_from_its_end(clockwise, start_deg):
    """deskew puts every point into the sensor frame at the revolution's end, from its own
    azimuth and the sensor's motion over the revolution, as LiDAR odometry does; the pattern says
    which way the sensor spins and where a revolution begins."""
    from l3e_env.sim.lidar import deskew

    pattern = dataclasses.replace(
        get_pattern("vlp16"), name=f"vlp16-{clockwise}-{start_deg}", clockwise=clockwise, scan_start_deg=start_deg
    )
    register_pattern(pattern)
    room = trimesh.creation.box(extents=(10.0, 6.0, 4.0))
    lidar = Lidar(EmbreeCaster(room), exact(pattern.name))
    start, end = pose_to_matrix([0.0, 0.0, 0.0, 0.0, 0.0, 0.0]), pose_to_matrix([0.1, 0.02, 0.0, 0.0, 0.02, 0.1])
    swept = lidar.scan(end, start=start, period=0.1)
    np.testing.assert_allclose(pattern.firing_share(swept.points) * 0.1, swept.times, atol=1e-6)
    ring = swept.beam == 7  # column 450 looks left (90 deg), column 0 ahead
    left, ahead = (swept.times[ring & (swept.column == c)][0] for c in (450, 0))
    assert (left, ahead) == (
        (pytest.approx(0.025), pytest.approx(0.05))
        if clockwise
        else (pytest.approx(0.0, abs=1e-6), pytest.approx(0.075))
    )
    straight = deskew(swept.points, np.linalg.inv(start) @ end, pattern)
    assert straight.dtype == np.float32
    assert _off_the_box(straight.astype(np.float64) @ end[:3, :3].T + end[:3, 3]).max() < 2e-3
    np.testing.assert_allclose(deskew(swept.points, np.eye(4), pattern), swept.points, atol=1e-6)  # at rest


def test_the_deskewing_motion_is_the_mean_of_the_odometry_s_last_steps():
    """Rotations averaged on SO(3), translations arithmetically, over the last DESKEW_STEPS only;
    a gyro's rotation replaces the odometry's."""
    from l3e_env.core.transforms import matrix_to_pose, pose_to_matrix
    from l3e_env.sim.lidar import DESKEW_STEPS, deskew_motion

    assert DESKEW_STEPS == 2
    np.testing.assert_array_equal(deskew_motion([]), np.eye(4))
    steps = [
        pose_to_matrix([5.0, 0, 0, 0, 0, 1.0]),
        pose_to_matrix([0.10, 0.02, 0, 0, 0, 0.1]),
        pose_to_matrix([0.14, 0.0, 0.01, 0, 0.02, 0.3]),
    ]
    mean = matrix_to_pose(deskew_motion(steps))  # the first step is too old to count
    np.testing.assert_allclose(mean, [0.12, 0.01, 0.005, 0.0, 0.01, 0.2], atol=1e-3)
    np.testing.assert_allclose(deskew_motion(steps[1:2]), steps[1], atol=1e-12)
    gyro = pose_to_matrix([0, 0, 0, 0.01, 0.0, 0.25])[:3, :3]
    inertial = matrix_to_pose(deskew_motion(steps, gyro))  # the gyro's turn, the odometry's translation
    np.testing.assert_allclose(inertial, [0.12, 0.01, 0.005, 0.01, 0.0, 0.25], atol=1e-3)
    np.testing.assert_allclose(deskew_motion([], gyro)[:3, :3], gyro)
    mounting = pose_to_matrix([0.1, 0.0, 0.3, 0, 0, 0.2])  # the sensor's motion: the body's, carried through it
    np.testing.assert_allclose(
        deskew_motion(steps, gyro, mounting=mounting),
        np.linalg.inv(mounting) @ deskew_motion(steps, gyro) @ mounting,
        atol=1e-12,
    )
