"""Record a drive once, then fuse it with every detector: ATE/RPE tables, plots and maps.

`record_run` drives a scene's route with the route follower and keeps, per step, the scan, the
leg-odometry increment and the ground truth. `run_ate` registers consecutive scans once (the
one registration), asks each detector for a mask, fuses odometry and masked ICP in the iSAM2
graph, and measures against ground truth. A saved recording can be evaluated again with new
detectors without driving.
"""

from __future__ import annotations

import json
import re
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import small_gicp
from tqdm import tqdm

from fusion import (
    FusionConfig,
    MetricError,
    ate,
    ate_aligned,
    check_backend,
    rpe,
    stretch_drift,
    write_kitti,
    write_tum,
)
from l3e_env.config import DESKEW_SOURCES, EnvConfig, FusionSettings, LidarConfig, OdometryConfig, RobotConfig, to_dict
from l3e_env.core.files import write_atomic
from l3e_env.core.transforms import inverse
from l3e_env.core.workers import ordered_map
from l3e_env.detection.detectors import (
    UNKNOWN,
    CascadeDetector,
    Detector,
    Prediction,
    ScanMCDetector,
    make_detector,
    registration_of,
)
from l3e_env.detection.pipeline import LocalizationPipeline, ScanRegistrar
from l3e_env.envs.navigation import NavigationEnv
from l3e_env.localizability.labels import AXES
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.follower import RouteFollower
from l3e_env.sim.imu import StepGyro, attitude_readings, attitude_sigmas
from l3e_env.sim.lidar import Lidar, Scan, deskew, deskew_motion, get_pattern
from l3e_env.sim.odometry import odometry_fusion_config
from l3e_env.sim.raycast import EmbreeCaster
from scenes import Scene, SceneError, canonical_scene_name, file_sha256, is_mesh_path, make_scene

from .baselines import BASELINES, BaselineRun, check_baselines, run_baseline

STORE_VOXEL = 0.2  # stored scans for ICP are thinned (ICP downsamples to 0.3 m anyway)
CLASSIFIER_POINTS = 4000  # the classifier's input size (ModelConfig.points)


class RecordingError(ValueError):
    """A recording.npz that is missing, cut short or not a recording: the message names the file."""


