"""A drive recorded once: its scans, odometry, IMU and truth (`DriveRecord`, `record_run`), deskewed
and registered scan to scan (`deskewed`, `register_sequence`)."""

from __future__ import annotations

import json
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import small_gicp
from tqdm import tqdm

from l3e_env.config import DESKEW_SOURCES, EnvConfig, LidarConfig, RobotConfig
from l3e_env.core.files import write_atomic
from l3e_env.core.transforms import inverse
from l3e_env.detection.pipeline import Keyframes, ScanRegistrar
from l3e_env.envs.navigation import NavigationEnv
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.follower import RouteFollower
from l3e_env.sim.imu import StepGyro
from l3e_env.sim.lidar import Scan, deskew, deskew_motion, get_pattern
from scenes import Scene, SceneError, canonical_scene_name, file_sha256, is_mesh_path

STORE_VOXEL = 0.2  # stored scans for ICP are thinned (ICP downsamples to 0.3 m anyway)
CLASSIFIER_POINTS = 4000  # the classifier's input size (ModelConfig.points)


class DriveRecordError(ValueError):
    """A saved drive (recording.npz) that is missing, cut short or not one: the message names the file."""


@dataclass
class DriveRecord:
    scene: str
    sensor: str
    seed: int
    T_b_s: np.ndarray
    ground_truth: np.ndarray  # (N+1, 4, 4) body poses
    odometry: np.ndarray  # (N, 4, 4) increments T_b(k-1)_b(k)
    scans: list[np.ndarray] = field(default_factory=list)  # N+1 scans, sensor frame, thinned for ICP
    # N+1 random subsets of the raw scans, as the classifier samples them (thinned scans have
    # another point density than the raw scans it was trained on)
    samples: list[np.ndarray] = field(default_factory=list)
    # make_scene's keyword arguments (a mesh scene's up axis, scale and route), to rebuild the scene
    scene_params: dict = field(default_factory=dict)
    mesh_sha256: str = ""  # a mesh scene's file, to tell it from an edited or replaced one
    sweep: bool = False  # scans swept over the robot's motion (LidarConfig.sweep), deskewed before they are fused

    def save(self, path: str | Path) -> None:
        """Written whole or not at all (a killed run leaves the file that was there); not compressed
        (docs/decisions.md, "Processes and files")."""
        write_atomic(
            path,
            lambda fh: np.savez(
                fh,
                scene=self.scene,
                sensor=self.sensor,
                seed=self.seed,
                T_b_s=self.T_b_s,
                scene_params=json.dumps(self.scene_params),
                mesh_sha256=self.mesh_sha256,
                sweep=self.sweep,
                ground_truth=self.ground_truth,
                odometry=self.odometry,
                **_ragged("points", self.scans),
                **_ragged("samples", self.samples),
            ),
        )

    @classmethod
    def load(cls, path: str | Path) -> DriveRecord:
        """DriveRecordError naming the file where it is missing, cut short or not a recording."""
        try:
            with np.load(path, allow_pickle=False) as z:
                samples = _unragged(z, "samples") if "samples_offsets" in z.files else []
                params = json.loads(str(z["scene_params"])) if "scene_params" in z.files else {}
                digest = str(z["mesh_sha256"]) if "mesh_sha256" in z.files else ""
                swept = bool(z["sweep"]) if "sweep" in z.files else False
                return cls(
                    str(z["scene"]),
                    str(z["sensor"]),
                    int(z["seed"]),
                    z["T_b_s"],
                    z["ground_truth"],
                    z["odometry"],
                    _unragged(z, "points"),
                    samples,
                    params,
                    digest,
                    swept,
                )
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise DriveRecordError(
                f"{path} cannot be read as a recording ({type(exc).__name__}: {exc}); record the "
                "drive again (l3e ate or l3e record --recording)"
            ) from exc

    def scene_file(self, moved_to: str | None = None) -> str:
        """The scene to rebuild: its name, or for a mesh its recorded path, or `moved_to` where the
        mesh has moved since; SceneError if the mesh is missing or not the recorded one."""
        if not is_mesh_path(self.scene):
            return self.scene
        path = self.scene
        if not Path(path).is_file():
            if moved_to is None or not is_mesh_path(moved_to):
                raise SceneError(
                    f"the recording's mesh {path} is not there: give its new path as the scene "
                    "(l3e ate --recording R --scene NEW_PATH)"
                )
            path = moved_to
        if self.mesh_sha256 and file_sha256(path) != self.mesh_sha256:
            raise SceneError(
                f"{path} is not the mesh this recording was made in (its SHA-256 differs): the "
                "recorded scans would not match its geometry"
            )
        return path

    def detector_input(self, k: int) -> np.ndarray:
        return self.samples[k] if self.samples else self.scans[k]


