"""Monte-Carlo registration errors estimated from one scan alone.

The labels (labels.py) ray-cast children around a parent in the full scene and register each
to the parent. With only the parent's scan in hand, its range image is the best surface there
is: neighbouring returns of neighbouring beams and columns are joined into triangles, except
across depth jumps, and the children are ray-cast against that mesh. It is physics rather than
learning, so it carries over to scene families no model was trained on, at the cost of M
registrations a scan. What the mesh lacks (surfaces the parent did not see) the children miss
too, so the estimate runs somewhat low; `calibration` scales it back (fitted on training scenes).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from .config import LidarConfig
from .labels import LabelConfig, registration_error
from .lidar import BeamPattern, Lidar, get_pattern
from .raycast import EmbreeCaster
from .registration import PreparedTarget, RegistrationConfig, RegistrationError, prepare_source, register
from .transforms import pose_to_matrix


@dataclass
class ScanMCConfig:
    """How the scan's own Monte-Carlo estimate is made."""

    children: int = 20  # registrations per scan (the labels use 200)
    max_range_ratio: float = 1.5  # two returns whose ranges differ more are not joined (a depth jump)
    # Estimated errors are multiplied by these: 1 / the median of estimate over label on 240 scans
    # of the training scenes with 20 children (`benchmarks/scan_mc_calibration.py`).
    calibration: tuple[float, ...] = (1.23, 1.23, 1.21, 1.17, 1.20, 1.11)


class ScanPatternError(ValueError):
    """Points that do not lie on the rays of the LiDAR's beam pattern."""


def beams_and_columns(points: np.ndarray, pattern: BeamPattern) -> tuple[np.ndarray, np.ndarray]:
    """The beam and column of each point, from its direction: a scan stored as bare points keeps
    them, since range noise moves a return along its ray only."""
    r = np.linalg.norm(points, axis=1)
    if not (r > 0).all():
        raise ScanPatternError("the scan holds a point at the sensor's origin")
    elevation = np.degrees(np.arcsin(np.clip(points[:, 2] / r, -1.0, 1.0)))
    beams = np.asarray(pattern.elevations_deg)
    beam = np.abs(elevation[:, None] - beams[None]).argmin(axis=1)
    spacing = np.min(np.diff(np.sort(beams))) if len(beams) > 1 else 1.0
    off = np.abs(elevation - beams[beam]).max(initial=0.0)
    if off > 0.25 * spacing:
        raise ScanPatternError(f"a point lies {off:.2f} deg off the nearest beam of {pattern.name} (beams "
                               f"{spacing:.2f} deg apart): give a scan of that sensor, in its own frame")
    step = 2 * np.pi / pattern.n_azimuth
    column = np.round((np.arctan2(points[:, 1], points[:, 0]) % (2 * np.pi)) / step).astype(np.int64)
    return beam, column % pattern.n_azimuth


def range_image_mesh(points: np.ndarray, pattern: BeamPattern, max_range_ratio: float = 1.5) -> trimesh.Trimesh:
    """The scan's points as vertices, each 2 x 2 block of neighbouring beams and columns (columns
    wrap around) as two triangles where all three returns exist and their ranges differ by less
    than `max_range_ratio`."""
    points = np.asarray(points, dtype=np.float64)
    beam, column = beams_and_columns(points, pattern)
    shape = (pattern.n_beams, pattern.n_azimuth)
    vertex = np.full(shape, -1, dtype=np.int64)
    vertex[beam, column] = np.arange(len(points))
    beside = (np.roll(vertex, -1, axis=1)[beam, column] >= 0).mean() if len(points) else 0.0
    if beside < 0.5:  # a full revolution has a return in the next column beside nearly every return
        raise ScanPatternError(f"only {beside:.0%} of the scan's returns have one beside them: the scan is thinned "
                               "or sampled, and the estimate needs every return of a revolution")
    ranges = np.zeros(shape)
    ranges[beam, column] = np.linalg.norm(points, axis=1)
    order = np.argsort(pattern.elevations_deg)  # rows from the lowest beam up, so that rows k, k+1 neighbour
    vertex, ranges = vertex[order], ranges[order]

    def corner(grid: np.ndarray, down: int, right: int) -> np.ndarray:
        return np.roll(grid, -right, axis=1)[down:down + pattern.n_beams - 1]

    faces = []
    for tri in (((0, 0), (0, 1), (1, 0)), ((0, 1), (1, 1), (1, 0))):
        ids = [corner(vertex, d, r) for d, r in tri]
        rs = [corner(ranges, d, r) for d, r in tri]
        hi, lo = np.maximum.reduce(rs), np.minimum.reduce(rs)
        ok = (ids[0] >= 0) & (ids[1] >= 0) & (ids[2] >= 0) & (hi < max_range_ratio * lo)
        faces.append(np.stack([i[ok] for i in ids], axis=1))
    return trimesh.Trimesh(points, np.concatenate(faces), process=False)


