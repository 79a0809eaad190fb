"""One's own scans, read from files or a ROS bag and judged by the detectors: along which axes
scan-to-scan registration would fail there (`l3e judge`). A scan is in its sensor's frame, as
the driver writes it; points that are NaN, infinite or at the origin (no return, as organised
clouds keep them) are dropped and counted. The axes are those of the scan's level frame (z up):
the up direction is given (`gravity`), or else the ground plane's fit, and the judgement says which."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from itertools import chain
from pathlib import Path

import numpy as np

from l3e_env.config import LidarConfig
from l3e_env.core.points import out_of_reach, random_subset, too_many_points
from l3e_env.core.transforms import level_rotation, rotation_pose
from l3e_env.core.workers import ordered_map
from l3e_env.detection.detectors import (
    CascadeDetector,
    Detector,
    HessianDetector,
    Prediction,
    ScanMCDetector,
    make_detector,
    registration_of,
)
from l3e_env.io.ouster import expand_captures
from l3e_env.io.recorded import RecordedScan
from l3e_env.io.scan_files import ScanFileError, read_scan
from l3e_env.localizability.labels import AXES
from l3e_env.localizability.registration import (
    RegistrationConfig,
    RegistrationError,
    RegistrationResult,
    scan_hessian,
)
from l3e_env.localizability.up import ground_up
from l3e_env.sim.patterns import BeamPattern, PatternError, fit_pattern, get_pattern, in_lidar_frame, register_pattern

# what each detector's score means, printed under the table
SCORES = {
    "learned": "probability that the axis is not localizable (flagged above the model's threshold)",
    "eigen": "share of the axis in the Hessian's degenerate subspace (flagged above 0.5)",
    "dcreg": "log of the axis's condition ratio in its decoupled subspace over 2 log kappa (flagged above 0.5)",
    "xicp": "threshold / (threshold + L), L the correspondences that constrain the axis squarely (flagged above 0.5)",
    "drpm": "share of the axis in the directions whose signal is not above s times the noise (flagged above 0.5)",
    "scanmc": "r / (1 + r), r = estimated registration error over the label threshold (flagged above 0.5)",
    "learned+scanmc": "the classifier's probability where it is sure; where an axis lies within the margin "
    "of its threshold, scanmc's r / (1 + r) for every axis",
    "none": "nothing is flagged",
}


@dataclass
class Judgement:
    path: str
    points: int  # points judged
    dropped: int  # NaN, infinite or at the origin
    predictions: dict[str, Prediction]
    error: str | None = None  # the file could not be read, or its points are not a scan: why (nothing judged)
    stamp: float | None = None  # seconds, for a scan read from a bag
    frame: str | None = None  # how the cloud was turned into its sensor's lidar frame, where it was
    sensor: str | None = None  # the beam pattern it was judged with, where there was one
    up: str | None = None  # where the up direction (the level frame's z) came from, and the sensor's tilt
    shown: np.ndarray | None = None  # a subset of the points in the level frame, where JudgeOptions.shown asks


@dataclass(frozen=True)
class JudgeOptions:
    """How a run judges its scans: scanmc's seed, the scans judged at a time, the up direction in the
    sensor's frame ((3,) for every scan or (N, 3) one per scan in order; None: each scan's ground
    plane's fit, `up_direction`), where a learned detector's network runs, and how many of each scan's
    points its judgement keeps to be shown (a Rerun recording)."""

    seed: int = 0
    workers: int = 1
    gravity: np.ndarray | None = None
    device: str = "cpu"
    shown: int = 0  # keep a random subset of this many of each scan's points, in its level frame (0: none)


MAX_UP_FROM_GROUND_DEG = 60.0  # a given up direction this far from the ground plane's normal is refused


class UpError(ValueError):
    """No up direction for a scan: none given and no ground plane to fit, or one given that the scan's
    own ground contradicts."""


def up_direction(
    points: np.ndarray,
    gravity: np.ndarray | None,
    registration: RegistrationConfig | None = None,
    source: str = "as given",
) -> tuple[np.ndarray, str]:
    """The up direction (against gravity) in the scan's sensor frame, and where it came from: `gravity`
    where given (`source` says by what; checked against the ground plane where one can be fitted), else
    the ground plane's normal. UpError where there is none, or where the given one lies more than
    MAX_UP_FROM_GROUND_DEG from the ground's normal (a vector in another frame, or pointing down)."""
    if len(points) < (registration or RegistrationConfig()).min_points and gravity is None:
        return np.array([0.0, 0.0, 1.0]), "too few points to fit a ground plane: the sensor taken as level"
    found = ground_up(points)
    ground = None if found is None else found[0]
    if gravity is not None:
        up = level_rotation(gravity)[2]  # refuses a zero or non-finite vector by name
        if ground is not None:
            off = float(np.degrees(np.arccos(np.clip(up @ ground, -1.0, 1.0))))
            if off > MAX_UP_FROM_GROUND_DEG:
                raise UpError(
                    f"the given up direction {np.round(up, 3).tolist()} lies {off:.0f} deg from the scan's ground "
                    f"plane (at most {MAX_UP_FROM_GROUND_DEG:.0f}): give the direction against gravity in the "
                    "sensor's own frame (--gravity)"
                )
        return up, f"up {source}, the sensor tilted {tilt_deg(up):.1f} deg"
    if ground is None:
        raise UpError(
            f"no ground plane could be fitted to find the up direction{_degeneracy(points)}: give it with "
            "--gravity X,Y,Z (against gravity, in the sensor's frame; 0,0,1 for a level sensor) or a file of "
            "one per scan"
        )
    return ground, f"up from the ground plane's fit, the sensor tilted {tilt_deg(ground):.1f} deg"


