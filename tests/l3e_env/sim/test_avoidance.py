"""The local layer that keeps a policy steering on a wrong estimate off what the scan shows."""

from __future__ import annotations

import numpy as np
import pytest

from l3e_env.config import RobotConfig
from l3e_env.core.transforms import planar_pose
from l3e_env.sim.avoidance import FreeHeadings
from l3e_env.sim.follower import RouteFollower
from scenes.geometry import box, ground_plane, merge
from scenes.scene import Scene


def wall_across(x: float, y0: float, y1: float) -> np.ndarray:
    """Body-frame obstacles: a wall across the way at `x` from y0 to y1."""
    return np.column_stack([np.full(200, x), np.linspace(y0, y1, 200)])


def test_free_distance_is_measured_from_the_nose_in_a_corridor_as_wide_as_the_base():
    free = FreeHeadings(half_width=0.4, front=0.45)
    wall = wall_across(2.0, -1.0, 1.0)
    d = free.free_distance(wall, np.radians([0.0, 30.0, 90.0, 180.0]))
    assert d[0] == pytest.approx(1.55, abs=0.02)
    # at 30 degrees the corridor's right edge meets the wall first: at y = (2 sin 30 - 0.4) / cos 30
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    assert d[1] == pytest.approx(2.0 * c + (2.0 * s - 0.4) / c * s - 0.45, abs=0.02)
    assert np.isinf(d[2]) and np.isinf(d[3])  # beside and behind: nothing
    assert np.isinf(free.free_distance(np.zeros((0, 2)), np.zeros(3))).all()
    # a post just outside the corridor's half width leaves the way free, one inside it does not
    assert np.isinf(free.free_distance(np.array([[1.0, 0.41]]), np.zeros(1)))[0]
    assert free.free_distance(np.array([[1.0, 0.39]]), np.zeros(1))[0] == pytest.approx(0.55)


def test_steer_keeps_a_free_heading_and_takes_the_nearest_free_one_towards_its_own_heading():
    free = FreeHeadings()
    assert free.steer(np.zeros((0, 2)), 0.7) == pytest.approx(0.7)
    # a block to the right and ahead-right: wanting to turn right (-90 deg) into it, the robot goes on
    # along it (the free side nearer its own heading), not back
    block = np.vstack([wall_across(1.0, -6.0, -0.5), np.column_stack([np.linspace(-3, 1.0, 100), np.full(100, -0.6)])])
    heading = free.steer(block, np.radians(-90))
    assert -np.radians(60) < heading <= np.radians(10)
    assert free.free_distance(block, np.array([heading]))[0] >= free.look
    # boxed in: the heading asked for comes back (the recovery's turn)
    around = np.column_stack([np.cos(np.linspace(-np.pi, np.pi, 400)), np.sin(np.linspace(-np.pi, np.pi, 400))])
    assert free.steer(around, 0.3) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="half_width > 0"):
        FreeHeadings(half_width=0.0)


def test_guard_turns_a_blocked_walk_forward_and_leaves_a_free_one():
    free = FreeHeadings()
    action = np.array([1.0, 0.0, 0.0], dtype=np.float32)
    np.testing.assert_allclose(free.guard(action, wall_across(5.0, -1, 1)), action)
    turned = free.guard(action, wall_across(1.2, -3.0, 0.5))  # open to the left only
    assert turned[2] > 0.5 and 0 <= turned[0] < 1.0
    backwards = np.array([-0.5, 0.0, 0.1], dtype=np.float32)  # only the walk forward is guarded
    np.testing.assert_allclose(free.guard(backwards, wall_across(1.2, -3.0, 0.5)), backwards)


def test_obstacles_are_the_returns_at_the_bases_height():
    robot = RobotConfig()
    T_b_s = planar_pose(*robot.lidar_offset, 0.0)
    sensor_z = robot.lidar_offset[2]
    points = np.array(
        [
            [2.0, 0.0, -robot.standing_height - sensor_z],  # the floor
            [2.0, 0.5, -robot.standing_height - sensor_z + 0.1],  # a pebble
            [2.0, 1.0, -sensor_z],  # at the base's centre height
            [3.0, 0.0, 2.0],
        ]
    )  # a roof
    np.testing.assert_allclose(FreeHeadings.obstacles(points, T_b_s, robot), [[2.0, 1.0]])


def corner_scene() -> Scene:
    """A route along x that turns right round the far end of a block, as the bypass's detour turns."""
    mesh = merge([ground_plane(-5, 20, -12, 6), box((6.0, -5.0, 1.0), (8.0, 8.0, 2.0))])  # x 2..10, y -9..-1
    route = np.array([[0.0, 0.0, 0.0], [12.0, 0.0, 0.0], [12.0, -8.0, 0.0]])
    return Scene("corner", mesh, [route], (0, 0, 0), (12.0, -8.0), {"main": route})


@pytest.mark.parametrize("avoid", [False, True])
@pytest.mark.slow
def test_a_follower_whose_estimate_runs_ahead_walks_round_the_block_only_with_the_local_layer(avoid):
    from l3e_env.envs import NavigationEnv

    env = NavigationEnv(scene_object=corner_scene(), scene="corner")
    try:
        env.reset(seed=0)
        ahead = np.eye(4)
        ahead[0, 3] = 3.5  # the estimate 3.5 m ahead: the robot turns where the block still is
        follow = RouteFollower(env.scene.route, avoid=FreeHeadings() if avoid else None)
        blocked, lowest = 0, 0.0
        for _ in range(400):
            obstacles = FreeHeadings.obstacles(env.scan.points, env.robot.T_b_s, env.config.robot)
            _, _, terminated, _, info = env.step(follow(ahead @ info_pose(env), obstacles))
            blocked += info["blocked"]
            lowest = min(lowest, float(info["T_w_b"][1, 3]))
            if terminated:
                break
        if avoid:
            assert lowest < -4.0 and blocked < 20  # round the block's end and down its side
        else:
            assert lowest > -1.0 and blocked > 100  # pushed against the block's top
    finally:
        env.close()


def info_pose(env) -> np.ndarray:
    return env.robot.T_w_b
