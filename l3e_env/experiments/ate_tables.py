"""The ATE experiment's rows and tables: drift inside each named region, failed rows, the summary over
seeds, trajectories as files."""

from __future__ import annotations

import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from fusion import (
    stretch_drift,
    write_kitti,
    write_tum,
)
from l3e_env.config import RobotConfig
from l3e_env.localizability.labels import AXES
from scenes import Scene

from .fuse import DetectorResult


def regions_inside(ground_truth: np.ndarray, scene: Scene) -> dict[str, np.ndarray]:
    """Per named region of the scene (the mine's yard, tunnel and quarry), which poses of the drive
    lie inside it (N,): found once a drive, for every row's region_drift."""
    where = [scene.region_of(p) for p in ground_truth[:, :2, 3]]
    return {region: np.array([w == region for w in where]) for region in scene.regions}


UNITS = ("m", "pct")  # a region's drift in metres and in % of the true distance travelled there
Drift = dict[str, dict[str, float | None]]  # region -> {"m": ..., "pct": ...}


def region_drift(trajectory: np.ndarray, ground_truth: np.ndarray, inside: dict[str, np.ndarray]) -> Drift:
    """Per region (`regions_inside`): the error the estimate accumulated while the robot was inside it
    (fusion.stretch_drift), in metres and in % of the true distance travelled there (None where the
    drive did not move inside the region)."""
    out: Drift = {}
    for region, poses in inside.items():
        drift, distance = stretch_drift(trajectory, ground_truth, poses)
        moved = distance > 0
        out[region] = {
            "m": round(drift, 3) if moved else None,
            "pct": round(100 * drift / distance, 2) if moved else None,
        }
    return out


@dataclass
class AteRow:
    """One row of the ATE table: an estimate's errors against the truth, the share of steps its detector
    flagged per axis, what the run cost and its drift per region; or, with `error`, why it could not be
    made (every figure None). `extra`: what a kind of row adds (a cascade's steps checked)."""

    detector: str
    ate_m: float | None = None
    ate_aligned_m: float | None = None
    rpe_m: float | None = None
    rpe_deg: float | None = None
    flagged: dict[str, float | None] = field(default_factory=lambda: dict.fromkeys(AXES))
    seconds: float | None = None
    unknown_steps: int = 0
    fallback_steps: int = 0
    detector_errors: int = 0
    drift: Drift = field(default_factory=dict)
    error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def of(cls, result: DetectorResult, drift: Drift) -> AteRow:
        """The row of a scored estimate."""
        return cls(
            result.name,
            round(result.ate, 3),
            None if result.ate_aligned is None else round(result.ate_aligned, 3),
            round(result.rpe_translation, 4),
            round(float(np.degrees(result.rpe_rotation)), 3),
            {a: round(float(f), 3) for a, f in zip(AXES, result.masks.mean(axis=0))},
            round(result.seconds, 2),
            result.unknown_steps,
            result.fallback_steps,
            result.detector_errors,
            drift,
            extra={"bias_observed": result.observed, "gated_axes": result.gated_axes} if result.observed else {},
        )

    @classmethod
    def failed(cls, name: str, error: str, scene: Scene) -> AteRow:
        """The row of an estimate that could not be made: its name and why, every figure None."""
        return cls(name, drift={g: dict.fromkeys(UNITS) for g in scene.regions}, error=error)

    def record(self) -> dict[str, Any]:
        """The row as results.json holds it."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "extra"}
        return {**out, **self.extra}


def regions_of(rows: list[AteRow]) -> list[str]:
    """The regions whose drift the rows carry, in order."""
    return list(rows[0].drift) if rows else []


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


def summarize_seeds(runs: dict[int, list[AteRow]]) -> list[dict]:
    """Per detector, over drives of several seeds: ATE and aligned ATE as mean, standard deviation
    and range, and the ATE against odometry alone on the same drive, which cancels most of one
    drive's luck (the odometry's noise decides much of the drift of every detector); and the mean drift
    in each region of the scene (region_drift)."""
    seeds = sorted(runs)
    names = [r.detector for r in runs[seeds[0]]]
    if any([r.detector for r in runs[k]] != names for k in seeds):
        raise ValueError("every seed's drive must be fused with the same detectors")
    if names[0] != "odometry only":
        raise ValueError("each drive's rows start with odometry only, as run_ate returns them")
    summary = []
    regions = regions_of(runs[seeds[0]])
    for i, name in enumerate(names):
        drifts: dict[str, dict[str, float | None]] = {}
        for g in regions:  # the mean over the drives that moved inside the region
            found = [runs[k][i].drift[g] for k in seeds]
            drifts[g] = {}
            for unit in UNITS:
                moved = [float(value) for d in found if (value := d[unit]) is not None]
                drifts[g][unit] = round(float(np.mean(moved)), 3) if moved else None
        ate = np.array([runs[k][i].ate_m for k in seeds], dtype=float)  # NaN where an estimate failed
        aligned = np.array([runs[k][i].ate_aligned_m for k in seeds], dtype=float)
        ratio = ate / np.array([runs[k][0].ate_m for k in seeds])  # row 0: odometry only
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
                "drift_mean": drifts,
            }
        )
    return summary


def format_seed_table(summary: list[dict]) -> str:
    w = _name_width(summary)
    regions = list(summary[0]["drift_mean"])
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
                f"  {'-':>14s}" if r["drift_mean"][g]["pct"] is None else f"  {r['drift_mean'][g]['pct']:14.1f}"
                for g in regions
            )
        )
    return "\n".join(lines)


def _name_width(rows: list[dict]) -> int:
    """The detector column's width: the longest name, at least 14 characters."""
    return max([14, *(len(r["detector"]) for r in rows)])


def format_table(rows: list[AteRow]) -> str:
    """The ATE table; with regions, a column per region of the drift accumulated there (m and % of the
    distance travelled inside it); with the legs' bias states, the share of steps whose ICP observed
    each (a state that none observed kept its prior)."""
    w = max([14, *(len(r.detector) for r in rows)])
    regions = regions_of(rows)
    biases = next((list(o) for r in rows if (o := r.extra.get("bias_observed"))), [])
    head = (
        f"{'detector':{w}s} {'ATE m':>7s} {'aligned':>8s} {'RPE m':>7s} {'RPE deg':>8s}  "
        f"flagged x/y/z/roll/pitch/yaw      {'s':>6s}"
        + "".join(f"  {'drift ' + g:>15s}" for g in regions)
        + (f"  observed {'/'.join(biases)}" if biases else "")
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        if r.error:
            lines.append(f"{r.detector:{w}s} failed: {r.error}")
            continue
        flags = " ".join(f"{r.flagged[a]:.2f}" for a in AXES)
        al = "-" if r.ate_aligned_m is None else f"{r.ate_aligned_m:.3f}"
        drifts = "".join(
            f"  {'-':>15s}" if (d := r.drift[g])["m"] is None else f"  {d['m']:6.2f} m {d['pct']:5.1f}%"
            for g in regions
        )
        errors = f"{r.ate_m:7.3f} {al:>8s} {r.rpe_m:7.4f} {r.rpe_deg:8.3f}"
        observed = r.extra.get("bias_observed") or {}
        shares = "  " + " ".join(f"{observed[b]:.2f}" for b in biases) if observed else ""
        lines.append(f"{r.detector:{w}s} {errors}  {flags}  {r.seconds:6.1f}{drifts}{shares}")
    return "\n".join(lines)