def scan_errors(points: np.ndarray, lidar: LidarConfig, registration: RegistrationConfig, labels: LabelConfig,
                config: ScanMCConfig, rng: np.random.Generator) -> np.ndarray:
    """(6,) estimated mean registration errors of the scan (metres, radians), as labels.py
    computes them in the full scene, times the calibration. Raises RegistrationError where the
    scan itself cannot be registered, or more than half of the children cannot."""
    if config.children < 1:
        raise ValueError(f"the scan estimate needs at least one child, got {config.children}")
    points = np.asarray(points, dtype=np.float64)
    target = PreparedTarget(points, registration)  # checks shape, NaN and size first
    pattern = get_pattern(lidar.model)
    mesh = range_image_mesh(points, pattern, config.max_range_ratio)
    if len(mesh.faces) == 0:
        raise RegistrationError("no two neighbouring returns of the scan could be joined into a surface")
    sensor = Lidar(EmbreeCaster(mesh, threads=1), lidar)
    sigma = labels.sigma_vector("child")
    errors = []
    for _ in range(config.children):
        T_p_c = pose_to_matrix(rng.normal(0, 1, 6) * sigma)
        child = sensor.scan(T_p_c, rng)
        try:
            result = register(prepare_source(child.points, registration), target, registration, with_hessian=False)
        except RegistrationError:
            continue
        errors.append(registration_error(result.T_target_source, T_p_c, labels.error_frame))
    if len(errors) < max(1, config.children // 2):
        raise RegistrationError(f"{config.children - len(errors)} of {config.children} children of the scan's own "
                                "surface could not be registered")
    return np.mean(errors, axis=0) * np.asarray(config.calibration)


def _dataset_part(folders: list[str], rows: np.ndarray, config: ScanMCConfig, seed: int) -> np.ndarray:
    """Estimates of some rows, in a worker that opens the dataset itself (memory maps)."""
    from .config import from_dict
    from .dataset import open_datasets

    data = open_datasets(folders)
    settings = data.manifest["settings"]
    lidar, registration = from_dict(LidarConfig, settings["lidar"]), from_dict(RegistrationConfig,
                                                                               settings["registration"])
    labels = data.parts[0].label_config  # the parts of a union share the child sigmas and error frame
    out = np.full((len(rows), 6), np.nan)
    for k, row in enumerate(rows):
        try:  # seeded by the row: the same estimate whatever the number of workers
            out[k] = scan_errors(data.scan(int(row)), lidar, registration, labels, config,
                                 np.random.default_rng([seed, int(row)]))
        except (RegistrationError, ScanPatternError):
            pass
    return out


def dataset_scan_errors(folders: list[str], rows: np.ndarray, config: ScanMCConfig, seed: int = 0,
                        workers: int = 1, progress: bool = False) -> np.ndarray:
    """(len(rows), 6) estimates for rows of the dataset(s) `folders` (NaN for a scan that cannot
    be judged), over `workers` processes in chunks of a few scans, with a progress bar."""
    from concurrent.futures import ProcessPoolExecutor
    from contextlib import nullcontext
    from itertools import repeat

    from tqdm import tqdm

    rows = np.asarray(rows, dtype=np.int64)
    chunks = [rows[i:i + 4] for i in range(0, len(rows), 4)]
    jobs = (repeat(list(folders)), chunks, repeat(config), repeat(seed))
    out = np.full((len(rows), 6), np.nan)
    with (ProcessPoolExecutor(workers) if workers > 1 else nullcontext()) as pool, \
            tqdm(total=len(rows), desc=f"scan Monte-Carlo ({config.children} children)", disable=not progress,
                 leave=False) as bar:
        for k, part in enumerate(pool.map(_dataset_part, *jobs) if pool else map(_dataset_part, *jobs)):
            out[4 * k:4 * k + len(part)] = part
            bar.update(len(part))
    return out