def _ragged(name: str, arrays: list[np.ndarray]) -> dict[str, Any]:
    lengths = np.array([len(a) for a in arrays], dtype=np.int64)
    flat = np.concatenate(arrays) if arrays else np.zeros((0, 3), np.float32)
    return {name: flat, f"{name}_offsets" if name != "points" else "offsets": np.concatenate([[0], np.cumsum(lengths)])}


def _unragged(z, name: str) -> list[np.ndarray]:
    o, flat = z[f"{name}_offsets" if name != "points" else "offsets"], z[name]
    return [flat[o[i] : o[i + 1]] for i in range(len(o) - 1)]


@dataclass(frozen=True)
class DriveOptions:
    """How a route is driven and recorded: the LiDAR, the drive's seed, make_scene's arguments, whether
    each scan is swept over the step's motion (LidarConfig.sweep), where the drive stops (`max_steps`;
    default: the route's end, or 3x its length at full speed) and how many seconds the robot first
    stands at the start (an IMU initialiser's calibration; counted in `max_steps`)."""

    sensor: str = "vlp16"
    seed: int = 0
    scene_params: dict | None = None
    sweep: bool = False
    max_steps: int | None = None
    still: float = 0.0


class _Tape:
    """A drive's record as it is taken: true and odometry poses, each scan thinned for registration
    (STORE_VOXEL) and sampled for the classifier (CLASSIFIER_POINTS), and the full scans to `on_step`."""

    def __init__(self, seed: int, on_step: Callable[[Scan, dict], None] | None):
        self.gt: list[np.ndarray] = []
        self.odom: list[np.ndarray] = []
        self.scans: list[np.ndarray] = []
        self.samples: list[np.ndarray] = []
        self.sampler, self.on_step = np.random.default_rng([seed, 1]), on_step

    def add(self, env: NavigationEnv, info: dict, previous: np.ndarray | None) -> None:
        self.gt.append(info["T_w_b"])
        if previous is not None:
            self.odom.append(inverse(previous) @ info["odom_T_w_b"])
        points = env.scan.points
        cloud = small_gicp.voxelgrid_sampling(points.astype(np.float64), STORE_VOXEL)
        self.scans.append(np.asarray(cloud.points())[:, :3].astype(np.float32))
        if len(points) > CLASSIFIER_POINTS:
            points = points[self.sampler.choice(len(points), CLASSIFIER_POINTS, replace=False)]
        self.samples.append(points.astype(np.float32))
        if self.on_step is not None:
            self.on_step(env.scan, {**info, "T_b_s": env.robot.T_b_s})


