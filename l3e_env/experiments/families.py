"""The families benchmark: every scene family's drives fused with the reference rows and the detectors,
and whether the default estimate ends no worse than its own parts (`run_families`).

Each drive (family-seed, driven with that seed) is recorded once into `out/drives/<scene>/` and
reused; each fusion of it is kept under a key of the fusion settings and the detectors, so a run
that is stopped resumes where it stopped, and a changed setting fuses the recordings again without
driving. The drives are spread over the labelling's worker pool (`data.jobs`: local processes, or
Ray tasks on a cluster).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from l3e_env.config import FusionSettings
from l3e_env.data.jobs import JOB_BACKENDS, run_jobs
from l3e_env.sim.robot import SpawnError
from scenes import list_scenes

from .ate import AteOptions, run_ate
from .drive import DriveOptions, record_run

FAILED = "failed"  # a drive's rows: why it could not be driven
LEGS = "odometry + attitude"  # the legs and the IMU alone: one part of the fusion
UNMASKED = "none"  # ICP on every axis: the other part
DEFAULT_DETECTORS = ("none", "learned", "eigen:30", "dcreg:10")
DEFAULT_ROW = "learned"
# a default row is "no worse than its parts" where its mean is at most MEAN_RATIO times the smaller of
# the parts' means over a family's drives, and on each drive at most DRIVE_RATIO times the smaller of
# that drive's parts, or within DRIVE_SLACK metres of it (where both are a few centimetres)
MEAN_RATIO, DRIVE_RATIO, DRIVE_SLACK = 1.1, 1.5, 0.02


@dataclass(frozen=True)
class FamiliesOptions:
    """families: the scene families driven (all by default); seeds: drives 0..seeds-1 of each, scene
    <family>-<seed> driven with that seed; detectors: the rows fused beside odometry alone and the legs
    and the IMU (`LEGS`); oracle_seeds: the oracle's row (Monte-Carlo labels at the true pose, slow) on
    the first that many seeds; settings: every row's fusion (FusionSettings, the defaults by default);
    workers, backend, ray_address: the job pool (data.jobs)."""

    families: tuple[str, ...] = ()
    seeds: int = 3
    detectors: tuple[str, ...] = DEFAULT_DETECTORS
    oracle_seeds: int = 1
    settings: FusionSettings = FusionSettings()
    sensor: str = "vlp16"
    workers: int = 1
    backend: str = "local"
    ray_address: str | None = None

    def check(self) -> FamiliesOptions:
        known = list_scenes()
        unknown = [f for f in self.families if f not in known]
        if unknown:
            raise ValueError(f"unknown scene families {unknown}; known: {', '.join(known)}")
        if not 1 <= self.seeds <= 100 or not 0 <= self.oracle_seeds <= self.seeds:
            raise ValueError(f"seeds 1 to 100 and oracle seeds 0 to seeds, got {self.seeds} and {self.oracle_seeds}")
        if DEFAULT_ROW not in self.detectors or UNMASKED not in self.detectors:
            raise ValueError(f"the detectors must include '{UNMASKED}' and the default '{DEFAULT_ROW}'")
        if self.backend not in JOB_BACKENDS or self.workers < 1:
            raise ValueError(
                f"backend one of {JOB_BACKENDS} and at least one worker, got {self.backend!r}, {self.workers}"
            )
        return self

    def key(self) -> str:
        """The fusion's key: the settings and the detectors (not the pool)."""
        made = json.dumps([self.settings.record(), list(self.detectors), self.sensor], sort_keys=True)
        return hashlib.sha256(made.encode()).hexdigest()[:10]


@dataclass
class FamilyVerdict:
    """One family's rows over its drives: per row the drives' ATE (m), and the checks of the default."""

    family: str
    ate: dict[str, list[float]]  # row -> ATE of each drive (seed order); the oracle's on its seeds only
    mean_ok: bool
    drives_ok: list[bool]
    failed: list[str] = field(default_factory=list)  # why a drive could not be made

    def mean(self, row: str) -> float:
        return float(np.mean(self.ate[row]))

    def worst(self, row: str) -> float:
        return float(np.max(self.ate[row]))


@dataclass
class FamiliesRun:
    out_dir: Path
    families: list[FamilyVerdict]
    written: list[Path] = field(default_factory=list)

    @property
    def never_worse(self) -> bool:
        return all(f.mean_ok and all(f.drives_ok) for f in self.families if f.ate)

    def table(self) -> str:
        return format_families(self.families)


def run_families(out_dir: str | Path, options: FamiliesOptions | None = None, progress: bool = True) -> FamiliesRun:
    """Every family's drives recorded (once) and fused (once per settings key), the verdicts made,
    families.json, families.md and families.png written into out_dir."""
    options = (options or FamiliesOptions()).check()
    families = list(options.families or list_scenes())
    out = Path(out_dir)
    (out / "drives").mkdir(parents=True, exist_ok=True)
    jobs = [(f, s) for f in families for s in range(options.seeds)]
    results: dict[tuple[str, int], dict[str, Any]] = {}
    todo = []
    for job in jobs:
        done = _rows_file(out, options, job)
        if done.exists():
            results[job] = json.loads(done.read_text())
        else:
            todo.append(job)
    bar = tqdm(
        total=len(jobs), initial=len(jobs) - len(todo), desc="families' drives", unit="drive", disable=not progress
    )
    for job, rows in run_jobs(
        fuse_drive, (str(out), options), todo, options.workers, options.backend, options.ray_address
    ):
        results[job] = rows
        bar.update()
    bar.close()
    verdicts = [verdict(f, [results[(f, s)] for s in range(options.seeds)]) for f in families]
    run = FamiliesRun(out, verdicts)
    run.written = write_families(out, options, verdicts)
    return run


