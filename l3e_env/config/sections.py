"""Typed configuration: one dataclass per component, YAML in and out.

Defaults are the paper's values or documented choices; every artefact dumps the config that
made it (see `dump_yaml`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any


@dataclass
class LidarConfig:
    """Sensor model and noise. Ranges in metres; a miss produces no point."""

    model: str = "vlp16"  # vlp16 | os0-128 | a name registered with lidar.register_pattern
    backend: str = "embree"  # embree | pybullet
    range_noise_std: float = 0.03  # Gaussian range noise (VLP-16 datasheet: +-3 cm)
    dropout: float = 0.0  # probability that a return is lost
    min_range: float | None = None  # None: the pattern's own
    max_range: float | None = None  # None: the pattern's own
    # cast each column from the pose at its firing time while the robot moves (a spinning sensor's
    # motion distortion, with each point's time in Scan.times); False: the revolution at one pose
    sweep: bool = False


@dataclass
class RobotConfig:
    """A quadruped-sized stand-in (about ANYmal-C) commanded by a planar twist."""

    base_size: tuple[float, float, float] = (0.9, 0.5, 0.4)  # length, width, height of the base box
    standing_height: float = 0.55  # ground to base centre
    lidar_offset: tuple[float, float, float] = (0.0, 0.0, 0.3)  # sensor in the base frame
    feet_xy: tuple[float, float] = (0.35, 0.2)  # half-spacing of the feet that sense the ground
    max_step_up: float = 0.5  # highest ledge the robot climbs in one step
    max_twist: tuple[float, float, float] = (1.0, 0.5, 1.0)  # |vx| m/s, |vy| m/s, |yaw rate| rad/s
    dt: float = 0.1  # one step = one LiDAR revolution at 10 Hz


@dataclass
class OdometryConfig:
    """Leg odometry drift. Noise standard deviations grow with the motion of each step; biases
    are per metre travelled and wander slowly (random walk per sqrt(metre)). Yaw and z drift the
    most, as they do on legged robots."""

    trans_noise_per_m: float = 0.02  # sigma of x, y error per metre moved
    z_noise_per_m: float = 0.02
    rp_noise_per_m: float = 0.002  # rad per metre (roll and pitch)
    yaw_noise_per_m: float = 0.005  # rad per metre
    yaw_noise_per_rad: float = 0.02  # rad per radian turned
    yaw_bias_std: float = 0.001  # rad per metre, initial bias spread
    yaw_bias_walk: float = 0.0003  # rad/m per sqrt(m)
    z_bias_std: float = 0.005  # m per metre, initial bias spread
    z_bias_walk: float = 0.0005
    scale_error_std: float = 0.02  # constant stride-length scale error per episode


# the fusion's modes, checked where FusionSettings is made; the CLI's choices are these
ATTITUDE_MODES = ("none", "tilt", "full")  # the IMU's orientation in the fusion: none, roll and pitch, all three
# where a dataset's errors come from: children ray-cast in the scene (the Monte-Carlo labels, ground
# truth) or the parent scan's own estimate (a distillation set, for training only)
LABELLERS = ("scene", "scan")
DATASET_PRESETS = (
    "small",
    "paper",
    "level",
    "distill",
    "random",
    "random-32",
    "random-128",
)  # l3e_env.data.dataset.PRESETS, by name
GROUND_MODES = ("none", "plane")  # the scans' ground planes in the fusion: not used, or as patches (fusion.ground)
FUSION_BACKENDS = ("graph", "ekf")  # iSAM2 smoother, filterpy EKF
FUSION_MODES = ("mask", "full", "drop", "directions", "gate")  # see fusion.FusionConfig
DESKEW_SOURCES = ("gyro", "odometry")  # where a deskewing's rotation comes from; its translation is the odometry's


KEYFRAME_DISTANCE = 4.0  # m: the graph's scans registered onto keyframes renewed this often (docs/decisions.md)
MAX_DETECTOR_EVERY = 100  # steps (10 s at 10 Hz) a detector's answer may hold
# the detector judges every 4th scan (0.4 s at 10 Hz) and its answer holds between: a quarter of its cost
# a step (chosen in docs/decisions.md, "Fusion")
DETECTOR_EVERY = 4


@dataclass(frozen=True)
class FusionSettings:
    """The fusion that l3e_env runs, in the environments' loop (`EnvConfig.fusion`, off by default: it
    costs ICP and a detector per step), in `l3e ate`, `l3e sweep` and the policies' evaluation; the
    estimator's own parameters are `fusion.FusionConfig`, made from these by
    `sim.odometry.odometry_fusion_config`.
    detector: a detector spec (config.detector_spec.DETECTOR_GRAMMAR); backend: graph | ekf;
    mode: mask | full | drop (see fusion.FusionConfig); deskew: gyro | odometry, where a swept
    revolution's deskewing takes its rotation from (its translation is the leg odometry's);
    attitude: none | tilt | full, the IMU's orientation fused once a second (tilt: roll and pitch,
    which gravity holds; full: with the magnetometer's heading); odometry_bias: the leg odometry's
    biases estimated as fusion states, () or among "yaw", "z" and "scale" (see fusion.bias; their prior is the
    odometry config's); detector_process: a learned detector judges each scan in a process of its
    own while the step registers it (detection.ahead; the same answers, faster where a core is
    free). The fusion's ICP is the detectors' registration (the one their labels were made with),
    its factor weighed by the registration's Hessian (fusion.FusionConfig) and masked on the axes of
    the scan's level frame. detector_every: the detector judges every that many scans and its answer
    holds in between (a flag is late by at most that many steps less one). keyframe_distance: each
    scan is registered onto a keyframe renewed every that many metres (or 0.8 rad of turn, or 100
    scans), from the odometry's guess, and the ICP factor ties the keyframe's pose to the scan's
    (detection.pipeline.ScanRegistrar; the graph backend); 0: each scan onto the one before; None:
    KEYFRAME_DISTANCE with the graph, 0 with the EKF (which keeps no earlier pose to tie to).

    The defaults are a legged robot's estimator, one for every command (docs/decisions.md, "One
    estimator"): the IMU's roll and pitch, the legs' heading and stride-scale biases as states; each
    part stays one option away (attitude "none", odometry_bias (), keyframe_distance 0, detector_every 1)."""

    enabled: bool = False
    detector: str = "learned"
    backend: str = "graph"
    mode: str = "gate"
    deskew: str = "gyro"
    attitude: str = "tilt"
    odometry_bias: tuple[str, ...] = ("yaw", "scale")
    detector_process: bool = False
    keyframe_distance: float | None = None
    detector_every: int = DETECTOR_EVERY
    ground: str | None = None

    def __post_init__(self) -> None:
        distance = self.keyframe_distance
        if distance is None:  # the backend's default; frozen: set once, where the settings are made
            distance = KEYFRAME_DISTANCE if self.backend == "graph" else 0.0
            object.__setattr__(self, "keyframe_distance", distance)
        if self.ground is None:
            object.__setattr__(self, "ground", "plane" if self.backend == "graph" else "none")
        for name, value, allowed in (
            ("backend", self.backend, FUSION_BACKENDS),
            ("mode", self.mode, FUSION_MODES),
            ("deskew", self.deskew, DESKEW_SOURCES),
            ("attitude", self.attitude, ATTITUDE_MODES),
            ("ground", self.ground, GROUND_MODES),
        ):
            if value not in allowed:
                raise ValueError(f"fusion.{name} must be one of {allowed}, got {value!r}")
        if not distance >= 0:
            raise ValueError(f"fusion.keyframe_distance is metres, at least 0, not {distance!r}")
        every = self.detector_every
        if isinstance(every, bool) or not isinstance(every, int) or not 1 <= every <= MAX_DETECTOR_EVERY:
            raise ValueError(
                f"fusion.detector_every is a whole number of steps from 1 to {MAX_DETECTOR_EVERY}, not {every!r}"
            )
        if self.ground == "plane" and self.backend != "graph":
            raise ValueError(
                "fusion.ground 'plane' makes the ground under the robot a landmark of the graph, which the EKF "
                "does not keep: use backend graph, or ground none"
            )
        if distance > 0 and self.backend != "graph":
            raise ValueError(
                "fusion.keyframe_distance ties a scan to an earlier keyframe's pose, which the EKF no longer "
                "holds: use backend graph, or keyframe_distance 0"
            )

    def record(self) -> dict[str, Any]:
        """The settings whole, as results.json, sweep.json and a policy evaluation's settings hold them
        (under "fusion")."""
        return {f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v for f in fields(self)}


@dataclass
class EnvConfig:
    """Gymnasium environment options."""

    scene: str = "mine"
    scene_params: dict[str, Any] = field(default_factory=dict)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    route: str = "main"
    range_image_width: int | None = None  # None: the pattern's default
    goal_radius: float = 1.0
    # what ends an episode: the true pose within goal_radius of the goal ("truth"), or the fused
    # estimate, the pose the robot believes ("estimate", with the fusion on): a robot stops where
    # it believes the goal is, within stop_radius of it, and whether it truly arrived (within
    # goal_radius) is info's distance_to_goal. A robot stopping at stop_radius is sure to arrive only
    # while its error stays under goal_radius - stop_radius; 0.25 m is Nav2's default goal tolerance
    arrival: str = "truth"
    stop_radius: float = 0.25
    max_episode_steps: int | None = None  # None: 3x the route length at full speed
    progress_reward: float = 1.0  # per metre of progress to the goal
    step_penalty: float = 0.01
    collision_penalty: float = 0.1
    goal_reward: float = 10.0
    fusion: FusionSettings = field(default_factory=FusionSettings)