def record_run(
    scene: str = "mine",
    options: DriveOptions | None = None,
    progress: bool = True,
    scene_object: Scene | None = None,
    on_step: Callable[[Scan, dict], None] | None = None,
) -> DriveRecord:
    """Drive the scene's route once; `scene_object`, if given, is that scene already built.
    `on_step(scan, info)` sees every full scan with the step's info (T_w_b, odom_T_w_b) and the
    sensor's mounting T_b_s, the start's included, before the recording thins it (a bag writer)."""
    options = options or DriveOptions()
    standing = int(round(options.still / RobotConfig.dt))
    if standing < 0:
        raise ValueError(f"the robot stands still for 0 s or more, not {options.still} s")
    lidar = LidarConfig(model=options.sensor, sweep=options.sweep)
    config = EnvConfig(
        scene=scene, lidar=lidar, scene_params=options.scene_params or {}, max_episode_steps=options.max_steps
    )
    env = NavigationEnv(config, scene_object=scene_object)
    _, info = env.reset(seed=options.seed)
    follow, tape = RouteFollower(env.route), _Tape(options.seed, on_step)
    tape.add(env, info, None)
    bar = tqdm(total=env.max_steps, desc=f"recording {env.scene.name}", unit="step", disable=not progress)
    done = False
    while not done:
        previous = info["odom_T_w_b"]
        action = np.zeros(3) if standing > 0 else follow(info["T_w_b"])
        standing -= 1
        _, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
        tape.add(env, info, previous)
        bar.update()
    bar.close()
    # a mesh scene is rebuilt from its file, a procedural one from its canonical name ('tunnel' -> 'tunnel-0')
    name = canonical_scene_name(scene) if is_mesh_path(scene) else env.scene.name
    rec = DriveRecord(
        name,
        options.sensor,
        options.seed,
        env.robot.T_b_s,
        np.array(tape.gt),
        np.array(tape.odom),
        tape.scans,
        tape.samples,
        dict(options.scene_params or {}),
        file_sha256(scene) if is_mesh_path(scene) else "",
        options.sweep,
    )
    env.close()
    return rec


def deskewed(rec: DriveRecord, source: str = "gyro") -> DriveRecord:
    """A swept recording's scans and samples put into the sensor frame at each revolution's end, by
    the leg odometry's motion over the last steps (`deskew_motion`; the first revolution was taken
    standing still), its rotation the gyro's where `source` is "gyro": a StepGyro along the drive's
    true poses, drawing from the recording's own seed."""
    if source not in DESKEW_SOURCES:
        raise ValueError(f"deskewing source must be one of {DESKEW_SOURCES}, got {source!r}")
    if not rec.sweep:
        return rec
    pattern = get_pattern(rec.sensor)
    gyro = StepGyro(rng=np.random.default_rng([rec.seed, 4])) if source == "gyro" else None
    motions = [np.eye(4)]
    for k, (before, after) in enumerate(zip(rec.ground_truth, rec.ground_truth[1:])):
        turn = None if gyro is None else gyro.measure(before[:3, :3], after[:3, :3], RobotConfig.dt)
        motions.append(deskew_motion(rec.odometry[: k + 1], turn, mounting=rec.T_b_s))  # the last steps count
    return replace(
        rec,
        scans=[deskew(s, m, pattern) for s, m in zip(rec.scans, motions)],
        samples=[deskew(s, m, pattern) for s, m in zip(rec.samples, motions)],
    )


class RegisteredSteps(list):
    """A drive's registrations, one a step (scan k into pose k, k >= 1; None where impossible), and
    the first scan's ground plane (n, d in its sensor frame; None where none was found), which the
    fusion's ground takes at the start."""

    start_ground: np.ndarray | None = None

    def first(self, steps: int) -> RegisteredSteps:
        """The first `steps` registrations with the first scan's ground (a list slice drops it)."""
        part = RegisteredSteps(self[:steps])
        part.start_ground = self.start_ground
        return part


def register_sequence(
    rec: DriveRecord, config: RegistrationConfig, progress: bool = True, keyframes: Keyframes | None = None
) -> RegisteredSteps:
    """Scan k registered to scan k-1 from identity, or onto a keyframe from the leg odometry's guess
    (`keyframes`), as the pipeline's `ScanRegistrar` does on line; None where registration is
    impossible. Registered once, the steps serve every detector's fusion."""
    registrar = ScanRegistrar(config, keyframes=keyframes)
    results = RegisteredSteps()
    T_s_b = inverse(rec.T_b_s)
    for k, scan in enumerate(tqdm(rec.scans, desc="registering scans", unit="scan", disable=not progress)):
        if k == 0:
            registrar.start(scan)
            results.start_ground = registrar.first_ground(scan)
        else:
            results.append(registrar.next(scan, T_s_b @ rec.odometry[k - 1] @ rec.T_b_s))  # into pose k
    return results
