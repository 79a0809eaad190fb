"""The scan's own estimate (`localizability.scan_mc`) over the rows of labelled datasets, in
worker processes: what `l3e evaluate --scan-mc` scores against the labels."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from l3e_env.config import LidarConfig, from_dict
from l3e_env.core.transforms import level_rotation_of
from l3e_env.core.workers import ordered_map
from l3e_env.localizability.registration import RegistrationConfig, RegistrationError
from l3e_env.localizability.scan_mc import ScanEstimate, ScanMCConfig, ScanPatternError, scan_errors

from .dataset import open_datasets


class DatasetScans(NamedTuple):
    """What a worker estimates rows with: the dataset(s) opened by itself (memory maps) and their
    sensor and registration."""

    data: Any
    lidar: LidarConfig
    registration: RegistrationConfig
    config: ScanMCConfig
    seed: int


def open_dataset_scans(folders: list[str | Path], config: ScanMCConfig, seed: int) -> DatasetScans:
    """The dataset(s) `folders` opened for `row_estimate`, once per worker process."""
    data = open_datasets(folders)
    settings = data.manifest["settings"]
    return DatasetScans(
        data,
        from_dict(LidarConfig, settings["lidar"]),
        from_dict(RegistrationConfig, settings["registration"]),
        config,
        seed,
    )


def row_estimate(scans: DatasetScans, row: int) -> ScanEstimate | None:
    """One dataset row's estimate, None where its scan cannot be judged; seeded by the row, so it is
    the same whatever the number of workers."""
    part, at = scans.data.locate(int(row))
    try:
        return scan_errors(
            part.scan(at),
            scans.lidar,
            scans.registration,
            part.label_config,
            scans.config,
            np.random.default_rng([scans.seed, int(row)]),
            level_rotation_of(part.poses[at]),
        )
    except (RegistrationError, ScanPatternError):
        return None


def _estimate_rows(scans: DatasetScans, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimates and children drawn of some rows."""
    out, drawn = np.full((len(rows), 6), np.nan), np.zeros(len(rows), dtype=np.int64)
    for k, row in enumerate(rows):
        if (found := row_estimate(scans, row)) is not None:
            out[k], drawn[k] = found.errors, found.children
    return out, drawn


def dataset_scan_errors(
    folders: list[str], rows: np.ndarray, config: ScanMCConfig, seed: int = 0, workers: int = 1, progress: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(len(rows), 6) estimates for rows of the dataset(s) `folders` (NaN for a scan that cannot
    be judged) and the children drawn for each (0 there), over `workers` processes in chunks of
    a few scans, with a progress bar."""
    from tqdm import tqdm

    rows = np.asarray(rows, dtype=np.int64)
    chunks = [rows[i : i + 4] for i in range(0, len(rows), 4)]
    folders = list(folders)
    out, drawn = np.full((len(rows), 6), np.nan), np.zeros(len(rows), dtype=np.int64)
    with tqdm(
        total=len(rows), desc=f"scan Monte-Carlo (up to {config.children} children)", disable=not progress, leave=False
    ) as bar:
        parts = ordered_map(_estimate_rows, chunks, None, open_dataset_scans, (folders, config, seed), workers)
        for k, (part, children) in enumerate(parts):
            out[4 * k : 4 * k + len(part)], drawn[4 * k : 4 * k + len(part)] = part, children
            bar.update(len(part))
            bar.set_postfix(children=f"{drawn[: 4 * k + len(part)].mean():.0f}")
    return out, drawn
