import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from l3e_env.core.transforms import conjugate, level_rotation, level_rotation_of, matrix_to_pose, pose_to_matrix

angles = st.floats(-1.2, 1.2)


@settings(max_examples=60, deadline=None)
@given(roll=angles, pitch=angles, yaw=st.floats(-3.1, 3.1))
def test_the_level_frame_keeps_the_heading_and_takes_out_the_tilt(roll, pitch, yaw):
    T_w_s = pose_to_matrix([1.0, 2.0, 3.0, roll, pitch, yaw])
    R_l_s = level_rotation_of(T_w_s)
    np.testing.assert_allclose(R_l_s @ R_l_s.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R_l_s) == pytest.approx(1.0)
    # the world seen from the level frame is the sensor's heading alone: a turn about z by its yaw
    np.testing.assert_allclose(T_w_s[:3, :3] @ R_l_s.T, pose_to_matrix([0, 0, 0, 0, 0, yaw])[:3, :3], atol=1e-9)
    np.testing.assert_allclose(R_l_s @ T_w_s[2, :3], [0, 0, 1], atol=1e-12)  # up is the level frame's z


def test_a_level_sensor_is_its_own_level_frame_and_a_sensor_looking_up_still_gets_one():
    np.testing.assert_allclose(level_rotation([0, 0, 2.0]), np.eye(3), atol=1e-12)
    up = level_rotation([1.0, 0, 0])  # the sensor's x points up: no heading of its own
    np.testing.assert_allclose(up @ up.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(up @ [1.0, 0, 0], [0, 0, 1], atol=1e-12)


@pytest.mark.parametrize("bad", [[0, 0, 0], [np.nan, 0, 1], [0, np.inf, 1], [0, 1]])
def test_an_up_vector_that_is_zero_or_not_finite_is_refused_by_name(bad):
    with pytest.raises(ValueError, match="up vector"):
        level_rotation(bad)


def test_conjugation_writes_a_transform_in_a_turned_frame():
    T = pose_to_matrix([0.3, 0.0, 0.0, 0.0, 0.0, 0.1])
    R = pose_to_matrix([0, 0, 0, 0, 0, np.pi / 2])[:3, :3]  # x becomes y
    np.testing.assert_allclose(conjugate(T, R)[:3, 3], [0.0, 0.3, 0.0], atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-100, 100), min_size=3, max_size=3),
    st.floats(-np.pi, np.pi),
    st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3),
    st.floats(-np.pi, np.pi),
)
def test_poses_and_matrices_are_scipys_extrinsic_xyz_euler_angles(xyz, roll, pitch, yaw):
    from scipy.spatial.transform import Rotation

    T = pose_to_matrix(np.array([*xyz, roll, pitch, yaw]))
    np.testing.assert_allclose(T[:3, :3], Rotation.from_euler("xyz", [roll, pitch, yaw]).as_matrix(), atol=1e-12)
    assert np.array_equal(T[:3, 3], xyz) and np.array_equal(T[3], [0, 0, 0, 1])
    back = matrix_to_pose(T)
    assert back[:3].tolist() == xyz
    turned = (back[3:] - Rotation.from_matrix(T[:3, :3]).as_euler("xyz") + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(turned, 0.0, atol=1e-9)


def test_a_pose_at_gimbal_lock_reads_back_as_scipy_reads_it():
    from scipy.spatial.transform import Rotation

    T = pose_to_matrix(np.array([0, 0, 0, 0.3, np.pi / 2, 0.2]))
    with pytest.warns(UserWarning, match="Gimbal lock"):
        expected = Rotation.from_matrix(T[:3, :3]).as_euler("xyz")
        back = matrix_to_pose(T)
    np.testing.assert_allclose(back[3:], expected)
    np.testing.assert_allclose(pose_to_matrix(back), T, atol=1e-9)  # the same rotation