def _rows_file(out: Path, options: FamiliesOptions, job: tuple[str, int]) -> Path:
    family, seed = job
    return out / "drives" / f"{family}-{seed}" / f"fused-{options.key()}" / "rows.json"


def fuse_drive(config: tuple[str, FamiliesOptions], job: tuple[str, int]) -> tuple[tuple[str, int], dict[str, Any]]:
    """One drive of the benchmark (a pool's job): recorded where it is not yet, fused with every row
    (`l3e ate` on the recording, its folder beside it); returns the job and each row's ATE (m)."""
    out, options = Path(config[0]), config[1]
    family, seed = job
    scene = f"{family}-{seed}"
    folder = out / "drives" / scene
    recording = folder / "recording.npz"
    if not recording.exists():
        folder.mkdir(parents=True, exist_ok=True)
        try:
            record_run(scene, DriveOptions(options.sensor, seed), progress=False).save(recording)
        except SpawnError as exc:  # a scene whose route cannot be driven: said in the table, the rest go on
            return job, {FAILED: str(exc)}
    detectors = list(options.detectors) + (["oracle"] if seed < options.oracle_seeds else [])
    ate = AteOptions(
        sensor=options.sensor, seed=seed, recording=recording, fusion_settings=options.settings, maps=False
    )
    done = _rows_file(out, options, job)
    run = run_ate(done.parent, scene, detectors, ate, progress=False)
    rows = {r.detector: float(r.ate_m) if r.ate_m is not None else float("nan") for r in run.rows}
    done.write_text(json.dumps(rows))
    return job, rows


def verdict(family: str, made: list[dict[str, Any]]) -> FamilyVerdict:
    """The family's rows over its drives and whether the default is no worse than its parts (the
    smaller of `LEGS` and `UNMASKED`): in the mean, and on each drive; a drive that could not be made
    (`FAILED`) is named and left out."""
    drives = [d for d in made if FAILED not in d]
    failed = [d[FAILED] for d in made if FAILED in d]
    if not drives:
        return FamilyVerdict(family, {}, False, [], failed)
    names = list(drives[0])
    ate = {name: [d[name] for d in drives if name in d] for name in names}
    parts = [min(d[LEGS], d[UNMASKED]) for d in drives]
    mean_ok = bool(np.mean(ate[DEFAULT_ROW]) <= MEAN_RATIO * min(np.mean(ate[LEGS]), np.mean(ate[UNMASKED])))
    drives_ok = [
        bool(d[DEFAULT_ROW] <= DRIVE_RATIO * p or d[DEFAULT_ROW] <= p + DRIVE_SLACK) for d, p in zip(drives, parts)
    ]
    return FamilyVerdict(family, ate, mean_ok, drives_ok, failed)


def format_families(families: list[FamilyVerdict]) -> str:
    """A markdown table: per family and row the mean ATE over its drives and (worst drive); the
    default's verdict."""
    rows = next(([r for r in f.ate if r != "odometry only"] for f in families if f.ate), [])
    head = "| family | " + " | ".join(rows) + " | default no worse |"
    lines = [head, "|" + "---|" * (len(rows) + 2)]
    for f in families:
        cells = [f"{f.mean(r):.3g} ({f.worst(r):.3g})" if f.ate.get(r) else "" for r in rows]
        ok = (
            "yes"
            if f.mean_ok and all(f.drives_ok)
            else f"no (mean {'ok' if f.mean_ok else 'over'}, {sum(f.drives_ok)}/{len(f.drives_ok)} drives)"
        )
        ok += "".join(f"; a drive failed: {why}" for why in f.failed)
        lines.append(f"| {f.family} | " + " | ".join(cells) + f" | {ok} |")
    return "\n".join(lines)


def write_families(out: Path, options: FamiliesOptions, families: list[FamilyVerdict]) -> list[Path]:
    summary: dict[str, Any] = {
        "settings": options.settings.record(),
        "detectors": list(options.detectors),
        "seeds": options.seeds,
        "key": options.key(),
        "never_worse": all(f.mean_ok and all(f.drives_ok) for f in families if f.ate),
        "families": [
            {"family": f.family, "ate_m": f.ate, "mean_ok": f.mean_ok, "drives_ok": f.drives_ok, "failed": f.failed}
            for f in families
        ],
    }
    (out / "families.json").write_text(json.dumps(summary, indent=1))
    (out / "families.md").write_text(format_families(families) + "\n")
    from .ate_plots import plot_families

    plot_families(out / "families.png", families)
    return [out / "families.json", out / "families.md", out / "families.png"]
