"""The ground under the robot as a landmark of the graph (fusion.ground)."""

import gtsam
import numpy as np
import pytest

from fusion import FusionConfig, FusionGraph, plane_in_frame
from fusion.ground import PATCH_STEP, GroundPatches, check_plane, to_gtsam

HEIGHT = 0.55  # the body's height above its ground
ODOMETRY_SIGMAS = np.array([0.02, 0.02, 0.02, 0.002, 0.002, 0.01])
ICP_SIGMAS = (0.002, 0.002, 0.001, 0.0002, 0.0002, 0.0005)  # sure of its height, as on a floor


def step(x=0.1, z=0.0):
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def level_ground(height=HEIGHT):
    """The ground plane (n, d; n . p = d) under a level body `height` above it, in the body frame."""
    return np.array([0.0, 0.0, 1.0, -height])


def walk(steps, icp_z, ground_every, ground_z=None, legs_z=None, lag=None):
    """A walk along x on level ground (at height 0 until `ground_z(k)` says otherwise), the
    registration's height step `icp_z(k)`, the legs' `legs_z(k)` (the truth where None), and the
    ground plane seen every `ground_every` steps (0: never). Returns the true and fused heights."""
    config = FusionConfig(icp_covariance="fixed", icp_sigmas=ICP_SIGMAS, smoother_lag=lag)
    graph = FusionGraph(step(0.0, HEIGHT), config)
    ground = ground_z or (lambda k: 0.0)
    true_z, fused_z = [HEIGHT], [HEIGHT]
    for k in range(1, steps + 1):
        rise = ground(k) - ground(k - 1)
        legs = rise if legs_z is None else legs_z(k)
        T, _ = graph.add_step(step(0.1, legs), ODOMETRY_SIGMAS, step(0.1, icp_z(k)), np.zeros(6, bool))
        if ground_every and k % ground_every == 0:
            T = graph.add_ground(level_ground())  # the body stands HEIGHT above the ground under it
        true_z.append(ground(k) + HEIGHT)
        fused_z.append(T[2, 3])
    return np.array(true_z), np.array(fused_z), graph


def test_the_ground_holds_the_height_that_a_registrations_small_bias_loses():
    biased = lambda k: -0.0005  # noqa: E731  0.5 mm down a step, inside what the registration claims
    true_z, without, _ = walk(400, biased, ground_every=0)
    assert without[-1] - true_z[-1] < -0.15  # the bias adds up over the walk
    true_z, held, graph = walk(400, biased, ground_every=40)
    # held where the ground is seen; what is left tilts the patch, which only the first pose holds here
    assert abs(held[-1] - true_z[-1]) < 0.2 * abs(without[-1] - true_z[-1])
    assert graph.ground.index == 0  # one patch of level ground, however far


def test_a_slip_of_the_registration_is_not_a_step_of_the_ground():
    slip = lambda k: 0.2 if k == 55 else 0.0  # noqa: E731  one registration jumps 0.2 m up
    true_z, fused, graph = walk(200, slip, ground_every=20)
    assert graph.ground.index == 0  # the legs saw no step: the same patch
    assert abs(fused[-1] - true_z[-1]) < 0.02


def test_a_step_up_the_legs_walk_starts_a_new_patch_and_is_kept():
    ground = lambda k: 0.3 if k >= 55 else 0.0  # noqa: E731  a 0.3 m step up the stairs
    icp = lambda k: 0.3 if k == 55 else 0.0  # noqa: E731
    true_z, fused, graph = walk(200, icp, ground_every=20, ground_z=ground)
    assert graph.ground.index == 1
    assert abs(fused[-1] - true_z[-1]) < 0.02  # not pulled back down to the first patch


def test_a_patch_unseen_for_half_the_window_is_left_for_a_new_one():
    _, fused, graph = walk(300, lambda k: 0.0, ground_every=120, lag=100)
    assert graph.ground.index == 1  # seen at 120, and at 240: more than 50 steps after
    assert np.isfinite(fused).all()
    _, _, graph = walk(300, lambda k: 0.0, ground_every=40, lag=100)
    assert graph.ground.index == 0


def test_patches_compare_the_ground_carried_by_the_legs():
    patches = GroundPatches(stale_after=None)
    here = gtsam.Pose3()
    assert patches.patch(here, level_ground(), 0) and patches.index == 0
    for _ in range(10):
        patches.moved(gtsam.Pose3(gtsam.Rot3(), np.array([0.1, 0.0, 0.0])))
    assert not patches.patch(here, level_ground(), 10)  # the estimate's own pose does not count
    patches.moved(gtsam.Pose3(gtsam.Rot3(), np.array([0.1, 0.0, 2 * PATCH_STEP])))  # the legs step up
    assert patches.patch(here, level_ground(), 11) and patches.index == 1
    tilted = np.r_[np.array([np.sin(0.1), 0.0, np.cos(0.1)]), -HEIGHT]  # a 6 deg slope begins
    assert patches.patch(here, tilted, 12) and patches.index == 2


def test_planes_move_between_frames_and_bad_ones_are_named():
    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Ry(0.2).matrix()
    T[:3, 3] = (1.0, 2.0, 0.3)
    plane = np.array([0.0, 0.0, 1.0, -0.4])  # z = -0.4 in frame b
    in_a = plane_in_frame(plane, T)
    point_b = np.array([3.0, -1.0, -0.4])
    point_a = T[:3, :3] @ point_b + T[:3, 3]
    assert abs(in_a[:3] @ point_a - in_a[3]) < 1e-12
    coefficients = to_gtsam(plane).planeCoefficients()  # GTSAM's n . p + d = 0
    assert abs(coefficients[:3] @ point_b + coefficients[3]) < 1e-12
    for bad, words in (([0, 0, 1], "4 finite"), ([0, 0, np.nan, 1], "4 finite"), ([0, 0, 2, -1], "unit vector")):
        with pytest.raises(ValueError, match=words):
            check_plane(np.array(bad, dtype=float))
    with pytest.raises(ValueError, match="ground_sigmas"):
        FusionGraph(np.eye(4), FusionConfig(ground_sigmas=(0.001, -1.0)))