def _degeneracy(points: np.ndarray) -> str:
    """Why a scan holds no plane at all, where its points span less than one (all at one place, or on
    one line), as words to follow the refusal; empty where they do span one."""
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False) if len(points) > 1 else np.zeros(3)
    scale = max(float(spread[0]), 1e-12)
    if spread[0] < 1e-6:
        return " (every point of the scan lies at one place: it holds no geometry)"
    if spread[1] < 1e-6 * scale:
        return " (the scan's points lie on one line: it holds no surface)"
    return ""


def tilt_deg(up: np.ndarray) -> float:
    """The angle between the sensor's z and the up direction."""
    return float(np.degrees(np.arccos(np.clip(up[2] / np.linalg.norm(up), -1.0, 1.0))))


def level_pose(up: np.ndarray | None) -> np.ndarray:
    """A sensor pose (4x4, world z up) with the tilt of `up` and no heading of its own: what the
    detectors read the level frame from (None: a level sensor)."""
    return np.eye(4) if up is None else rotation_pose(level_rotation(up))


def judge_points(
    points: np.ndarray,
    detectors: list[Detector],
    registration: RegistrationConfig | None = None,
    rng: np.random.Generator | None = None,
    T_w_s: np.ndarray | None = None,
) -> dict[str, Prediction]:
    """Each detector's prediction for one scan (UNKNOWN where it cannot judge it), on the axes of the
    level frame of `T_w_s`'s tilt (`level_pose`; None: the sensor taken as level). The eigenvalue
    test and DCReg read the Hessian of the scan registered onto itself, as `l3e evaluate` scores it; scanmc
    draws its children from `rng` where given."""
    onto_itself = None  # eigen and dcreg answer UNKNOWN without it; the others do not read it
    if any(isinstance(d, HessianDetector) for d in detectors):
        try:
            H = scan_hessian(points, registration or registration_of(detectors))
            onto_itself = RegistrationResult(np.eye(4), H, True, 0, len(points), len(points), 0.0)
        except RegistrationError:
            pass
    return {
        d.name: d.judge(points, rng, T_w_s)
        if rng is not None and isinstance(d, (ScanMCDetector, CascadeDetector))
        else d.predict(points, onto_itself, T_w_s)
        for d in detectors
    }


