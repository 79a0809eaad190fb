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
