import numpy as np
import pytest
import trimesh

from l3e_env.config import OdometryConfig
from l3e_env.core.transforms import inverse, matrix_to_pose, planar_pose, pose_to_matrix
from l3e_env.sim.odometry import DeadReckoningCovariance, LegOdometry
from l3e_env.sim.robot import Robot, SpawnError
from l3e_env.sim.world import World
from scenes import Scene
from scenes.geometry import box, ground_plane, merge


def ramp_scene(slope_deg=10.0):
    plane = ground_plane(-20, 20, -5, 5, cell=2.0)
    v = plane.vertices.copy()
    v[:, 2] = np.tan(np.radians(slope_deg)) * v[:, 0]
    mesh = merge([trimesh.Trimesh(v, plane.faces, process=False), box((10, 0, 0), (0.3, 10, 10))])
    return Scene("ramp", mesh, [np.array([[-5.0, 0, 0], [5.0, 0, 0]])], (0, 0, 0), (5, 0))


def test_robot_follows_a_slope_and_stops_at_a_wall():
    world = World(ramp_scene(10.0))
    robot = Robot(world)
    T = robot.reset(-5.0, 0.0, 0.0, z_ground=np.tan(np.radians(10)) * -5)
    rpy = matrix_to_pose(T)[3:]
    assert abs(rpy[1] + np.radians(10)) < 1e-6  # nose up = negative pitch about y
    assert abs(rpy[0]) < 1e-9
    # base centre stands 0.55 m above the ramp along its normal
    foot = T[:3, 3] - T[:3, 2] * 0.55
    assert abs(foot[2] - np.tan(np.radians(10)) * foot[0]) < 1e-6
    blocked_any = False
    for _ in range(200):
        T, blocked = robot.step(np.array([1.0, 0.0, 0.0]))
        blocked_any |= blocked
    assert blocked_any
    assert 9.0 < T[0, 3] + 0.45 < 9.9  # nose against the wall at x = 9.85, not through it
    assert not world.in_collision(T)
    world.close()


def test_spawn_inside_geometry_or_off_the_map_is_refused():
    world = World(ramp_scene(0.0))
    robot = Robot(world)
    with pytest.raises(SpawnError, match="inside scene geometry; is the route's first waypoint on a floor.*--up-axis"):
        robot.reset(10.0, 0.0, 0.0)
    with pytest.raises(SpawnError, match="no ground"):
        robot.reset(50.0, 0.0, 0.0)
    robot.reset(0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        robot.step(np.array([np.nan, 0.0, 0.0]))


def test_sliding_along_a_wall_keeps_the_free_axis():
    world = World(ramp_scene(0.0))
    robot = Robot(world)
    robot.reset(9.35, 0.0, 0.0)
    T0 = robot.T_w_b
    T, blocked = robot.step(np.array([0.7, 0.3, 0.0]))
    assert blocked and T[1, 3] > T0[1, 3] + 0.02


@pytest.mark.slow
def test_leg_odometry_is_exact_at_rest_and_drifts_in_motion():
    odo = LegOdometry(OdometryConfig(), np.random.default_rng(1))
    T = planar_pose(1.0, 2.0, 0.5, 0.3)
    np.testing.assert_allclose(odo.measure(T, T), np.eye(4), atol=1e-12)
    # dead reckoning over a 100 m straight walk: error of the order of percent of distance
    errs = []
    for seed in range(20):
        odo = LegOdometry(OdometryConfig(), np.random.default_rng(seed))
        est, true = np.eye(4), np.eye(4)
        for _ in range(1000):
            nxt = true @ planar_pose(0.1, 0.0, 0.0, 0.0)
            est = est @ odo.measure(true, nxt)
            true = nxt
        errs.append(np.linalg.norm(est[:3, 3] - true[:3, 3]))
    assert 0.3 < np.median(errs) < 10.0
    step = pose_to_matrix([0.1, 0, 0, 0, 0, 0.05])
    a = LegOdometry(OdometryConfig(), np.random.default_rng(7)).measure(np.eye(4), step)
    b = LegOdometry(OdometryConfig(), np.random.default_rng(7)).measure(np.eye(4), step)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, pose_to_matrix([0.1, 0, 0, 0, 0, 0.05]))