class _Panel:
    """The detectors that judge a run's scans, for the run's sensor and, where the run was not given one,
    for each other sensor whose metadata a recording carries (captures of several sensors in one run),
    made when its first scan comes; a pattern is registered first, as a spawned worker does not
    inherit it."""

    def __init__(
        self,
        specs: list[str],
        sensor: LidarConfig,
        pattern: BeamPattern | None,
        given: bool,
        options: JudgeOptions,
    ) -> None:
        self.specs, self.pattern, self.given, self.options = specs, pattern, given, options
        self.seed, self.gravity = options.seed, options.gravity
        self._detectors: dict[str, list[Detector]] = {}
        self.detectors(pattern, sensor)  # a bad spec fails here, before any scan is read

    def detectors(self, pattern: BeamPattern | None, sensor: LidarConfig | None = None) -> list[Detector]:
        key = pattern.name if pattern is not None and needs_sensor(self.specs) else ""
        if key not in self._detectors:
            if pattern is not None:
                register_pattern(pattern)
            sensor = sensor or LidarConfig(model=pattern.name if pattern is not None else LidarConfig().model)
            self._detectors[key] = [
                make_detector(spec, seed=self.seed, sensor=sensor, device=self.options.device) for spec in self.specs
            ]
        return self._detectors[key]

    def judge(self, index: int, source: str | Path | RecordedScan) -> Judgement:
        """A scan file read, or a recording's scan, and judged; scanmc's children are seeded by the
        scan's place in the list, so that a scan is judged alike alone or in a worker (see read_levelled)."""
        try:
            gravity = self.gravity_of(index)
        except UpError as exc:
            return Judgement(
                str(getattr(source, "name", source)), 0, 0, {}, error=f"{getattr(source, 'name', source)}: {exc}"
            )
        scan = read_levelled(source, self.pattern, self.given, gravity, needs_sensor(self.specs))
        if scan.error is not None:
            return Judgement(scan.name, len(scan.points), scan.dropped, {}, scan.error, scan.stamp, scan.frame)
        detectors = self.detectors(scan.pattern)
        rng = np.random.default_rng([self.seed, index])
        return Judgement(
            scan.name,
            len(scan.points),
            scan.dropped,
            judge_points(scan.points, detectors, rng=rng, T_w_s=level_pose(scan.up)),
            stamp=scan.stamp,
            frame=scan.frame,
            sensor=scan.pattern.name if scan.pattern is not None else None,
            up=scan.how,
            shown=_shown(scan, self.options.shown, rng) if self.options.shown else None,
        )

    def gravity_of(self, index: int) -> np.ndarray | None:
        """The up direction given for the index-th scan: the one vector, or that scan's row of a list."""
        if self.gravity is None or self.gravity.ndim == 1:
            return self.gravity
        if index >= len(self.gravity):
            raise UpError(f"--gravity gives {len(self.gravity)} up directions, one per scan; scan {index + 1} has none")
        return self.gravity[index]


def _shown(scan: LevelledScan, most: int, rng: np.random.Generator) -> np.ndarray:
    """At most `most` of the scan's points (a random subset, drawn after the detectors' draws), turned
    into its level frame."""
    points = random_subset(scan.points[:, :3], most, rng)
    return (points @ level_pose(scan.up)[:3, :3].T).astype(np.float32)


@dataclass
class LevelledScan:
    """A scan read as the detectors judge it: its returns in the sensor's lidar frame, its up direction
    and where that came from; or why it cannot be judged (`error`, and then no points)."""

    name: str
    points: np.ndarray
    dropped: int = 0
    stamp: float | None = None
    frame: str | None = None
    pattern: BeamPattern | None = None
    up: np.ndarray | None = None
    how: str | None = None
    error: str | None = None


