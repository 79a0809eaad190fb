"""Localizability maps: a detector (learned, eigen, oracle or scanmc) evaluated over a grid of
level body poses (x, y, yaw bins) covering a scene's free space, cached on disk by scene, sensor,
detector and grid."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from tqdm import tqdm

from l3e_env.config import LidarConfig, RobotConfig, plain, to_dict
from l3e_env.config.detector_spec import MAP_DETECTORS, parse_detector
from l3e_env.core.files import write_atomic
from l3e_env.core.transforms import planar_pose
from l3e_env.core.workers import ordered_map
from l3e_env.detection.detectors import make_detector
from l3e_env.localizability.registration import RegistrationConfig, RegistrationError, register
from l3e_env.model.classifier import DEFAULT_CHECKPOINT, Classifier, ScanError
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster, make_caster
from scenes import Scene

from .freespace import FreeSpace

MAP_FORMAT = 1


class MapCacheError(FileNotFoundError):
    """No cached map for these settings, or a cache file that does not match them."""


def heading_bins(heading: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two heading bins (of `bins` evenly spaced from 0) around each heading, and the weight
    of the upper one, for linear interpolation around the circle."""
    f = (np.asarray(heading, dtype=np.float64) % (2 * np.pi)) / (2 * np.pi) * bins
    lo = np.floor(f).astype(np.int64) % bins
    return lo, (lo + 1) % bins, f - np.floor(f)


