"""The PyBullet world: the static scene as a concave mesh and the robot's collision box."""

from __future__ import annotations

import contextlib

import numpy as np
from scipy.spatial.transform import Rotation

from l3e_env.config import RobotConfig
from l3e_env.core.quiet import import_pybullet
from scenes import Scene

from .raycast import PyBulletCaster, add_static_mesh

pb = import_pybullet()  # without its build banner

SCENE_GROUP, ROBOT_GROUP = 1, 4


class World:
    """One PyBullet DIRECT client per world, so worlds in one process never interfere."""

    def __init__(self, scene: Scene, robot: RobotConfig | None = None):
        self.scene = scene
        self.robot_config = robot or RobotConfig()
        self.client = pb.connect(pb.DIRECT)
        self.scene_bodies = add_static_mesh(self.client, scene.mesh)
        self._boxes = np.array(  # (bodies, low/high, xyz): each piece's box, to touch only the pieces near the robot
            [pb.getAABB(body, physicsClientId=self.client) for body in self.scene_bodies], dtype=np.float64
        )
        half = np.asarray(self.robot_config.base_size) / 2
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=self.client)
        self.robot_body = pb.createMultiBody(baseMass=0, baseCollisionShapeIndex=shape, physicsClientId=self.client)
        # rays (mask SCENE_GROUP) never hit the robot's own body
        pb.setCollisionFilterGroupMask(self.robot_body, -1, ROBOT_GROUP, SCENE_GROUP, physicsClientId=self.client)
        self.rays = PyBulletCaster(self.client, collision_mask=SCENE_GROUP)

    def close(self) -> None:
        if self.client >= 0 and pb.isConnected(self.client):
            pb.disconnect(self.client)
        self.client = -1

    def __del__(self) -> None:  # best effort; explicit close() is preferred
        with contextlib.suppress(Exception):
            self.close()

    def in_collision(self, T_w_b: np.ndarray, tolerance: float = 0.005) -> bool:
        """Whether the robot's base box at T_w_b penetrates the scene."""
        quat = Rotation.from_matrix(T_w_b[:3, :3]).as_quat()
        pb.resetBasePositionAndOrientation(
            self.robot_body, T_w_b[:3, 3].tolist(), quat.tolist(), physicsClientId=self.client
        )
        # the scene's pieces whose boxes the robot's box (turned, in the world's axes) overlaps
        reach = np.abs(T_w_b[:3, :3]) @ (np.asarray(self.robot_config.base_size) / 2) + 0.05
        centre = T_w_b[:3, 3]
        overlap = np.all((self._boxes[:, 0] <= centre + reach) & (self._boxes[:, 1] >= centre - reach), axis=1)
        near = [body for body, hit in zip(self.scene_bodies, overlap) if hit]
        return any(
            c[8] < -tolerance
            for body in near
            for c in pb.getClosestPoints(self.robot_body, body, distance=0.0, physicsClientId=self.client)
        )

    def ground_pose(self, x: float, y: float, yaw: float, z_ref: float) -> np.ndarray | None:
        """Base pose standing on the terrain at (x, y, yaw), or None where there is no ground.

        Rays from above each foot find the terrain; a plane through the hits gives height, roll
        and pitch, so the body follows slopes the way a walking robot's does.
        """
        cfg = self.robot_config
        fx, fy = cfg.feet_xy
        feet = np.array([[fx, fy], [fx, -fy], [-fx, fy], [-fx, -fy], [0.0, 0.0]])
        c, s = np.cos(yaw), np.sin(yaw)
        xy = feet @ np.array([[c, s], [-s, c]]) + (x, y)
        top = z_ref + cfg.max_step_up
        starts = np.column_stack([xy, np.full(len(xy), top)])
        depth = cfg.max_step_up + 3.0
        dist = self.rays.cast_many(starts, np.array([0.0, 0.0, -1.0]), depth)
        hit = np.isfinite(dist)
        if hit.sum() < 3 or not hit[-1]:
            return None
        z = top - dist[hit]
        A = np.column_stack([np.ones(hit.sum()), feet[hit]])
        a, b, cc = np.linalg.lstsq(A, z, rcond=None)[0]
        # plane in the yawed frame: slopes b (forward) and cc (left)
        normal_local = np.array([-b, -cc, 1.0]) / np.sqrt(1 + b * b + cc * cc)
        R_yaw = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        z_axis = R_yaw @ normal_local
        x_axis = np.array([c, s, 0.0]) - z_axis * (z_axis @ np.array([c, s, 0.0]))
        x_axis /= np.linalg.norm(x_axis)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
        # the base centre stays above (x, y), standing_height from the terrain along its normal
        T[:3, 3] = (x, y, a + cfg.standing_height / z_axis[2])
        return T