def _read_points(source: str | Path | RecordedScan) -> tuple[str, float | None, np.ndarray | None, str | None]:
    """A scan file's or a recording scan's name, stamp, points, and the error where it has none."""
    if isinstance(source, RecordedScan):
        return source.name, source.stamp, source.points, source.error
    try:
        return str(source), None, read_scan(source), None
    except ScanFileError as exc:
        return str(source), None, None, str(exc)


def read_levelled(
    source: str | Path | RecordedScan,
    pattern: BeamPattern | None,
    given: bool,
    gravity: np.ndarray | None,
    own_pattern: bool,
) -> LevelledScan:
    """A scan file read, or a recording's scan, its points without a return dropped. A cloud of a
    sensor whose SDK gives another frame (an Ouster's, `pattern.lidar_to_sensor`) is put in the lidar
    frame. The sensor: `pattern` where `given`, else a recording's own, else (`own_pattern`) the one
    recognised from a file's returns, else `pattern`. The up direction: `gravity`, else the recording's
    IMU's (a bag's), else the ground's fit."""
    name, stamp, points, error = _read_points(source)
    frame = source.frame if isinstance(source, RecordedScan) else None
    if isinstance(source, RecordedScan) and source.pattern is not None and not given:
        pattern = source.pattern
    if error is None and points is not None and (many := too_many_points(len(points))) is not None:
        error = f"{name}: {many}"
    if error is not None or points is None:
        return LevelledScan(name, np.zeros((0, 3)), stamp=stamp, error=error or f"{name}: no points")
    kept = np.isfinite(points).all(axis=1) & (np.abs(points).sum(axis=1) > 0)
    scan = LevelledScan(name, points[kept], int((~kept).sum()), stamp, frame, pattern)
    if (far := out_of_reach(scan.points)) is not None:
        return replace(scan, error=f"{name}: {far}")
    if own_pattern and not isinstance(source, RecordedScan) and not given:
        scan.pattern = _recognised(scan.points) or pattern
    try:
        if scan.pattern is not None:
            scan.points, note = in_lidar_frame(scan.points, scan.pattern)
            scan.frame = note or frame
        scan.up, scan.how = _levelled_up(scan.points, gravity, source)
    except (PatternError, ValueError) as exc:  # an UpError, or an up vector level_rotation refuses
        return replace(scan, error=f"{name}: {exc}")
    return scan


def _levelled_up(
    points: np.ndarray, gravity: np.ndarray | None, source: str | Path | RecordedScan
) -> tuple[np.ndarray, str]:
    """up_direction with --gravity, else a recording's IMU, else the ground's fit; the ground's fit
    says why a recording's IMU gave none."""
    recorded = source if isinstance(source, RecordedScan) else None
    if gravity is None and recorded is not None and recorded.up is not None:
        return up_direction(points, recorded.up, source=recorded.up_source or "from the recording")
    up, how = up_direction(points, gravity)
    if gravity is None and recorded is not None and recorded.up_source is not None:
        how += f" ({recorded.up_source})"
    return up, how


def _recognised(points: np.ndarray) -> BeamPattern | None:
    """A scan file's own sensor, recognised from its returns (files given together may come from
    several sensors); None where it cannot be told, and the run's sensor is used."""
    try:
        return fit_pattern(points)[0]
    except PatternError:
        return None


def _judge_job(panel: _Panel, job: tuple[int, str | RecordedScan]) -> Judgement:
    return panel.judge(*job)


RECOGNITION_TRIES = 5  # readable scans tried: a bag's first revolution may be cut short