@dataclass
class LocalizabilityMap:
    """probabilities[n, k] are the detector's six non-localizability probabilities (x, y, z,
    roll, pitch, yaw; sensor frame) with the body level at positions[n] and heading yaws[k];
    NaN where the scan could not be judged. `thresholds` are the detector's own. `estimated[n, k]`
    says where the scan's Monte-Carlo estimate judged (scanmc, and the cascade where the
    classifier was unsure); None in a map saved before it was recorded."""

    scene: str
    positions: np.ndarray  # (N, 2)
    yaws: np.ndarray  # (K,) radians, evenly spaced from 0
    probabilities: np.ndarray  # (N, K, 6)
    thresholds: np.ndarray  # (6,)
    meta: dict[str, Any] = field(default_factory=dict)
    estimated: np.ndarray | None = None  # (N, K) bool

    def __post_init__(self) -> None:
        self._tree = cKDTree(self.positions)

    @property
    def masked(self) -> np.ndarray:
        """(N, K, 6) 1.0 where the fusion would drop ICP on that axis; unknown scans mask nothing,
        as in the fusion loop."""
        p = np.nan_to_num(self.probabilities, nan=0.0)
        return (p > self.thresholds).astype(np.float64)

    def nearest(self, xy: np.ndarray) -> np.ndarray:
        """Index of the nearest mapped position for each of the points (..., 2), flattened."""
        _, n = self._tree.query(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
        return n

    def lookup(self, xy: np.ndarray, yaw: np.ndarray | float, values: np.ndarray | None = None) -> np.ndarray:
        """Values (default: `masked`) at the nearest mapped position, linear between yaw bins: (..., 6)."""
        values = self.masked if values is None else values
        xy = np.asarray(xy, dtype=np.float64)
        n = self.nearest(xy)
        yaw = np.broadcast_to(np.asarray(yaw, dtype=np.float64), xy.shape[:-1]).reshape(-1)
        lo, hi, w = heading_bins(yaw, len(self.yaws))
        out = (1 - w[:, None]) * values[n, lo] + w[:, None] * values[n, hi]
        return out.reshape(*xy.shape[:-1], values.shape[-1])

    def save(self, path: str | Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = np.array(json.dumps(plain({**self.meta, "format": MAP_FORMAT, "scene": self.scene})))
        arrays = {
            "positions": self.positions,
            "yaws": self.yaws,
            "probabilities": self.probabilities,
            "thresholds": self.thresholds,
            "meta": meta,
        }
        if self.estimated is not None:
            arrays["estimated"] = self.estimated
        stored: dict[str, Any] = arrays
        write_atomic(path, lambda fh: np.savez_compressed(fh, **stored))

    @classmethod
    def load(cls, path: str | Path) -> LocalizabilityMap:
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                arrays = {k: z[k] for k in ("positions", "yaws", "probabilities", "thresholds")}
                arrays["estimated"] = z["estimated"] if "estimated" in z.files else None
        except (OSError, KeyError, ValueError) as exc:
            raise MapCacheError(f"{path}: not a readable localizability map ({exc})") from exc
        if meta.get("format") != MAP_FORMAT:
            raise MapCacheError(f"{path}: map format {meta.get('format')}, this version reads {MAP_FORMAT}")
        return cls(meta["scene"], meta=meta, **arrays)


def file_digest(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]


class MapJudge:
    """Six probabilities of non-localizability for a batch of sensor poses, and the thresholds
    above which the fusion masks an axis. Kinds, as in l3e_env.detection.detectors.make_detector:
    - learned[:checkpoint]: the classifier on the scan at each pose (NaN: a scan it cannot judge);
      learned-sym[:checkpoint] averages it over the eight mirror/swap views of each scan;
    - eigen:<tau>, dcreg:<kappa>: Zhang's test or DCReg's on the Hessian of registering a scan taken
      `step` metres further ahead onto the pose's scan (what the fusion loop sees between consecutive
      scans); xicp[:L], drpm[:s]: X-ICP's or DRPM's test on the pose's scan's own correspondences;
    - oracle[:M]: Monte-Carlo ICP labels with M children at the pose (slow; ground truth);
    - scanmc[:M]: the same estimated from the scan at the pose alone (l3e_env.localizability.scan_mc; slow);
    - learned+scanmc[:margin]: the shipped classifier, and scanmc where it is unsure. Its two judges
      have different thresholds, so the classifier's probabilities are moved to put its thresholds
      at 0.5 (sigmoid of the log-odds over the threshold): the same flags on one scale.
    The classical tests and oracle give 0/1 masks as probabilities; all but learned have thresholds 0.5."""

    def __init__(self, spec: str, lidar: Lidar, seed: int = 0, step: float = 0.1):
        self.spec, self.lidar, self.seed, self.step = spec, lidar, seed, step
        parsed = parse_detector(spec, allowed=MAP_DETECTORS, what="map detector")
        kind = parsed.kind
        self.kind = "learned" if parsed.learned else kind
        if parsed.learned:
            self.classifier = Classifier.load(parsed.checkpoint, symmetric=kind == "learned-sym")
            self.classifier.check_settings(lidar.config.model)
            self.thresholds = self.classifier.thresholds.copy()
            self.identity = f"{kind}-{file_digest(parsed.checkpoint or DEFAULT_CHECKPOINT)}"
        else:
            # one of several detector classes, each read by what it offers below (its labels, its estimate)
            self.detector: Any = cast(Any, make_detector(spec, lidar, seed))
            self.thresholds = np.full(6, 0.5)
            self.identity = self.detector.name.replace(":", "")
            if kind == "learned+scanmc":
                self.detector.learned.classifier.check_settings(lidar.config.model)
                self.identity += "-" + file_digest(DEFAULT_CHECKPOINT)
            if kind in ("oracle", "scanmc", "learned+scanmc"):  # new labels, calibration or seeding: another map
                config = self.detector.labels if kind == "oracle" else self.estimate_config
                self.identity += "-" + settings_digest({"config": to_dict(config), "children": "seeded by pose"})

    @property
    def estimate_config(self) -> Any:
        """The ScanMCConfig of a scanmc or learned+scanmc judge."""
        return self.detector.scan_mc.config if self.kind == "learned+scanmc" else self.detector.config

    def _judge_scan(self, points: np.ndarray, rng: np.random.Generator, T: np.ndarray) -> tuple[np.ndarray, bool]:
        """scanmc's or the cascade's six probabilities for one scan, with thresholds 0.5 (NaN: unknown),
        and whether the scan's estimate judged it."""
        if self.kind == "learned+scanmc":
            return self.detector.scores_at_half(points, rng, T)
        pred = self.detector.judge(points, rng, T)
        return (pred.probabilities if pred.known else np.full(6, np.nan)), True

    def __call__(self, poses: list[np.ndarray], rngs: list[np.random.Generator]) -> np.ndarray:
        return self.judge_poses(poses, rngs)[0]

    def judge_poses(self, poses: list[np.ndarray], rngs: list[np.random.Generator]) -> tuple[np.ndarray, np.ndarray]:
        """(n, 6) probabilities, and (n,) whether the scan's Monte-Carlo estimate judged each pose."""
        out, estimated = np.full((len(poses), 6), np.nan), np.zeros(len(poses), dtype=bool)
        if self.kind == "learned":
            scans = [self.lidar.scan(T, rng).points for T, rng in zip(poses, rngs)]
            try:
                return self.classifier.probabilities(scans, np.asarray(poses)), estimated
            except ScanError:  # judge one by one; a scan that cannot be judged stays NaN
                for i, (scan, T) in enumerate(zip(scans, poses)):
                    with contextlib.suppress(ScanError):
                        out[i] = self.classifier.probabilities([scan], T[None])[0]
                return out, estimated
        for i, (T, rng) in enumerate(zip(poses, rngs)):
            # the children come from the pose's own rng, so a map does not depend on the order of its poses
            if self.kind == "oracle":
                pred = self.detector.judge(T, rng)
            elif self.kind in ("scanmc", "learned+scanmc"):
                out[i], estimated[i] = self._judge_scan(self.lidar.scan(T, rng).points, rng, T)
                continue
            else:
                ahead = T @ planar_pose(self.step, 0.0, 0.0, 0.0)
                ahead_points = self.lidar.scan(ahead, rng).points
                here = self.lidar.scan(T, rng).points
                try:
                    reg = register(ahead_points, here)
                except RegistrationError:
                    continue
                pred = self.detector.predict(here, reg, T)
            if pred.known:
                out[i] = pred.mask.astype(np.float64)
        return out, estimated


@dataclass(frozen=True)
class MapGrid:
    """Where and how a map judges: positions every `resolution` m of free space, `yaw_bins` headings,
    the body level on the floor at the robot's standing height, the scans of `lidar`, each pose seeded
    by (seed, cell, heading)."""

    resolution: float = 1.0
    yaw_bins: int = 4
    robot: RobotConfig = field(default_factory=RobotConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    seed: int = 0


def map_settings(scene: Scene, free: FreeSpace, grid: MapGrid, judge: MapJudge) -> dict[str, Any]:
    """Everything a map depends on; its hash names the cache file. The registration is in it
    because eigen and oracle maps run ICP, so a new ICP setting must not reuse their old maps."""
    resolution, yaw_bins, robot, seed = grid.resolution, grid.yaw_bins, grid.robot, grid.seed
    return {
        "format": MAP_FORMAT,
        "scene": scene.name,
        "scene_faces": int(len(scene.mesh.faces)),
        "scene_bounds": scene.bounds.round(3).tolist(),
        "free_space_resolution": free.resolution,
        "free_cells": int(free.free.sum()),
        "resolution": float(resolution),
        "yaw_bins": int(yaw_bins),
        "detector": judge.identity,
        "lidar": to_dict(judge.lidar.config),
        "robot": to_dict(robot),
        "registration": to_dict(RegistrationConfig()),
        "seed": int(seed),
    }


def settings_digest(settings: dict[str, Any]) -> str:
    """A short hash of everything a cached file depends on: other settings, another file name."""
    return hashlib.sha256(json.dumps(plain(settings), sort_keys=True).encode()).hexdigest()[:12]


def cache_path(cache_dir: str | Path, settings: dict[str, Any]) -> Path:
    key = settings_digest(settings)
    return Path(cache_dir) / f"{settings['scene']}-{settings['lidar']['model']}-{settings['detector']}-{key}.npz"


def default_cache_dir() -> Path:
    """$L3E_CACHE/maps, else the user's cache folder."""
    root = os.environ.get("L3E_CACHE") or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "l3e"
    return Path(root) / "maps"


def map_positions(free: FreeSpace, resolution: float) -> np.ndarray:
    """Free cells on the lattice of `resolution` through the world origin."""
    cells = np.argwhere(free.free)
    ratio = free.center(cells) / resolution
    on = cells[np.isclose(ratio, np.round(ratio), atol=1e-6).all(axis=1)]
    if len(on) == 0:
        raise ValueError(f"no free cell on the {resolution} m map lattice; use a finer resolution")
    return on


def _map_judge(spec: str, mesh: trimesh.Trimesh, lidar: LidarConfig, seed: int, step: float) -> MapJudge:
    """A map worker's own judge, with a LiDAR on its own copy of the scene."""
    return MapJudge(spec, Lidar(EmbreeCaster(mesh, threads=1), lidar), seed, step)


def _judge_batch(judge: MapJudge, job: tuple[list[np.ndarray], list[list[int]]]) -> tuple[np.ndarray, np.ndarray]:
    poses, seeds = job
    return judge.judge_poses(poses, [np.random.default_rng(s) for s in seeds])


def build_map(
    scene: Scene,
    free: FreeSpace,
    detector: str,
    grid: MapGrid | None = None,
    batch: int = 8,
    progress: bool = False,
    workers: int = 1,
) -> LocalizabilityMap:
    """`detector`'s judgement (MapJudge) of every (position, yaw) of the grid; `workers` processes judge
    batches of poses side by side (each pose has its own seed, so the map is the same)."""
    grid = grid or MapGrid()
    if grid.yaw_bins < 1 or workers < 1:
        raise ValueError(f"yaw_bins and workers must be at least 1, got {grid.yaw_bins} and {workers}")
    judge = MapJudge(detector, scene_lidar(scene, grid.lidar), grid.seed)
    settings = map_settings(scene, free, grid, judge)
    resolution, yaw_bins, robot, seed = grid.resolution, grid.yaw_bins, grid.robot, grid.seed
    cells = map_positions(free, resolution)
    positions = free.center(cells)
    yaws = np.arange(yaw_bins) * 2 * np.pi / yaw_bins
    T_b_s = planar_pose(*robot.lidar_offset, 0.0)
    poses = [(n, k) for n in range(len(cells)) for k in range(yaw_bins)]
    probabilities = np.full((len(cells), yaw_bins, 6), np.nan)
    estimated = np.zeros((len(cells), yaw_bins), dtype=bool)
    chunks = [poses[start : start + batch] for start in range(0, len(poses), batch)]
    jobs = [
        (
            [
                planar_pose(
                    positions[n][0], positions[n][1], free.ground[tuple(cells[n])] + robot.standing_height, yaws[k]
                )
                @ T_b_s
                for n, k in chunk
            ],
            [[seed, n, k] for n, k in chunk],
        )
        for chunk in chunks
    ]
    found = ordered_map(
        _judge_batch,
        jobs,
        judge,
        _map_judge,
        (judge.spec, scene.mesh, judge.lidar.config, judge.seed, judge.step),
        workers,
    )
    judged = list(
        tqdm(found, total=len(jobs), desc=f"{judge.spec} map of {scene.name}", unit="batch", disable=not progress)
    )
    for chunk, (p, by_estimate) in zip(chunks, judged):
        for (n, k), row, e in zip(chunk, p, by_estimate):
            probabilities[n, k], estimated[n, k] = row, e
    return LocalizabilityMap(scene.name, positions, yaws, probabilities, judge.thresholds.copy(), settings, estimated)


def scene_lidar(scene: Scene, lidar: LidarConfig | None = None) -> Lidar:
    return Lidar(make_caster("embree", scene.mesh), lidar or LidarConfig())


@dataclass(frozen=True)
class MapBuild:
    """How a map that is not cached is built: by `workers` processes, with a progress bar, and
    `announce` told what is built, where it is cached and how long it took (minutes on one core,
    which a progress bar hidden by --quiet would not say)."""

    workers: int = 1
    progress: bool = False
    announce: Callable[[str], None] | None = None


def get_map(
    scene: Scene,
    free: FreeSpace,
    detector: str = "learned",
    cache_dir: str | Path | None = None,
    build: bool | MapBuild = True,
    grid: MapGrid | None = None,
) -> LocalizabilityMap:
    """The cached map for these settings; where it is missing, built as `build` says (True: MapBuild's
    defaults) and cached, or MapCacheError where `build` is False."""
    grid = grid or MapGrid()
    judge = MapJudge(detector, scene_lidar(scene, grid.lidar), grid.seed)
    settings = map_settings(scene, free, grid, judge)
    path = cache_path(cache_dir or default_cache_dir(), settings)
    if path.exists():
        cached = LocalizabilityMap.load(path)
        if cached.meta != json.loads(json.dumps(plain(settings))):
            raise MapCacheError(f"{path}: cached with other settings than the ones asked for; delete it to rebuild")
        return cached
    if not build:
        raise MapCacheError(
            f"no {detector} localizability map of scene '{scene.name}' cached for these settings "
            f"({path}); make it with `l3e policy map --scene {scene.name} --detector {detector}`"
        )
    how = build if isinstance(build, MapBuild) else MapBuild()
    if how.announce is not None:
        positions = len(map_positions(free, grid.resolution))
        how.announce(
            f"building the {detector} localizability map of {scene.name} ({positions} positions x {grid.yaw_bins} "
            f"headings, {how.workers} process(es)); it is cached in {path.parent} for every later run"
        )
    began = time.perf_counter()
    result = build_map(scene, free, detector, grid, progress=how.progress, workers=how.workers)
    result.save(path)
    if how.announce is not None:
        how.announce(f"built in {time.perf_counter() - began:.0f} s: {path}")
    return result
