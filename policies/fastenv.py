"""Fast PPO training: the robot's planar kinematics on the free-space grid, with the cached
localizability map in place of LiDAR, detector, ICP and the factor graph (thousands of steps
per second instead of about 20). Policies trained here are evaluated with the full pipeline.

Reward per decision: progress (metres of shortest free-space distance to the goal gained)
- lam * expected drift of the motion (the planner's drift model on the map, see
policies.planner, plus turn_drift per radian turned and lateral_drift per metre walked sideways)
- step_penalty - collision_penalty when blocked - tight_penalty per metre walked in cells next to
an obstacle + goal_reward on arrival.
Here the robot is a point on free cells; the simulated robot is a 0.9 x 0.5 m box that fits a
cell next to an obstacle only square to the grid at its centre, so brushing past obstacles (which
gets it stuck there) costs as much as the walk gains, the planner's squeeze rule.
The expected drift penalises steps taken where the detector will mask axes, weighted by how much
the odometry drifts along them; the fused estimate's actual error is only known with the full
pipeline, too slow to train on here, and its expectation is what this term is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from l3e_env.config import EnvConfig, RobotConfig
from l3e_env.sim.robot import planar_motion

from .context import SceneContext
from .observation import PolicyView
from .planner import TIGHT_CLEARANCE


def action_layout(sideways: bool) -> tuple[str, ...]:
    """The names of a policy's action components (each normalised to [-1, 1])."""
    return ("vx", "vy", "yaw_rate") if sideways else ("vx", "yaw_rate")


def as_twist(action: Any, sideways: bool) -> np.ndarray:
    """A policy's action as the robot's normalised twist (vx, vy, yaw rate), clipped to [-1, 1];
    a ValueError names an action of the wrong size or with non-finite numbers."""
    layout = action_layout(sideways)
    a = np.asarray(action, dtype=np.float64)
    if a.shape != (len(layout),) or not np.isfinite(a).all():
        raise ValueError(f"action must be {len(layout)} finite numbers ({', '.join(layout)}), got {action!r}")
    a = np.clip(a, -1.0, 1.0)
    return a if sideways else np.array([a[0], 0.0, a[1]])


@dataclass
class FastEnvConfig:
    lam: float = 50.0  # weight of expected drift (m) against metres of progress, as in the planner
    action_repeat: int = 5  # environment steps (0.1 s each) per decision
    progress_reward: float = 1.0
    step_penalty: float = 0.05
    collision_penalty: float = 0.5
    tight_penalty: float = 1.0  # per metre walked where the clearance is under tight_clearance
    # expected drift (m) per radian turned, weighed by lam like the map's: every turn leaves ICP's
    # heading a little off even where nothing is masked (about 0.0015 rad per radian on the fork,
    # docs/log.md), a position error over the planner's 10 m lever arm. Without it a policy
    # that swings its heading at the full yaw rate pays nothing here and drifts 3x more in the pipeline
    turn_drift: float = 0.015
    # expected drift (m) per metre walked sideways (along the body's y): at full speed a diagonal
    # gait leaves ICP's heading 1.2-4.5 deg off over the fork's route against 1.0-3.3 deg walking
    # forward, depending on how the voxel grid lies (docs/log.md, "PPO's gait" and "ICP's
    # heading over a route"), about 0.007 m of drift per metre over the 10 m lever arm at the first
    # measured 4 deg. 0.015 halves PPO's drift; the policy then walks facing its way, and on fork-104
    # it wedges a corner against a box, which the evaluation's recovery (BackOff) backs it out of
    lateral_drift: float = 0.015
    # the policy's action: (vx, vy, yaw rate), or without `sideways` (vx, yaw rate), walking facing
    # its way as the route followers do (docs/results.md, "Where the detour should pay", says how each did)
    sideways: bool = True
    tight_clearance: float = TIGHT_CLEARANCE  # m, the planner's
    goal_reward: float = 10.0
    # the full pipeline's evaluation stops where the robot's estimate comes this close to the goal: a
    # policy trained to a wider radius never learns the last metre and circles the goal there
    goal_radius: float = EnvConfig().stop_radius
    robot: RobotConfig = field(default_factory=RobotConfig)


