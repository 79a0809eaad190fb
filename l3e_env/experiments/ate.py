"""Record a drive once, then fuse it with every detector: ATE/RPE tables, plots and maps.

`record_run` drives a scene's route with the route follower and keeps, per step, the scan, the
leg-odometry increment and the ground truth. `run_ate` registers consecutive scans once (the
one registration), asks each detector for a mask, fuses odometry and masked ICP in the iSAM2
graph, and measures against ground truth. A saved recording can be evaluated again with new
detectors without driving.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from fusion import (
    FusionConfig,
)
from l3e_env.config import FusionSettings, LidarConfig, OdometryConfig, RobotConfig, to_dict
from l3e_env.detection.detectors import (
    CascadeDetector,
    Detector,
    ScanMCDetector,
    make_detector,
    registration_of,
)
from l3e_env.detection.pipeline import Keyframes
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.lidar import Lidar, get_pattern
from l3e_env.sim.odometry import odometry_fusion_config
from l3e_env.sim.raycast import EmbreeCaster
from scenes import Scene, make_scene

from .ate_tables import (
    AteRow,
    file_stem,
    format_seed_table,
    format_table,
    region_drift,
    regions_inside,
    summarize_seeds,
    write_trajectories,
)
from .baselines import BASELINES, BaselineRun, check_baselines, run_baseline
from .drive import DriveOptions, DriveRecord, deskewed, record_run, register_sequence
from .fuse import FusedRun, fuse_recording, odometry_only, scored
from .recast import OdometryAttitude, RecastCascade, RecastScans


@dataclass
class AteRun:
    """One drive fused with every detector: the table's rows (odometry only first) and what was written."""

    out_dir: Path
    rows: list[AteRow]
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
    that judge the route with scanmc before the fusion (the same judgements as one). fusion_settings:
    every fusion's (its backend; its deskew, where a swept recording's deskewing takes its rotation
    from; its attitude, the IMU's orientation in the fusion, and with it a row "odometry + attitude"
    after odometry alone; the biases' prior from the default OdometryConfig, as the drive's).
    max_steps: a shorter drive. baselines: external LiDAR odometries
    (experiments.baselines: kiss-icp, genz-icp) run on the drive's scans as recorded (a swept drive's
    with their firing times, which they deskew themselves), each a row after the fusion's; their
    settings go into results.json, and one that fails says so in its row. frontends: the LiDAR front
    ends whose steps the fusion takes ("icp": scan-to-scan ICP; or a baseline's name: its relative
    motions with the ICP's information, BaselineRun.registrations); every detector is fused with each,
    the rows of a front end other than ICP named "<detector> @<front end>". maps: each row's map (a
    PLY and a top view) written beside the table (a benchmark of many drives leaves them out). rerun:
    a Rerun recording of the drive and its rows written there (experiments.rerun_log; rerun-sdk)."""

    sensor: str = "vlp16"
    seed: int = 0
    recording: str | Path | None = None
    scene_params: dict | None = None
    workers: int = 1
    fusion_settings: FusionSettings = FusionSettings()
    max_steps: int | None = None
    baselines: list[str] = field(default_factory=list)
    frontends: list[str] = field(default_factory=lambda: ["icp"])
    maps: bool = True
    rerun: str | Path | None = None

    def check(self) -> None:
        """ValueError naming a setting no drive can use (and a missing baseline package), before the drive."""
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")
        if not self.frontends or any(f != "icp" and f not in BASELINES for f in self.frontends):
            raise ValueError(f"front ends: icp or one of {', '.join(BASELINES)}, got {self.frontends}")
        check_baselines([*self.baselines, *(f for f in self.frontends if f != "icp")])
        if self.rerun:
            from .rerun_log import check_rerun

            check_rerun()  # rerun-sdk missing: said before the drive


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
    `options`: run_ate's (not a recording: that is one drive; their seed is each drive's; a Rerun
    recording FILE.rrd is written per drive as FILE-seed-<seed>.rrd)."""
    options = options or AteOptions()
    if len(seeds) < 1:
        raise ValueError("give one seed or more")
    if options.recording:
        raise ValueError("a recording is one drive: drive several seeds without it")
    out = Path(out_dir)
    runs = {}
    for seed in seeds:
        rerun = Path(options.rerun).with_stem(f"{Path(options.rerun).stem}-seed-{seed}") if options.rerun else None
        runs[seed] = run_ate(out / f"seed-{seed}", scene, detectors, replace(options, seed=seed, rerun=rerun), progress)
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
    rec: DriveRecord
    raw: DriveRecord
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
    keyframes = Keyframes(distance=options.fusion_settings.keyframe_distance or 0.0)  # set by its __post_init__
    regs = register_sequence(drive.rec, drive.registration, progress, keyframes)
    icp_seconds = time.perf_counter() - t0
    ahead = judge_ahead(drive, options.workers, progress, options.fusion_settings.detector_every)
    dets = drive.detectors
    if options.fusion_settings.attitude != "none":
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
        "deskew": options.fusion_settings.deskew if drive.raw.sweep else None,
        "fusion": options.fusion_settings.record(),
        "steps": len(drive.rec.odometry),
        "icp_seconds": round(icp_seconds, 1),
        "icp_failed_or_not_converged": sum(r is None or not r.converged for r in regs),
        "registration": to_dict(drive.registration),
        "frontends": options.frontends,
        "baselines": {
            name: {"config": run.config, "seconds": round(run.seconds, 2), "error": run.error}
            for name, run in runs.items()
        },
        "rows": [r.record() for r in rows],
    }
    written = write_ate(out, summary, drive, results, options.maps)
    if options.rerun:
        from .rerun_log import log_drive

        written.append(log_drive(options.rerun, drive.scene.mesh, drive.rec, results, RobotConfig.dt))
    return AteRun(out, rows, drive.raw.sweep, written)