@pytest.mark.slow
def test_dead_reckoning_covariance_matches_the_spread_of_simulated_walks():
    """20 m along an arc: the propagated covariance (scale and biases carried along) gives each
    axis's spread over 200 simulated walks within 20 %."""
    step = planar_pose(0.1, 0.0, 0.0, 0.01)
    covariance, truth = DeadReckoningCovariance(), np.eye(4)
    for _ in range(200):
        truth = truth @ step
        P, twist = covariance.step(step, truth, 0.1)
    ends = []
    for run in range(200):
        odometry, T_odom, T_true = LegOdometry(rng=np.random.default_rng(run)), np.eye(4), np.eye(4)
        for _ in range(200):
            T_odom, T_true = T_odom @ odometry.measure(T_true, T_true @ step), T_true @ step
        # the error as the covariance states it: position in the odometry frame, rotation about its axes
        rotation = T_odom[:3, :3] @ T_true[:3, :3].T
        ends.append(
            np.r_[
                T_odom[:3, 3] - T_true[:3, 3],
                matrix_to_pose(np.block([[rotation, np.zeros((3, 1))], [np.zeros((1, 3)), 1.0]]))[3:],
            ]
        )
    spread = np.std(ends, axis=0)
    np.testing.assert_allclose(np.sqrt(np.diag(P)), spread, rtol=0.2)
    assert np.allclose(P, P.T) and np.linalg.eigvalsh(P).min() > 0
    assert twist.shape == (6, 6) and (np.diag(twist) > 0).all()


def test_transforms_round_trip():
    v = np.array([1.0, -2.0, 0.5, 0.1, -0.2, 2.5])
    T = pose_to_matrix(v)
    np.testing.assert_allclose(matrix_to_pose(T), v, atol=1e-12)
    np.testing.assert_allclose(T @ inverse(T), np.eye(4), atol=1e-12)


def test_a_mesh_in_pieces_holds_the_robot_as_one_shape_does(monkeypatch):
    """Split into shapes of 7 triangles, the ramp stands the robot at the same pose and its wall still
    stops it: a mesh too large for one PyBullet shape drives as a small one does."""
    import l3e_env.sim.raycast as raycast

    whole = World(ramp_scene(10.0))
    monkeypatch.setattr(raycast, "MAX_SHAPE_TRIANGLES", 7)
    pieces = World(ramp_scene(10.0))
    assert len(whole.scene_bodies) == 1 and len(pieces.scene_bodies) >= 10
    robots = [Robot(w) for w in (whole, pieces)]
    poses = [r.reset(-5.0, 0.0, 0.0, z_ground=np.tan(np.radians(10)) * -5) for r in robots]
    for _ in range(200):
        poses = [r.step(np.array([1.0, 0.0, 0.0]))[0] for r in robots]
    np.testing.assert_allclose(poses[0], poses[1], atol=1e-9)
    assert 9.0 < poses[1][0, 3] + 0.45 < 9.9  # stopped by the wall, in its own piece
    whole.close()
    pieces.close()


def _grid(cells: tuple[int, int], origin, u, v) -> trimesh.Trimesh:
    """A flat rectangle from `origin` along u and v, cut into cells[0] x cells[1] squares of 2 triangles."""
    i, j = np.meshgrid(np.arange(cells[0] + 1), np.arange(cells[1] + 1), indexing="ij")
    vertices = np.asarray(origin) + i.reshape(-1, 1) / cells[0] * np.asarray(u) + j.reshape(-1, 1) / cells[1] * v
    k = (i[:-1, :-1] * (cells[1] + 1) + j[:-1, :-1]).ravel()
    faces = np.r_[np.c_[k, k + cells[1] + 1, k + 1], np.c_[k + 1, k + cells[1] + 1, k + cells[1] + 2]]
    return trimesh.Trimesh(vertices, faces, process=False)


@pytest.mark.slow
def test_a_mesh_of_two_million_triangles_is_driven():
    """A corridor of 2 million triangles (a surveyed tunnel's size; PyBullet takes ~175 000 a shape):
    the robot stands on its floor, walks it and is stopped by its end wall."""
    floor = _grid((1000, 500), (-1.0, -2.5, 0.0), (12.0, 0, 0), (0, 5.0, 0))
    walls = [_grid((1000, 250), (-1.0, y, 0.0), (12.0, 0, 0), (0, 0, 3.0)) for y in (-2.0, 2.0)]
    end = _grid((10, 10), (9.0, -2.5, 0.0), (0, 5.0, 0), (0, 0, 3.0))
    mesh = merge([floor, *walls, end])
    assert len(mesh.faces) >= 2_000_000
    world = World(Scene("survey", mesh, [np.array([[0.0, 0, 0], [8.0, 0, 0]])], (0, 0, 0), (8, 0)))
    robot = Robot(world)
    T = robot.reset(0.0, 0.0, 0.0, z_ground=0.0)
    assert abs(T[2, 3] - 0.55) < 1e-6  # standing on the floor
    for _ in range(120):
        T, blocked = robot.step(np.array([1.0, 0.0, 0.0]))
    assert blocked and 8.0 < T[0, 3] + 0.45 < 9.0  # at the end wall, not through it
    side = T.copy()
    side[1, 3] = 1.95
    assert world.in_collision(side) and not world.in_collision(T)
    world.close()
