"""Drive the robot stand-in through a scene to a goal, observing LiDAR and leg odometry."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from l3e_env.config import EnvConfig, from_dict
from l3e_env.core.transforms import inverse, matrix_to_pose
from l3e_env.sim.imu import StepAttitude, StepGyro
from l3e_env.sim.lidar import DESKEW_STEPS, Lidar, Scan, deskew, deskew_motion
from l3e_env.sim.odometry import LegOdometry
from l3e_env.sim.raycast import make_caster
from l3e_env.sim.render import TopDownRenderer
from l3e_env.sim.robot import Robot
from l3e_env.sim.world import World
from scenes import Scene, make_scene
from scenes.geometry import polyline_length

ARRIVAL = ("truth", "estimate")  # EnvConfig.arrival: which pose ends an episode at the goal


def check_env_config(config: EnvConfig) -> None:
    """ValueError for an arrival, stop radius or fusion the episode cannot use."""
    if config.arrival not in ARRIVAL:
        raise ValueError(f"arrival must be one of {ARRIVAL}, got {config.arrival!r}")
    if not 0 < config.stop_radius <= config.goal_radius:
        raise ValueError(
            f"stop_radius must be above 0 and at most the goal radius of {config.goal_radius} m, "
            f"got {config.stop_radius!r}"
        )
    if config.arrival == "estimate" and not config.fusion.enabled:
        raise ValueError(
            "arrival 'estimate' ends an episode on the fused estimate: turn the fusion on "
            "(fusion.enabled), or use arrival 'truth'"
        )


class NavigationEnv(gym.Env):
    """Observation (Dict):
      ranges   (beams, width) float32: range image in metres, 0 where there is no return
      valid    (beams, width) int8: 1 where `ranges` holds a return
      odometry (6,) float32: leg-odometry increment of the last step, (x, y, z, roll, pitch, yaw)
      goal     (3,) float32: goal in the body frame (x, y, distance)
    Action: Box [-1, 1]^3, the twist (vx, vy, yaw rate) as a fraction of the robot's max twist
    (default 1 m/s, 0.5 m/s, 1 rad/s); NaN or out-of-range actions raise ValueError.
    Reward: progress_reward x metres gained towards the goal - step_penalty
      - collision_penalty when blocked by geometry + goal_reward on arrival.
    Terminated on arrival within goal_radius of the true pose, or with `arrival="estimate"` where
    the fused estimate, the pose the robot believes, comes within stop_radius; truncated after
    max_episode_steps.
    info: T_w_b (4x4 ground truth), pose (x, y, z, roll, pitch, yaw), odom_T_w_b (dead reckoning),
      blocked, distance_to_goal. The current Scan (points in the sensor frame) is `env.unwrapped.scan`.
      With `fusion.enabled` (see FusionSettings) also: fused_T_w_b (odometry and masked ICP
      fused), localizability_probabilities and localizability_mask (6,) in (x, y, z, roll,
      pitch, yaw) order, localizability_known, running_ate (m, fused vs ground truth since reset)
      and fusion_counts (ICP failures, unknown predictions, detector errors, fallbacks).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        config: EnvConfig | dict | None = None,
        render_mode: str | None = None,
        scene_object: Scene | None = None,
        **overrides: Any,
    ):
        super().__init__()
        if isinstance(config, dict) or config is None:
            config = from_dict(EnvConfig, {**(config or {}), **overrides})
        elif overrides:
            raise ValueError("pass either an EnvConfig or keyword options, not both")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        check_env_config(config)
        self.config, self.render_mode = config, render_mode
        self.scene = scene_object or make_scene(config.scene, **config.scene_params)
        if config.route not in self.scene.routes:
            raise ValueError(
                f"scene '{self.scene.name}' has no route '{config.route}'; routes: {sorted(self.scene.routes)}"
            )
        self.route = self.scene.routes[config.route]
        self.world = World(self.scene, config.robot)
        self.robot = Robot(self.world)
        self.lidar = Lidar(make_caster(config.lidar.backend, self.scene.mesh, self.world.client), config.lidar)
        self.odometry = LegOdometry(config.odometry)
        pattern = self.lidar.pattern
        self.width = config.range_image_width or pattern.image_width
        if pattern.n_azimuth % self.width:
            raise ValueError(
                f"range_image_width {self.width} must divide the {pattern.n_azimuth} columns of {pattern.name}"
            )
        self.observation_space = self._observation_space()
        self.action_space = spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)
        speed = float(config.robot.max_twist[0])
        route_length = polyline_length(self.route)
        self.max_steps = config.max_episode_steps or int(np.ceil(3 * route_length / (speed * config.robot.dt)))
        self._renderer: TopDownRenderer | None = None
        self.fusion = None
        swept_fusion = config.fusion.enabled and config.lidar.sweep
        self.gyro = StepGyro() if swept_fusion and config.fusion.deskew == "gyro" else None  # deskews only there
        self.attitude = StepAttitude() if config.fusion.enabled and config.fusion.attitude != "none" else None
        if config.fusion.enabled:
            from l3e_env.detection.pipeline import OnlineFusion  # ICP, detector and GTSAM only when asked for

            self.fusion = OnlineFusion(config.fusion, self.lidar, config.odometry, self.robot.T_b_s)
        self._fusion_info: dict[str, Any] = {}

    def _observation_space(self) -> spaces.Dict:
        """The range image and its valid returns, the odometry step and the goal in the body frame."""
        shape = (self.lidar.pattern.n_beams, self.width)
        odom_bound = np.array([5.0, 5.0, 5.0, np.pi, np.pi, np.pi], dtype=np.float32)
        extent = np.float32(2 * np.linalg.norm(self.scene.bounds[1] - self.scene.bounds[0]))
        return spaces.Dict(
            {
                "ranges": spaces.Box(0.0, self.lidar.max_range, shape, np.float32),
                "valid": spaces.Box(0, 1, shape, np.int8),
                "odometry": spaces.Box(-odom_bound, odom_bound, (6,), np.float32),
                "goal": spaces.Box(-extent, extent, (3,), np.float32),
            }
        )

    # -- gymnasium API -------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        x, y, yaw = self.scene.start
        self.robot.reset(x, y, yaw, z_ground=float(self.route[0, 2]))
        # the odometry and the LiDAR draw from streams of their own, so that a drive's odometry noise is the
        # same whatever the sensor, its beam pattern or its sweep setting
        odometry_rng, self._lidar_rng = self.np_random.spawn(2)
        self.odometry.reset(odometry_rng)
        # streams of their own: the odometry's and the LiDAR's draws stay as they were
        gyro_rng, attitude_rng = self.np_random.spawn(2)
        if self.gyro is not None:
            self.gyro.reset(gyro_rng)
        if self.attitude is not None:
            self.attitude.reset(attitude_rng)
        self.odom_T_w_b = self.robot.T_w_b.copy()
        self._odometry_steps: list[np.ndarray] = []  # the odometry's last steps, to deskew with
        self.steps = 0
        self.trail = [self.robot.T_w_b[:3, 3].copy()]
        # swept: the revolution before the start, standing still
        start = self.robot.T_w_s if self.config.lidar.sweep else None
        self._scan = self.lidar.scan(self.robot.T_w_s, self._lidar_rng, start=start, period=self.config.robot.dt)
        self._distance = self._goal_distance()
        if self.fusion is not None:
            self._fusion_info = self.fusion.reset(self.robot.T_w_b, self._scan.points)
        return self._observation(np.eye(4)), self._info(blocked=False)

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (3,) or not np.isfinite(action).all():
            raise ValueError(f"action must be 3 finite numbers (vx, vy, yaw_rate), got {action!r}")
        if not ((action >= self.action_space.low) & (action <= self.action_space.high)).all():
            raise ValueError(
                f"action {action} is outside the action space [{self.action_space.low}, {self.action_space.high}]"
            )
        T_prev = self.robot.T_w_b
        T_cur, blocked = self.robot.step(action * np.asarray(self.config.robot.max_twist))
        increment = self.odometry.measure(T_prev, T_cur)
        self.odom_T_w_b = self.odom_T_w_b @ increment
        # a swept revolution turns with the step: from the pose before it to the pose after it
        start = T_prev @ self.robot.T_b_s if self.config.lidar.sweep else None
        self._scan = self.lidar.scan(self.robot.T_w_s, self._lidar_rng, start=start, period=self.config.robot.dt)
        if self.fusion is not None:
            points = self._scan.points
            if start is not None:  # deskewed with the gyro's turn and the odometry's motion, as LiDAR odometry does
                self._odometry_steps = (self._odometry_steps + [increment])[-DESKEW_STEPS:]
                turn = (
                    None
                    if self.gyro is None
                    else self.gyro.measure(T_prev[:3, :3], T_cur[:3, :3], self.config.robot.dt)
                )
                motion = deskew_motion(self._odometry_steps, turn, mounting=self.robot.T_b_s)
                points = deskew(points, motion, self.lidar.pattern)
            attitude = None if self.attitude is None else self.attitude.measure(T_cur[:3, :3], self.config.robot.dt)
            self._fusion_info = self.fusion.step(increment, points, T_cur, attitude)
        self.steps += 1
        self.trail.append(T_cur[:3, 3].copy())
        distance = self._goal_distance()
        reward = self.config.progress_reward * (self._distance - distance) - self.config.step_penalty
        reward -= self.config.collision_penalty * blocked
        self._distance = distance
        if self.config.arrival == "estimate":  # where the robot believes it is
            terminated = self._goal_distance(self._fusion_info["fused_T_w_b"]) <= self.config.stop_radius
        else:
            terminated = distance <= self.config.goal_radius
        reward += self.config.goal_reward * terminated
        truncated = (not terminated) and self.steps >= self.max_steps
        return self._observation(increment), float(reward), bool(terminated), bool(truncated), self._info(blocked)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = TopDownRenderer(self.scene)
        return self._renderer.frame(self.robot.T_w_b, self.scan_world(), np.array(self.trail))

    def close(self):
        if self.fusion is not None:
            self.fusion.close()
        self.world.close()

    # -- helpers ---------------------------------------------------------------------------
    @property
    def scan(self) -> Scan:
        return self._scan

    def scan_world(self) -> np.ndarray:
        T = self.robot.T_w_s
        return self._scan.points @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)

    def _goal_distance(self, T_w_b: np.ndarray | None = None) -> float:
        """From the robot's true pose, or from `T_w_b`, to the goal (m)."""
        T_w_b = self.robot.T_w_b if T_w_b is None else T_w_b
        return float(np.linalg.norm(self.scene.goal - T_w_b[:2, 3]))

    def _observation(self, increment: np.ndarray) -> dict[str, np.ndarray]:
        ranges = self._scan.range_image(self.width)
        goal_b = inverse(self.robot.T_w_b) @ np.array([*self.scene.goal, self.robot.T_w_b[2, 3], 1.0])
        return {
            "ranges": ranges,
            "valid": (ranges > 0).astype(np.int8),
            "odometry": matrix_to_pose(increment).astype(np.float32),
            "goal": np.array([goal_b[0], goal_b[1], self._distance], dtype=np.float32),
        }

    def _info(self, blocked: bool) -> dict[str, Any]:
        return {
            "T_w_b": self.robot.T_w_b.copy(),
            "pose": matrix_to_pose(self.robot.T_w_b),
            "odom_T_w_b": self.odom_T_w_b.copy(),
            "blocked": bool(blocked),
            "distance_to_goal": self._distance,
            **self._fusion_info,
        }