class MapNavigationEnv(gym.Env):
    """Drive from each variant's start to its goal; a variant is drawn per episode."""

    def __init__(self, contexts: list[SceneContext], config: FastEnvConfig | None = None):
        if not contexts:
            raise ValueError("MapNavigationEnv needs at least one scene context")
        missing = [c.scene.name for c in contexts if c.locmap is None]
        if missing:
            raise ValueError(f"scenes without a localizability map: {missing}")
        self.config = config or FastEnvConfig()
        self.views = [PolicyView(c.space, c.built_map, c.scene.goal, self.config.lam) for c in contexts]
        self.contexts = contexts
        self.observation_space = self.views[0].observation_space
        self.action_space = spaces.Box(-1.0, 1.0, (len(action_layout(self.config.sideways)),), dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.k = int(self.np_random.integers(len(self.contexts)))
        ctx, self.view = self.contexts[self.k], self.views[self.k]
        self.x, self.y, self.yaw = (float(v) for v in ctx.scene.start)
        self.to_go = self.view.distance_to_go(np.array([self.x, self.y]))
        if not np.isfinite(self.to_go):
            raise ValueError(f"scene '{ctx.scene.name}': the goal cannot be reached from the start")
        speed = self.config.robot.max_twist[0] * self.config.robot.dt * self.config.action_repeat
        self.max_decisions = int(np.ceil(3 * self.to_go / speed))
        self.decisions, self.expected_drift, self.length, self.tight_length = 0, 0.0, 0.0, 0.0
        self.trail = [(self.x, self.y)]
        return self.view(self.x, self.y, self.yaw), self._info(False)

    def step(self, action):
        cfg, robot = self.config, self.config.robot
        twist = as_twist(action, cfg.sideways) * np.asarray(robot.max_twist)
        blocked, drift, moved, tight = False, 0.0, 0.0, 0.0
        for _ in range(cfg.action_repeat):
            dx, dy, yaw = planar_motion(self.yaw, twist, robot.dt)  # the simulated robot's own kinematics
            x, y = self.x + dx, self.y + dy
            for cx, cy in ((x, y), (x, self.y), (self.x, y), (self.x, self.y)):  # slide along walls
                if self.view.space.is_free(np.array([cx, cy])):
                    break
            blocked |= (cx, cy) != (x, y)
            step = float(np.hypot(cx - self.x, cy - self.y))
            if step > 0:
                drift += step * float(self.view.drift_rate(np.array([cx, cy]), yaw))
            drift += (cfg.turn_drift * abs(twist[2]) + cfg.lateral_drift * abs(twist[1])) * robot.dt
            moved += step
            tight += step * (self.view.clearance(np.array([cx, cy])) < cfg.tight_clearance)
            self.x, self.y, self.yaw = cx, cy, yaw
        self.trail.append((self.x, self.y))
        self.decisions += 1
        self.expected_drift += drift
        self.length += moved
        self.tight_length += tight
        to_go = self.view.distance_to_go(np.array([self.x, self.y]))
        reward = cfg.progress_reward * (self.to_go - to_go) - cfg.lam * drift - cfg.step_penalty
        reward -= cfg.collision_penalty * blocked + cfg.tight_penalty * tight
        self.to_go = to_go
        terminated = bool(np.hypot(*(self.view.goal - (self.x, self.y))) <= cfg.goal_radius)
        reward += cfg.goal_reward * terminated
        truncated = (not terminated) and self.decisions >= self.max_decisions
        return self.view(self.x, self.y, self.yaw), float(reward), terminated, truncated, self._info(blocked)

    def _info(self, blocked: bool) -> dict[str, Any]:
        return {
            "scene": self.contexts[self.k].scene.name,
            "pose": (self.x, self.y, self.yaw),
            "blocked": blocked,
            "expected_drift": self.expected_drift,
            "path_length": self.length,
            "tight_length": self.tight_length,
            "distance_to_go": self.to_go,
        }