def prepare_drive(out: Path, scene: str, specs: list[str], options: AteOptions, progress: bool) -> AteDrive:
    """The scene (a recording's own, or `scene`), its LiDAR and the detectors (a bad spec fails before
    the drive), then the drive itself, recorded into out/recording.npz where none was given."""
    rec = DriveRecord.load(options.recording) if options.recording else None
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
        driving = DriveOptions(options.sensor, options.seed, options.scene_params, max_steps=options.max_steps)
        rec = record_run(scene, driving, progress, scene_object=scene_obj)
        rec.save(out / "recording.npz")
    return AteDrive(scene_obj, lidar, deskewed(rec, options.fusion_settings.deskew), rec, dets, registration)


def judge_ahead(drive: AteDrive, workers: int, progress: bool, every: int = 1) -> list[float]:
    """The scan estimates of the route judged over `workers` processes before the fusion; returns the
    seconds each detector spent so (counted in its time). The fusion asks its detector every `every`
    steps: call k is at scan every k + 1's pose."""
    ahead = [0.0] * len(drive.detectors)
    scans = range(1, len(drive.rec.ground_truth), every)
    poses = [drive.rec.ground_truth[k] @ drive.rec.T_b_s for k in scans]
    for i, det in enumerate(drive.detectors):
        t0 = time.perf_counter()
        if isinstance(det, RecastScans) and workers > 1:
            det.judge_ahead(poses, drive.scene, workers, progress)
        elif isinstance(det, RecastCascade) and workers > 1:
            det.judge_ahead([drive.rec.detector_input(k) for k in scans], poses, drive.scene, workers, progress)
        ahead[i] = time.perf_counter() - t0
    return ahead


def fuse_frontends(
    rec: DriveRecord,
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
        failed = runs[frontend].error if frontend != "icp" else None
        if failed is not None:
            lost += [(f"{det.name} @{frontend}", failed) for det in dets]
            continue
        steps = regs if frontend == "icp" else runs[frontend].registrations(regs)
        by_front = fuse_recording(rec, dets, steps, fusion, progress=progress, settings=options.fusion_settings)
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
) -> tuple[list, list[AteRow]]:
    """The results (odometry only first, the fusions, the baselines alone) and the table's rows with
    each one's drift inside each named region; a failed row says why."""
    rec, scene = drive.rec, drive.scene
    results = [odometry_only(rec)] + fused
    inside = regions_inside(rec.ground_truth, scene)
    rows = [AteRow.of(r, region_drift(r.trajectory, rec.ground_truth, inside)) for r in results]
    for det, row in zip(dets * len(options.frontends), rows[1:]):
        if isinstance(det, RecastCascade):  # what the estimate cost it: steps it was asked, scans it judged
            row.extra.update(checked_steps=det.cascade.checked, judged_steps=det.judged_steps)
    rows += [AteRow.failed(name, error, scene) for name, error in lost]
    for name in options.baselines:
        run = runs[name]
        if run.error is not None or run.trajectory is None:
            rows.append(AteRow.failed(name, run.error or "no trajectory", scene))
            continue
        steps = len(rec.odometry)
        masks, probabilities = np.zeros((steps, 6), bool), np.full((steps, 6), np.nan)
        results.append(scored(FusedRun(name, run.trajectory, masks, probabilities, run.seconds), rec.ground_truth))
        rows.append(AteRow.of(results[-1], region_drift(run.trajectory, rec.ground_truth, inside)))
    return results, rows


def write_ate(out: Path, summary: dict, drive: AteDrive, results: list, maps_too: bool = True) -> list[Path]:
    """results.json, the trajectories' and timeline's plots, a map per row and the trajectories as
    files; returns what was written (the recording first, where the drive made one)."""
    (out / "results.json").write_text(json.dumps(summary, indent=1))
    from .ate_plots import plot_map, plot_timeline, plot_trajectories

    plot_trajectories(out / "trajectories.png", drive.scene, drive.rec, results)
    plot_timeline(out / "timeline.png", results[1:])
    maps = []
    for r in results[1:] if maps_too else []:
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
