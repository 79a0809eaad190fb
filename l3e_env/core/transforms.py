"""SE(3) helpers in the project's axis order (x, y, z, roll, pitch, yaw)."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def pose_to_matrix(xyzrpy: np.ndarray) -> np.ndarray:
    """(x, y, z, roll, pitch, yaw) -> 4x4, rotation R = Rz(yaw) Ry(pitch) Rx(roll). Written out: a
    simulated step converts poses dozens of times, and a scipy Rotation costs many times as much a call."""
    v = np.asarray(xyzrpy, dtype=np.float64)
    x, y, z = v[:3].tolist()
    (cr, cp, cy), (sr, sp, sy) = np.cos(v[3:6]).tolist(), np.sin(v[3:6]).tolist()
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr, x],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr, y],
            [-sp, cp * sr, cp * cr, z],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def matrix_to_pose(T: np.ndarray) -> np.ndarray:
    """4x4 -> (x, y, z, roll, pitch, yaw), pitch within +-90 deg (as scipy's extrinsic "xyz" Euler
    angles); written out as pose_to_matrix, with scipy's at gimbal lock (pitch within 1e-6 rad of 90 deg)."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    out = np.empty(6)
    out[:3] = T[:3, 3]
    cos_pitch = math.hypot(R[0, 0], R[1, 0])
    if cos_pitch < 1e-6:
        out[3:] = Rotation.from_matrix(R).as_euler("xyz")
    else:
        out[3:] = math.atan2(R[2, 1], R[2, 2]), math.atan2(-R[2, 0], cos_pitch), math.atan2(R[1, 0], R[0, 0])
    return out


def planar_pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    return pose_to_matrix(np.array([x, y, z, 0.0, 0.0, yaw]))


def inverse(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def nearest_rigid(T: np.ndarray) -> np.ndarray:
    """T with its rotation replaced by the nearest rotation (SVD): a pose composed from many keeps
    its rounding, and one taken through `inverse` (which transposes) amplifies it."""
    u, _, vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return out


def rotation_angle(T: np.ndarray) -> float:
    """The angle (rad) of T's rotation."""
    return float(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0)))


def yaw_of(T: np.ndarray) -> float:
    return float(np.arctan2(T[1, 0], T[0, 0]))


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a pose for tangent vectors ordered (translation, rotation): a perturbation in
    the frame T moves into its parent's. Hand-written: GTSAM's AdjointMap orders rotation first."""
    R, t = T[:3, :3], T[:3, 3]
    skew = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R
    A[:3, 3:] = skew @ R
    return A


def level_rotation(up: np.ndarray) -> np.ndarray:
    """R_l_s: the rotation from a sensor's frame into its level frame, given the up direction
    (against gravity) in the sensor's frame. The level frame's z is up, its x the sensor's x
    projected onto the level plane (the sensor's heading), its y completes it; roll, pitch and yaw
    are the turns about those axes. A sensor pointing its x straight up or down has no heading:
    its -z (or z) projected onto the level plane stands in for it."""
    u = np.asarray(up, dtype=np.float64).reshape(-1)
    if u.shape != (3,) or not np.isfinite(u).all():
        raise ValueError(f"an up vector is three finite numbers, got {np.asarray(up).tolist()}")
    norm = float(np.linalg.norm(u))
    if norm < 1e-9:
        raise ValueError("the up vector is zero: give the direction against gravity in the sensor's frame")
    z = u / norm
    for axis in (np.array([1.0, 0.0, 0.0]), -np.sign(z[0]) * np.array([0.0, 0.0, 1.0])):
        x = axis - (axis @ z) * z
        if np.linalg.norm(x) > 1e-6:
            break
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def level_rotation_of(T_w_s: np.ndarray) -> np.ndarray:
    """R_l_s of a sensor posed in a world whose z is up."""
    return level_rotation(np.asarray(T_w_s, dtype=np.float64)[2, :3])


def rotation_pose(R: np.ndarray) -> np.ndarray:
    """The 4x4 transform of a rotation alone (no translation)."""
    T = np.eye(4)
    T[:3, :3] = R
    return T


def conjugate(T: np.ndarray, R_b_a: np.ndarray) -> np.ndarray:
    """A transform of frame a's points written in frame b (same origin, b = R_b_a a): R T R^T."""
    A = rotation_pose(R_b_a)
    return A @ T @ inverse(A)