@dataclass
class Recording:
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
        """Written whole or not at all (a killed run leaves the file that was there)."""
        write_atomic(
            path,
            lambda fh: np.savez_compressed(
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
    def load(cls, path: str | Path) -> Recording:
        """RecordingError naming the file where it is missing, cut short or not a recording."""
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
            raise RecordingError(
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


class RecastScans:
    """The scan estimate (scanmc), in a replay. It meshes every return of a revolution, and a
    recording keeps thinned scans, so the scan is cast again from the scene at the recorded true
    sensor pose: the same scene, sensor and pose, another draw of the range noise and dropout. It
    is judged every `stride` steps and held between, as the oracle is, since a judgement costs up
    to M registrations (about 2 s at M = 60). Each judged step draws its scan and children from its
    own seed, so `judge_ahead` can judge a whole route in several processes first."""

    def __init__(self, detector: ScanMCDetector, lidar: Lidar, stride: int = 5, seed: int = 0):
        if stride < 1:
            raise ValueError(f"a detector is judged every stride >= 1 steps, got {stride}")
        self.detector, self.lidar, self.stride, self.seed = detector, lidar, stride, seed
        self.name = detector.name
        self._calls, self._last, self._ahead = 0, UNKNOWN, {}

    def judge_step(self, step: int, T_w_s: np.ndarray) -> Prediction:
        scan = self.lidar.scan(T_w_s, np.random.default_rng([self.seed, 2, step]))
        return self.detector.judge(scan.points, np.random.default_rng([self.seed, 3, step]))

    def judgement(self, step: int, T_w_s: np.ndarray) -> Prediction:
        """The step's judgement: the one made ahead, or made now."""
        return self._ahead.pop(step, None) or self.judge_step(step, T_w_s)

    def judge_ahead(
        self, poses: list[np.ndarray], scene: Scene, workers: int, progress: bool = True, steps: list[int] | None = None
    ) -> None:
        """Judge the steps that `predict` will be asked for (every `stride`-th, or `steps`), T_w_s of
        call k being poses[k]."""
        steps = list(range(0, len(poses), self.stride)) if steps is None else steps
        jobs = [(k, poses[k]) for k in steps]
        judged = list(
            tqdm(
                ordered_map(_judge_recast_step, jobs, self, _recast_on, (self, scene.mesh), workers),
                total=len(jobs),
                disable=not progress,
                desc=f"judging with {self.name} ({workers} workers)",
                unit="scan",
            )
        )
        self._ahead = dict(zip(steps, judged))

    def __getstate__(self) -> dict:  # a worker gets the settings, and casts against its own scene
        return {**self.__dict__, "lidar": self.lidar.config, "_ahead": {}}

    def predict(self, points: np.ndarray, registration=None, T_w_s: np.ndarray | None = None) -> Prediction:
        if T_w_s is None:
            raise ValueError(f"{self.name} in a replay casts the scan again at the true sensor pose: give T_w_s")
        try:
            if self._calls % self.stride == 0:
                self._last = UNKNOWN  # a judgement that raises is not held over the next steps
                self._last = self.judgement(self._calls, T_w_s)
            return self._last
        finally:
            self._calls += 1


class RecastCascade:
    """learned+scanmc in a replay: the classifier reads the recorded samples, and where it is unsure
    the estimate judges the scan cast again at the true pose (RecastScans). At most one judgement
    per `stride` steps, as the estimate alone has: the first unsure step of each block of `stride`
    steps is judged, and its judgement serves the block's later unsure steps."""

    def __init__(self, cascade: CascadeDetector, lidar: Lidar, stride: int = 5, seed: int = 0):
        self.cascade, self.recast = cascade, RecastScans(cascade.scan_mc, lidar, stride, seed)
        self.name = cascade.name
        self._calls, self._held = 0, {}
        self._classified: dict[int, tuple[Prediction, bool]] = {}  # by judge_ahead, for predict to take

    def predict(self, points: np.ndarray, registration=None, T_w_s: np.ndarray | None = None) -> Prediction:
        if T_w_s is None:
            raise ValueError(f"{self.name} in a replay casts the scan again at the true sensor pose: give T_w_s")
        step, self._calls = self._calls, self._calls + 1
        self.cascade.calls += 1
        first, unsure = self._classified.pop(step, None) or self.cascade.classify(points, T_w_s)
        if not unsure:
            return first
        self.cascade.checked += 1
        block = step // self.recast.stride
        if block not in self._held:
            self._held[block] = self.recast.judgement(step, T_w_s)
        return self._held[block]

    @property
    def judged_steps(self) -> int:
        """Scans the estimate has judged (one per block with an unsure step)."""
        return len(self._held)

    def judge_ahead(
        self, samples: list[np.ndarray], poses: list[np.ndarray], scene: Scene, workers: int, progress: bool = True
    ) -> None:
        """Judge the steps that `predict` will ask the estimate for, the samples and T_w_s of call k
        being samples[k] and poses[k]."""
        self._classified = {k: self.cascade.classify(points, T) for k, (points, T) in enumerate(zip(samples, poses))}
        first_unsure: dict[int, int] = {}
        for k, (_, unsure) in self._classified.items():
            if unsure:
                first_unsure.setdefault(k // self.recast.stride, k)
        self.recast.judge_ahead(poses, scene, workers, progress, steps=list(first_unsure.values()))


def _recast_on(recast: RecastScans, mesh) -> RecastScans:
    """A worker's own copy, with a LiDAR on its own copy of the scene."""
    recast.lidar = Lidar(EmbreeCaster(mesh, threads=1), recast.lidar)
    return recast


def _judge_recast_step(recast: RecastScans, job: tuple[int, np.ndarray]) -> Prediction:
    return recast.judge_step(*job)


def _ragged(name: str, arrays: list[np.ndarray]) -> dict[str, np.ndarray]:
    lengths = np.array([len(a) for a in arrays], dtype=np.int64)
    flat = np.concatenate(arrays) if arrays else np.zeros((0, 3), np.float32)
    return {name: flat, f"{name}_offsets" if name != "points" else "offsets": np.concatenate([[0], np.cumsum(lengths)])}


def _unragged(z, name: str) -> list[np.ndarray]:
    o, flat = z[f"{name}_offsets" if name != "points" else "offsets"], z[name]
    return [flat[o[i] : o[i + 1]] for i in range(len(o) - 1)]


def record_run(
    scene: str = "mine",
    sensor: str = "vlp16",
    seed: int = 0,
    progress: bool = True,
    scene_params: dict | None = None,
    scene_object: Scene | None = None,
    on_step: Callable[[Scan, dict], None] | None = None,
    sweep: bool = False,
    max_steps: int | None = None,
    still: float = 0.0,
) -> Recording:
    """Drive the scene's route once; `scene_object`, if given, is that scene already built.
    `on_step(scan, info)` sees every full scan with the step's info (T_w_b, odom_T_w_b) and the
    sensor's mounting T_b_s, the start's included, before the recording thins it (a bag writer).
    `sweep`: each step's scan is swept over the step's motion (LidarConfig.sweep). `max_steps`: stop the
    drive there (a short run; default: the route's end, or 3x its length at full speed). `still`: seconds
    the robot first stands at the start (an IMU initialiser's calibration), counted in `max_steps`."""
    env = NavigationEnv(
        EnvConfig(
            scene=scene,
            lidar=LidarConfig(model=sensor, sweep=sweep),
            scene_params=scene_params or {},
            max_episode_steps=max_steps,
        ),
        scene_object=scene_object,
    )
    obs, info = env.reset(seed=seed)
    follow = RouteFollower(env.route)

    def thin(points: np.ndarray) -> np.ndarray:
        cloud = small_gicp.voxelgrid_sampling(points.astype(np.float64), STORE_VOXEL)
        return np.asarray(cloud.points())[:, :3].astype(np.float32)

    sampler = np.random.default_rng([seed, 1])

    def sample(points: np.ndarray) -> np.ndarray:
        if len(points) > CLASSIFIER_POINTS:
            points = points[sampler.choice(len(points), CLASSIFIER_POINTS, replace=False)]
        return points.astype(np.float32)

    gt, odom, scans, samples = [info["T_w_b"]], [], [thin(env.scan.points)], [sample(env.scan.points)]
    if on_step is not None:
        on_step(env.scan, {**info, "T_b_s": env.robot.T_b_s})
    bar = tqdm(total=env.max_steps, desc=f"recording {env.scene.name}", unit="step", disable=not progress)
    done, standing = False, int(round(still / RobotConfig.dt))
    if standing < 0:
        raise ValueError(f"the robot stands still for 0 s or more, not {still} s")
    while not done:
        prev_odom = info["odom_T_w_b"]
        action = np.zeros(3) if standing > 0 else follow(info["T_w_b"])
        standing -= 1
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
        gt.append(info["T_w_b"])
        odom.append(inverse(prev_odom) @ info["odom_T_w_b"])
        scans.append(thin(env.scan.points))
        samples.append(sample(env.scan.points))
        if on_step is not None:
            on_step(env.scan, {**info, "T_b_s": env.robot.T_b_s})
        bar.update()
    bar.close()
    # a mesh scene is rebuilt from its file, a procedural one from its canonical name ('tunnel' -> 'tunnel-0')
    name = canonical_scene_name(scene) if is_mesh_path(scene) else env.scene.name
    rec = Recording(
        name,
        sensor,
        seed,
        env.robot.T_b_s,
        np.array(gt),
        np.array(odom),
        scans,
        samples,
        dict(scene_params or {}),
        file_sha256(scene) if is_mesh_path(scene) else "",
        sweep,
    )
    env.close()
    return rec


@dataclass
class DetectorResult:
    name: str
    trajectory: np.ndarray
    masks: np.ndarray  # (N, 6) bool
    probabilities: np.ndarray  # (N, 6)
    ate: float
    ate_aligned: float | None
    rpe_translation: float
    rpe_rotation: float
    seconds: float
    unknown_steps: int
    fallback_steps: int
    detector_errors: int = 0

    def row(self) -> dict:
        flagged = self.masks.mean(axis=0)
        return {
            "detector": self.name,
            "ate_m": round(self.ate, 3),
            "ate_aligned_m": None if self.ate_aligned is None else round(self.ate_aligned, 3),
            "rpe_m": round(self.rpe_translation, 4),
            "rpe_deg": round(float(np.degrees(self.rpe_rotation)), 3),
            **{f"flagged_{a}": round(float(f), 3) for a, f in zip(AXES, flagged)},
            "seconds": round(self.seconds, 2),
            "unknown_steps": self.unknown_steps,
            "fallback_steps": self.fallback_steps,
            "detector_errors": self.detector_errors,
        }


def deskewed(rec: Recording, source: str = "gyro") -> Recording:
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


def register_sequence(rec: Recording, config: RegistrationConfig, progress: bool = True) -> list:
    """Scan k registered to scan k-1 from identity, as the pipeline's `ScanRegistrar` does on line; None
    where registration is impossible. Registered once, the steps serve every detector's fusion."""
    registrar = ScanRegistrar(config)
    results = []
    for k, scan in enumerate(tqdm(rec.scans, desc="registering scans", unit="scan", disable=not progress)):
        if k == 0:
            registrar.start(scan)
        else:
            results.append(registrar.next(scan))
    return results


class OdometryAttitude:
    """The odometry fused with the IMU's attitude alone: every ICP axis masked, for the reference
    row against which the detectors' rows show what the scans add to the IMU."""

    name = "odometry + attitude"

    def predict(self, points: np.ndarray, registration=None, T_w_s: np.ndarray | None = None) -> Prediction:
        return Prediction(np.ones(6), np.ones(6, dtype=bool))


def fuse_recording(
    rec: Recording,
    detectors: list[Detector],
    registrations: list,
    fusion: FusionConfig | None = None,
    odometry: OdometryConfig | None = None,
    progress: bool = True,
    backend: str = "graph",
    attitude: str = "none",
) -> list[DetectorResult]:
    """The recording's odometry and registrations through the localization pipeline with each
    detector; with `attitude` ("tilt" or "full", see `imu.attitude_sigmas`) the IMU's orientation joins
    every ATTITUDE_EVERY steps, the same readings for every detector (drawn from the recording's seed)."""
    check_backend(backend)
    fusion, odometry = fusion or FusionConfig(), odometry or OdometryConfig()
    gt = rec.ground_truth
    readings = (
        None
        if attitude_sigmas(attitude) is None
        else attitude_readings(gt, RobotConfig.dt, rng=np.random.default_rng([rec.seed, 5]))
    )
    out = []
    for det in detectors:
        t0 = time.perf_counter()
        pipeline = LocalizationPipeline(det, backend, fusion, odometry, rec.T_b_s, attitude)
        pipeline.start(gt[0])
        masks, probs, unknown, fallbacks, errors = [], [], 0, 0, 0
        for k, reg in enumerate(tqdm(registrations, desc=f"fusing with {det.name}", unit="step", disable=not progress)):
            step = pipeline.step(
                rec.odometry[k],
                reg,
                rec.detector_input(k + 1),
                gt[k + 1] @ rec.T_b_s,
                None if readings is None else readings[k + 1],
            )
            unknown += not step.prediction.known
            errors += step.detector_failed
            fallbacks += step.fallback
            masks.append(step.prediction.mask)
            probs.append(step.prediction.probabilities)
        out.append(
            _scored(
                det.name,
                pipeline.trajectory(),
                gt,
                np.array(masks),
                np.array(probs),
                time.perf_counter() - t0,
                unknown,
                fallbacks,
                errors,
            )
        )
    return out


def odometry_only(rec: Recording) -> DetectorResult:
    traj = [rec.ground_truth[0]]
    for inc in rec.odometry:
        traj.append(traj[-1] @ inc)
    n = len(rec.odometry)
    return _scored("odometry only", np.array(traj), rec.ground_truth, np.ones((n, 6), bool), np.ones((n, 6)), 0.0, 0, 0)


def _scored(
    name: str,
    traj: np.ndarray,
    gt: np.ndarray,
    masks: np.ndarray,
    probs: np.ndarray,
    seconds: float,
    unknown: int,
    fallbacks: int,
    errors: int = 0,
) -> DetectorResult:
    """A trajectory with its metrics against ground truth (aligned ATE is None for colinear runs)."""
    try:
        aligned = ate_aligned(traj, gt)
    except MetricError:
        aligned = None
    rt, rr = rpe(traj, gt, delta=min(10, len(gt) - 1))
    return DetectorResult(name, traj, masks, probs, ate(traj, gt), aligned, rt, rr, seconds, unknown, fallbacks, errors)


@dataclass
class AteRun:
    """One drive fused with every detector: the table's rows (odometry only first) and what was written."""

    out_dir: Path
    rows: list[dict]
    swept: bool  # the drive's scans were swept revolutions, deskewed before they were judged and registered
    written: list[Path]

    def table(self) -> str:
        return format_table(self.rows)


@dataclass
class AteSeeds:
    """Drives of several seeds: each drive's run, the summary over them per detector, what was written."""

    out_dir: Path
    runs: dict[int, AteRun]
    summary: list[dict]
    written: list[Path]

    def table(self) -> str:
        return format_seed_table(self.summary)


@dataclass
class AteOptions:
    """How `l3e ate` drives and fuses.

    sensor, seed: the drive's LiDAR and seed. recording: a saved drive to fuse again (its own scene is
    used; the scene given matters only as the new path of a recorded mesh that has moved).
    scene_params: make_scene's arguments (a mesh scene's up axis, scale and route). workers: processes
    that judge the route with scanmc before the fusion (the same judgements as one). deskew: where a
    swept recording's deskewing takes its rotation from (config.DESKEW_SOURCES). attitude: the
    IMU's orientation in the fusion ("none", "tilt" or "full"); with it, a row "odometry + attitude"
    follows odometry alone. fusion_settings: every fusion's (the biases' prior from the default
    OdometryConfig, as the drive's). max_steps: a shorter drive. baselines: external LiDAR odometries
    (experiments.baselines: kiss-icp, genz-icp) run on the drive's scans as recorded (a swept drive's
    with their firing times, which they deskew themselves), each a row after the fusion's; their
    settings go into results.json, and one that fails says so in its row. frontends: the LiDAR front
    ends whose steps the fusion takes ("icp": scan-to-scan ICP; or a baseline's name: its relative
    motions with the ICP's information, BaselineRun.registrations); every detector is fused with each,
    the rows of a front end other than ICP named "<detector> @<front end>"."""

    sensor: str = "vlp16"
    seed: int = 0
    recording: str | Path | None = None
    backend: str = "graph"
    scene_params: dict | None = None
    workers: int = 1
    deskew: str = "gyro"
    attitude: str = "none"
    fusion_settings: FusionSettings = FusionSettings()
    max_steps: int | None = None
    baselines: list[str] = field(default_factory=list)
    frontends: list[str] = field(default_factory=lambda: ["icp"])

    def check(self) -> None:
        """ValueError naming a setting no drive can use (and a missing baseline package), before the drive."""
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")
        if self.deskew not in DESKEW_SOURCES:
            raise ValueError(f"deskew must be one of {DESKEW_SOURCES}, got {self.deskew!r}")
        attitude_sigmas(self.attitude)
        if not self.frontends or any(f != "icp" and f not in BASELINES for f in self.frontends):
            raise ValueError(f"front ends: icp or one of {', '.join(BASELINES)}, got {self.frontends}")
        check_baselines([*self.baselines, *(f for f in self.frontends if f != "icp")])


def run_ate_seeds(
    out_dir: str | Path,
    scene: str,
    detectors: list[str],
    seeds: range,
    options: AteOptions | None = None,
    on_drive: Callable[[int, AteRun], None] | None = None,
    progress: bool = True,
) -> AteSeeds:
    """`run_ate` on one drive per seed, each into `out_dir/seed-<seed>`, then the summary over them
    (`summarize_seeds`) into seeds.json and seeds.png; `on_drive(seed, run)` sees each drive as it ends.
    `options`: run_ate's (not a recording: that is one drive; their seed is each drive's)."""
    options = options or AteOptions()
    if len(seeds) < 1:
        raise ValueError("give one seed or more")
    if options.recording:
        raise ValueError("a recording is one drive: drive several seeds without it")
    out = Path(out_dir)
    runs = {}
    for seed in seeds:
        runs[seed] = run_ate(out / f"seed-{seed}", scene, detectors, replace(options, seed=seed), progress)
        if on_drive is not None:
            on_drive(seed, runs[seed])
    summary = summarize_seeds({seed: run.rows for seed, run in runs.items()})
    (out / "seeds.json").write_text(json.dumps(summary, indent=1))
    from .ate_plots import plot_seeds

    plot_seeds(out / "seeds.png", summary)
    return AteSeeds(out, runs, summary, [out / "seeds.json", out / "seeds.png"])


@dataclass
class AteDrive:
    """One drive's inputs: the scene, its LiDAR, the recording (deskewed where swept, `raw` as
    recorded) and the detectors (made for it)."""

    scene: Scene
    lidar: Lidar
    rec: Recording
    raw: Recording
    detectors: list[Detector]
    registration: RegistrationConfig


def run_ate(
    out_dir: str | Path, scene: str, detectors: list[str], options: AteOptions | None = None, progress: bool = True
) -> AteRun:
    """The `l3e ate` command as a function: drives (or loads) the route, registers its scans, fuses
    them with every detector and front end, scores each row against the truth and writes everything
    to out_dir; returns the rows."""
    options = options or AteOptions()
    options.check()
    fusion = odometry_fusion_config(OdometryConfig(), options.fusion_settings)
    out = Path(out_dir)
    drive = prepare_drive(out, scene, detectors, options, progress)
    t0 = time.perf_counter()
    regs = register_sequence(drive.rec, drive.registration, progress)
    icp_seconds = time.perf_counter() - t0
    ahead = judge_ahead(drive, options.workers, progress)
    dets = drive.detectors
    if options.attitude != "none":
        dets, ahead = [OdometryAttitude(), *dets], [0.0, *ahead]
    runs = {
        name: run_baseline(
            name,
            drive.raw.scans,
            drive.raw.ground_truth[0],
            drive.raw.T_b_s,
            get_pattern(drive.raw.sensor) if drive.raw.sweep else None,
            progress=progress,
        )
        for name in dict.fromkeys([*(f for f in options.frontends if f != "icp"), *options.baselines])
    }
    fused, lost = fuse_frontends(drive.rec, dets, ahead, regs, runs, fusion, options, progress)
    results, rows = score_rows(drive, dets, fused, lost, runs, options)
    summary = {
        "scene": drive.rec.scene,
        "sensor": drive.rec.sensor,
        "seed": drive.rec.seed,
        "swept": drive.raw.sweep,
        "deskew": options.deskew if drive.raw.sweep else None,
        "backend": options.backend,
        "attitude": options.attitude,
        **options.fusion_settings.record(),
        "steps": len(drive.rec.odometry),
        "icp_seconds": round(icp_seconds, 1),
        "icp_failed_or_not_converged": sum(r is None or not r.converged for r in regs),
        "registration": to_dict(drive.registration),
        "frontends": options.frontends,
        "baselines": {
            name: {"config": run.config, "seconds": round(run.seconds, 2), "error": run.error}
            for name, run in runs.items()
        },
        "rows": rows,
    }
    written = write_ate(out, summary, drive, results)
    return AteRun(out, rows, drive.raw.sweep, written)


def prepare_drive(out: Path, scene: str, specs: list[str], options: AteOptions, progress: bool) -> AteDrive:
    """The scene (a recording's own, or `scene`), its LiDAR and the detectors (a bad spec fails before
    the drive), then the drive itself, recorded into out/recording.npz where none was given."""
    rec = Recording.load(options.recording) if options.recording else None
    scene_obj = (
        make_scene(rec.scene_file(moved_to=scene), **rec.scene_params)
        if rec
        else make_scene(scene, **(options.scene_params or {}))
    )
    lidar = Lidar(EmbreeCaster(scene_obj.mesh), LidarConfig(model=rec.sensor if rec else options.sensor))
    dets = [make_detector(spec, lidar, options.seed) for spec in specs]
    registration = registration_of(dets)
    dets = [
        RecastScans(d, lidar, seed=options.seed)
        if isinstance(d, ScanMCDetector)
        else RecastCascade(d, lidar, seed=options.seed)
        if isinstance(d, CascadeDetector)
        else d
        for d in dets
    ]
    out.mkdir(parents=True, exist_ok=True)
    if rec is None:
        rec = record_run(
            scene,
            options.sensor,
            options.seed,
            progress,
            options.scene_params,
            scene_object=scene_obj,
            max_steps=options.max_steps,
        )
        rec.save(out / "recording.npz")
    return AteDrive(scene_obj, lidar, deskewed(rec, options.deskew), rec, dets, registration)


def judge_ahead(drive: AteDrive, workers: int, progress: bool) -> list[float]:
    """The scan estimates of the route judged over `workers` processes before the fusion; returns the
    seconds each detector spent so (counted in its time)."""
    ahead = [0.0] * len(drive.detectors)
    poses = [T @ drive.rec.T_b_s for T in drive.rec.ground_truth[1:]]  # call k of the fusion is at scan k + 1's pose
    for i, det in enumerate(drive.detectors):
        t0 = time.perf_counter()
        if isinstance(det, RecastScans) and workers > 1:
            det.judge_ahead(poses, drive.scene, workers, progress)
        elif isinstance(det, RecastCascade) and workers > 1:
            det.judge_ahead(
                [drive.rec.detector_input(k + 1) for k in range(len(poses))], poses, drive.scene, workers, progress
            )
        ahead[i] = time.perf_counter() - t0
    return ahead


def fuse_frontends(
    rec: Recording,
    dets: list,
    ahead: list[float],
    regs: list,
    runs: dict[str, BaselineRun],
    fusion: FusionConfig,
    options: AteOptions,
    progress: bool,
) -> tuple[list, list[tuple[str, str]]]:
    """Every detector fused with every front end's steps; returns the results and, for a front end
    whose odometry failed, its rows' names with the error."""
    fused, lost = [], []
    for frontend in options.frontends:
        if frontend != "icp" and runs[frontend].error is not None:
            lost += [(f"{det.name} @{frontend}", runs[frontend].error) for det in dets]
            continue
        steps = regs if frontend == "icp" else runs[frontend].registrations(regs)
        by_front = fuse_recording(
            rec, dets, steps, fusion=fusion, progress=progress, backend=options.backend, attitude=options.attitude
        )
        for result, seconds, det in zip(by_front, ahead, dets):
            result.seconds += seconds
            result.name = det.name if frontend == "icp" else f"{det.name} @{frontend}"
        fused += by_front
    return fused, lost


def score_rows(
    drive: AteDrive,
    dets: list,
    fused: list,
    lost: list[tuple[str, str]],
    runs: dict[str, BaselineRun],
    options: AteOptions,
) -> tuple[list, list[dict]]:
    """The results (odometry only first, the fusions, the baselines alone) and the table's rows with
    each one's drift inside each named region; a failed row says why."""
    rec, scene = drive.rec, drive.scene
    results = [odometry_only(rec)] + fused
    inside = regions_inside(rec.ground_truth, scene)
    rows = [{**r.row(), **region_drift(r.trajectory, rec.ground_truth, inside)} for r in results]
    for det, row in zip(dets * len(options.frontends), rows[1:]):
        if isinstance(det, RecastCascade):  # what the estimate cost it: steps it was asked, scans it judged
            row.update(checked_steps=det.cascade.checked, judged_steps=det.judged_steps)
    rows += [failed_row(name, error, scene) for name, error in lost]
    for name in options.baselines:
        run = runs[name]
        if run.error is not None:
            rows.append(failed_row(name, run.error, scene))
            continue
        steps = len(rec.odometry)
        results.append(
            _scored(
                name,
                run.trajectory,
                rec.ground_truth,
                np.zeros((steps, 6), bool),
                np.full((steps, 6), np.nan),
                run.seconds,
                0,
                0,
            )
        )
        rows.append({**results[-1].row(), **region_drift(run.trajectory, rec.ground_truth, inside)})
    return results, rows


def write_ate(out: Path, summary: dict, drive: AteDrive, results: list) -> list[Path]:
    """results.json, the trajectories' and timeline's plots, a map per row and the trajectories as
    files; returns what was written (the recording first, where the drive made one)."""
    (out / "results.json").write_text(json.dumps(summary, indent=1))
    from .ate_plots import plot_map, plot_timeline, plot_trajectories

    plot_trajectories(out / "trajectories.png", drive.scene, drive.rec, results)
    plot_timeline(out / "timeline.png", results[1:])
    maps = []
    for r in results[1:]:
        maps += plot_map(out / f"map_{file_stem(r.name)}", drive.rec, r.trajectory)
    written = [
        out / "results.json",
        out / "trajectories.png",
        out / "timeline.png",
        *maps,
        *write_trajectories(out / "trajectories", drive.rec.ground_truth, results),
    ]
    if (out / "recording.npz").exists():
        written.insert(0, out / "recording.npz")
    return written


def regions_inside(ground_truth: np.ndarray, scene: Scene) -> dict[str, np.ndarray]:
    """Per named region of the scene (the mine's yard, tunnel and quarry), which poses of the drive
    lie inside it (N,): found once a drive, for every row's region_drift."""
    where = [scene.region_of(p) for p in ground_truth[:, :2, 3]]
    return {region: np.array([w == region for w in where]) for region in scene.regions}


def region_drift(trajectory: np.ndarray, ground_truth: np.ndarray, inside: dict[str, np.ndarray]) -> dict:
    """Per region (`regions_inside`): the error the estimate accumulated while the robot was inside it
    (fusion.stretch_drift), in metres and in % of the true distance travelled there; as row fields
    drift_<region>_m and drift_<region>_pct (None where the drive did not move inside the region)."""
    out: dict[str, float | None] = {}
    for region, poses in inside.items():
        drift, distance = stretch_drift(trajectory, ground_truth, poses)
        out[f"drift_{region}_m"] = round(drift, 3) if distance > 0 else None
        out[f"drift_{region}_pct"] = round(100 * drift / distance, 2) if distance > 0 else None
    return out


def failed_row(name: str, error: str, scene: Scene) -> dict:
    """The row of an estimate that could not be made: its name and why, every figure None."""
    keys = (
        "ate_m",
        "ate_aligned_m",
        "rpe_m",
        "rpe_deg",
        *(f"flagged_{a}" for a in AXES),
        "seconds",
        *(f"drift_{g}_{u}" for g in scene.regions for u in ("m", "pct")),
    )
    return {
        "detector": name,
        **dict.fromkeys(keys),
        "unknown_steps": 0,
        "fallback_steps": 0,
        "detector_errors": 0,
        "error": error,
    }


def regions_of(rows: list[dict]) -> list[str]:
    """The regions whose drift the rows carry, in order."""
    return (
        [k[len("drift_") : -len("_m")] for k in rows[0] if k.startswith("drift_") and k.endswith("_m")] if rows else []
    )


def write_trajectories(folder: Path, ground_truth: np.ndarray, results: list[DetectorResult]) -> list[Path]:
    """The ground truth and each row's estimate of the body's pose, in TUM (times from the drive's start)
    and KITTI files, so that evo_ape and other tools read them: `evo_ape tum ground_truth.tum learned.tum`."""
    folder.mkdir(parents=True, exist_ok=True)
    stamps = np.arange(len(ground_truth)) * RobotConfig.dt
    written = []
    for stem, poses in [("ground_truth", ground_truth), *((file_stem(r.name), r.trajectory) for r in results)]:
        write_tum(folder / f"{stem}.tum", stamps, poses)
        write_kitti(folder / f"{stem}.kitti", poses)
        written += [folder / f"{stem}.tum", folder / f"{stem}.kitti"]
    return written


def file_stem(detector_name: str) -> str:
    """A detector's name as a file name: 'learned:runs/a/model.pt' names a path, not a folder."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", detector_name).strip("_")


def summarize_seeds(runs: dict[int, list[dict]]) -> list[dict]:
    """Per detector, over drives of several seeds: ATE and aligned ATE as mean, standard deviation
    and range, and the ATE against odometry alone on the same drive, which cancels most of one
    drive's luck (the odometry's noise decides much of the drift of every detector); and the mean drift
    in each region of the scene (region_drift)."""
    seeds = sorted(runs)
    names = [r["detector"] for r in runs[seeds[0]]]
    if any([r["detector"] for r in runs[k]] != names for k in seeds):
        raise ValueError("every seed's drive must be fused with the same detectors")
    if names[0] != "odometry only":
        raise ValueError("each drive's rows start with odometry only, as run_ate returns them")
    summary = []
    regions = regions_of(runs[seeds[0]])
    for i, name in enumerate(names):
        drifts = {}
        for g in regions:  # the mean over the drives that moved inside the region
            for unit in ("m", "pct"):
                values = [runs[k][i][f"drift_{g}_{unit}"] for k in seeds if runs[k][i][f"drift_{g}_{unit}"] is not None]
                drifts[f"drift_{g}_{unit}_mean"] = round(float(np.mean(values)), 3) if values else None
        ate = np.array([runs[k][i]["ate_m"] for k in seeds], dtype=float)  # NaN where an estimate failed
        aligned = np.array([runs[k][i]["ate_aligned_m"] for k in seeds], dtype=float)
        ratio = ate / np.array([runs[k][0]["ate_m"] for k in seeds])  # row 0: odometry only
        summary.append(
            {
                "detector": name,
                "seeds": seeds,
                "ate_m": ate.tolist(),
                "ate_mean_m": round(float(ate.mean()), 3),
                "ate_std_m": round(float(ate.std(ddof=1)), 3),
                "ate_min_m": float(ate.min()),
                "ate_max_m": float(ate.max()),
                "ate_aligned_mean_m": round(float(np.nanmean(aligned)), 3),
                "ate_over_odometry_mean": round(float(ratio.mean()), 3),
                "ate_over_odometry_std": round(float(ratio.std(ddof=1)), 3),
                **drifts,
            }
        )
    return summary


def format_seed_table(summary: list[dict]) -> str:
    w = _name_width(summary)
    regions = [k[len("drift_") : -len("_pct_mean")] for k in summary[0] if k.endswith("_pct_mean")]
    head = (
        f"{'detector':{w}s} {'ATE m mean':>10s} {'std':>6s} {'min':>7s} {'max':>7s} {'aligned':>8s}  "
        f"{'ATE / odometry':>14s}" + "".join(f"  {'drift ' + g + ' %':>14s}" for g in regions)
    )
    lines = [
        f"over {len(summary[0]['seeds'])} drives (seeds {summary[0]['seeds'][0]}-{summary[0]['seeds'][-1]})",
        head,
        "-" * len(head),
    ]
    for r in summary:
        lines.append(
            f"{r['detector']:{w}s} {r['ate_mean_m']:10.3f} {r['ate_std_m']:6.3f} {r['ate_min_m']:7.3f} "
            f"{r['ate_max_m']:7.3f} {r['ate_aligned_mean_m']:8.3f}  "
            f"{r['ate_over_odometry_mean']:7.3f} +-{r['ate_over_odometry_std']:.3f}"
            + "".join(
                f"  {'-':>14s}" if r[f"drift_{g}_pct_mean"] is None else f"  {r[f'drift_{g}_pct_mean']:14.1f}"
                for g in regions
            )
        )
    return "\n".join(lines)


def _name_width(rows: list[dict]) -> int:
    """The detector column's width: the longest name, at least 14 characters."""
    return max([14, *(len(r["detector"]) for r in rows)])


def format_table(rows: list[dict]) -> str:
    """The ATE table; with regions, a column per region of the drift accumulated there (m and % of the
    distance travelled inside it)."""
    w = _name_width(rows)
    regions = regions_of(rows)
    head = (
        f"{'detector':{w}s} {'ATE m':>7s} {'aligned':>8s} {'RPE m':>7s} {'RPE deg':>8s}  "
        f"flagged x/y/z/roll/pitch/yaw      {'s':>6s}" + "".join(f"  {'drift ' + g:>15s}" for g in regions)
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        if r.get("error"):
            lines.append(f"{r['detector']:{w}s} failed: {r['error']}")
            continue
        flags = " ".join(f"{r[f'flagged_{a}']:.2f}" for a in AXES)
        al = "-" if r["ate_aligned_m"] is None else f"{r['ate_aligned_m']:.3f}"
        drifts = "".join(
            f"  {'-':>15s}"
            if r[f"drift_{g}_m"] is None
            else f"  {r[f'drift_{g}_m']:6.2f} m {r[f'drift_{g}_pct']:5.1f}%"
            for g in regions
        )
        lines.append(
            f"{r['detector']:{w}s} {r['ate_m']:7.3f} {al:>8s} {r['rpe_m']:7.4f} {r['rpe_deg']:8.3f}  "
            f"{flags}  {r['seconds']:6.1f}{drifts}"
        )
    return "\n".join(lines)