def recognise_sensor(
    scans: Iterator[str | Path | RecordedScan],
) -> tuple[Iterator[str | Path | RecordedScan], BeamPattern | None, str]:
    """The sensor's beam pattern from the metadata a recording carries (an Ouster capture's), else
    from the first of the first few readable scans that gives one (`fit_pattern`, with the bag's ring
    field where it has one), or None where none does; what was found, or why not; and the scans
    again from the first."""
    seen: list[str | Path | RecordedScan] = []
    refused: list[str] = []
    unreadable: list[str] = []
    scan_error = ""
    for scan in scans:
        seen.append(scan)
        if isinstance(scan, RecordedScan) and scan.pattern is not None:
            return chain(seen, scans), scan.pattern, f"{scan.pattern.name}, from the metadata of {scan.name}"
        if isinstance(scan, RecordedScan):
            name, points, rings = scan.name, scan.points, scan.rings
        else:
            name, rings = str(scan), None
            try:
                points = read_scan(scan)
            except ScanFileError as exc:
                points, scan_error = None, str(exc)
        if points is None:
            unreadable.append(scan.error or f"{name}: no points" if isinstance(scan, RecordedScan) else scan_error)
            continue
        try:
            if (many := too_many_points(len(points))) is not None:
                raise PatternError(many)
            pattern, how = fit_pattern(points, rings)
        except PatternError as exc:
            refused.append(f"{name}: {exc}")
            if len(refused) < RECOGNITION_TRIES:
                continue
            break
        if refused:
            before = "the scan" if len(refused) == 1 else f"the {len(refused)} scans"
            how += f" (from {name}; not from {before} before it: {refused[0]})"
        return chain(seen, scans), pattern, how
    if len(refused) > 1:
        return (
            chain(seen, scans),
            None,
            (f"not recognised from any of the first {len(refused)} readable scans; the first, {refused[0]}"),
        )
    if refused:
        return chain(seen, scans), None, f"not recognised from {refused[0]}"
    if unreadable:
        return iter(seen), None, f"none of its {len(unreadable)} scan(s) could be read: the first, {unreadable[0]}"
    return iter(seen), None, "the recording holds no scan to recognise it from"


def needs_sensor(specs: list[str]) -> bool:
    """Whether a detector simulates the sensor's beams (scanmc and learned+scanmc do; the others read
    points only)."""
    return any(spec.partition(":")[0] in ("scanmc", "learned+scanmc") for spec in specs)


def judge_scans(
    scans: Iterable[str | Path | RecordedScan],
    specs: list[str],
    sensor: LidarConfig | None = None,
    options: JudgeOptions = JudgeOptions(),
    on_sensor: Callable[[BeamPattern | None, str], None] | None = None,
    sensor_index: int | None = None,
) -> Iterator[Judgement]:
    """Judge each scan, a file to read (an Ouster capture read scan by scan, `read_capture`, with the
    metadata JSON given as `sensor` where there is one) or a recording's scan (`read_bag`), with each detector
    (config.detector_spec.DETECTOR_GRAMMAR; make_detector refuses the oracle,
    which needs a scene), after dropping its points without a return, in the order given,
    `options.workers` scans at a time. Without `sensor`, a detector that needs one gets the pattern
    recognised from the first scans (the default where none fits), reported to `on_sensor`
    with what was found or why not. An Ouster capture of several sensors gives every sensor's scans, each
    judged with its own sensor's detectors, or `sensor_index`'s only. A scan that cannot be read gives a
    Judgement with its `error`, and the next one is read. `options`: see JudgeOptions."""
    if options.workers < 1:
        raise ValueError(f"workers must be at least 1, got {options.workers}")
    metadata = sensor.model if sensor and sensor.model.lower().endswith(".json") else None
    scans = expand_captures(scans, metadata, sensor_index)
    pattern = None
    if sensor is not None:
        pattern = get_pattern(sensor.model)  # an unknown sensor is named before any file is read
    elif needs_sensor(specs):
        scans, pattern, how = recognise_sensor(iter(scans))
        if pattern is not None:
            register_pattern(pattern)
        if on_sensor is not None:
            on_sensor(pattern, how)
    given = sensor is not None
    # a sensor not recognised is taken as the default; scanmc answers unknown for scans not of it
    sensor = sensor or LidarConfig(model=pattern.name if pattern else LidarConfig().model)
    gravity = None if options.gravity is None else np.asarray(options.gravity, dtype=np.float64)
    if gravity is not None and gravity.shape != (3,) and (gravity.ndim != 2 or gravity.shape[1] != 3):
        raise ValueError(f"gravity is one up vector (3,) or one per scan (N, 3), got shape {gravity.shape}")
    options = replace(options, gravity=gravity)
    panel = _Panel(specs, sensor, pattern, given, options)
    jobs = ((i, scan if isinstance(scan, RecordedScan) else str(scan)) for i, scan in enumerate(scans))
    yield from ordered_map(_judge_job, jobs, panel, _Panel, (specs, sensor, pattern, given, options), options.workers)


def _width(name: str) -> int:
    """A detector's column: 16 characters, or its name and two spaces where that is longer."""
    return max(16, len(name) + 2)


def format_judgement(j: Judgement) -> str:
    """A table of each detector's per-axis score, flagged axes marked '*', and a summary line."""
    if j.error:
        return f"{j.error}: not judged"
    names = list(j.predictions)
    lines = [
        f"{j.path}: {j.points} points"
        + (f" ({j.dropped} without a return dropped)" if j.dropped else "")
        + (f", {j.frame}" if j.frame else "")
        + (f"; {j.up}" if j.up else ""),
        f"  {'axis':6s}" + "".join(f"{n:>{_width(n)}s}" for n in names),
    ]
    for a, axis in enumerate(AXES):
        cells = [
            f"{p.probabilities[a]:{_width(n) - 1}.2f}{'*' if p.mask[a] else ' '}"
            if p.known
            else f"{'unknown':>{_width(n)}s}"
            for n, p in j.predictions.items()
        ]
        lines.append(f"  {axis:6s}" + "".join(cells))
    for n in names:
        p = j.predictions[n]
        said = (
            f"cannot judge this scan ({p.reason or 'too few points, or not a full revolution of the sensor'})"
            if not p.known
            else "not localizable along " + ", ".join(a for a, m in zip(AXES, p.mask) if m)
            if p.mask.any()
            else "localizable along every axis"
        )
        lines.append(f"  {n}: {said}")
    return "\n".join(lines)


def judgement_record(j: Judgement, sensor: str | None) -> dict:
    """The judgement as JSON-ready data (NaN scores of a scan a detector cannot judge as null)."""
    where = {"path": j.path} | ({} if j.stamp is None else {"stamp": j.stamp})
    if j.error:
        return where | {"error": j.error}
    return where | {
        "points": j.points,
        "dropped": j.dropped,
        "sensor": j.sensor or sensor,
        "frame": j.frame or "as given",
        "up": j.up,
        "detectors": {
            name: {
                "known": p.known,
                **({"reason": p.reason} if p.reason else {}),
                "scores": [float(v) if np.isfinite(v) else None for v in p.probabilities],
                "not_localizable": [a for a, m in zip(AXES, p.mask) if m],
            }
            for name, p in j.predictions.items()
        },
    }


def write_judgements(
    path: str | Path, judgements: list[Judgement], sensor: str | None, where: np.ndarray | None = None
) -> Path:
    """The judgements as a JSON list (judgement_record), each with its `where` position on the
    recording's path (null off the path's time) where a path was read."""
    records = [judgement_record(j, sensor) for j in judgements]
    for record, position in zip(records, [] if where is None else where):
        record["position"] = [float(v) for v in position] if np.isfinite(position).all() else None
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(records, indent=1) + "\n")
    return out


def score_legend(specs: list[str]) -> str:
    kinds = dict.fromkeys(spec.partition(":")[0].removesuffix("-sym") for spec in specs)
    return "\n".join(f"  {k}: {SCORES[k]}" for k in kinds if k in SCORES)
