"""The judgements of a sequence of scans (a bag, or files in order) as pictures: per detector,
which axes are flagged scan by scan, over time, or on a map of the bag's path, so that the
stretch of a run where an axis goes blind stands out."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from l3e_env.localizability.labels import AXES

from .judge import Judgement


def flag_matrix(judgements: list[Judgement], detector: str) -> np.ndarray:
    """(6, scans): 1 flagged, 0 localizable, NaN where the scan was not read or not judged."""
    out = np.full((6, len(judgements)), np.nan)
    for k, j in enumerate(judgements):
        p = j.predictions.get(detector)
        if p is not None and p.known:
            out[:, k] = p.mask
    return out


def _detectors(judgements: list[Judgement]) -> list[str]:
    """The detectors that judged any scan, in the order first seen."""
    names = list(dict.fromkeys(n for j in judgements for n in j.predictions))
    if not names:
        raise ValueError("no scan was judged: nothing to plot")
    return names


def _save(fig, path: str | Path, dpi: int) -> None:
    import matplotlib.pyplot as plt

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def plot_timeline(judgements: list[Judgement], path: str | Path) -> None:
    """Rows of axes against time (seconds since the first scan, for a bag) or the scan's place, a panel
    per detector, and per sensor where the scans come from several (a capture of several sensors)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = _detectors(judgements)
    sensors = list(dict.fromkeys(j.sensor for j in judgements if j.sensor is not None))
    groups: dict[str | None, list[Judgement]] = (
        {s: [j for j in judgements if j.sensor == s] for s in sensors} if len(sensors) > 1 else {None: judgements}
    )
    panels = [(s, n) for s, group in groups.items() for n in names if any(n in j.predictions for j in group)]
    stamps = [float(s) for j in judgements if (s := j.stamp) is not None]
    timed = len(stamps) == len(judgements)
    cmap = matplotlib.colormaps["Reds"].resampled(2).with_extremes(bad="0.8")
    fig, axes = plt.subplots(len(panels), 1, figsize=(10, 1.4 + 1.1 * len(panels)), sharex=timed, squeeze=False)
    for ax, (sensor, name) in zip(axes[:, 0], panels):
        group = groups[sensor]
        x = (
            np.array([j.stamp for j in group], dtype=np.float64) - stamps[0]
            if timed
            else np.arange(len(group), dtype=np.float64)
        )
        gaps = np.diff(x) if len(x) > 1 else np.ones(1)
        edges = np.concatenate([[x[0] - gaps[0] / 2], (x[:-1] + x[1:]) / 2, [x[-1] + gaps[-1] / 2]])
        ax.pcolormesh(edges, np.arange(7), np.ma.masked_invalid(flag_matrix(group, name)), cmap=cmap, vmin=0, vmax=1)
        ax.set_yticks(np.arange(6) + 0.5, AXES)
        ax.invert_yaxis()
        title = f"{name}: red = not localizable, grey = not judged"
        ax.set_title(title if sensor is None else f"{sensor}, {title}", fontsize=9, loc="left")
    axes[-1, 0].set_xlabel("seconds since the first scan" if timed else "scan")
    fig.tight_layout()
    _save(fig, path, 120)


def plot_path(
    judgements: list[Judgement], where: np.ndarray, route: np.ndarray, path: str | Path, title: str = ""
) -> None:
    """A map per detector and axis, seen from above at equal scale: the robot's `route` (K, 3) as a
    line and each judged scan at `where` (N, 3; NaN: off the route's time), red where the axis is
    flagged. A route longer east-west than north-south gets its six axes one under another."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = _detectors(judgements)
    placed = np.isfinite(where).all(axis=1)
    if not placed.any():
        raise ValueError("no judged scan lies within the path's time: nothing to place on the map")
    lo, hi = route[:, :2].min(axis=0) - 2.0, route[:, :2].max(axis=0) + 2.0
    ratio = (hi[1] - lo[1]) / (hi[0] - lo[0])  # north-south over east-west extent
    wide = ratio <= 1.0
    if wide:  # six rows of axes, a column per detector
        width = 18.0 / len(names)
        grid, panel = (6, len(names)), (width, float(np.clip(width * ratio, 1.3, 4.0)))
    else:
        grid, panel = (len(names), 6), (3.0, float(np.clip(3.0 * ratio, 2.5, 6.0)))
    fig, axes = plt.subplots(*grid, figsize=(panel[0] * grid[1], 0.6 + (panel[1] + 0.4) * grid[0]), squeeze=False)
    for d, name in enumerate(names):
        flags = flag_matrix(judgements, name)
        for k in range(6):
            ax = axes[k, d] if wide else axes[d, k]
            ax.plot(route[:, 0], route[:, 1], color="0.75", lw=0.8, zorder=1)
            judged = placed & np.isfinite(flags[k])
            flagged = judged & (flags[k] == 1)
            ax.scatter(*where[judged & ~flagged, :2].T, s=5, color="0.35", zorder=2, linewidths=0)
            ax.scatter(*where[flagged, :2].T, s=9, color="tab:red", zorder=3, linewidths=0)
            ax.update_datalim([lo, hi])  # 2 m round the path
            ax.set_aspect("equal", adjustable="datalim")  # metres alike both ways; the limits give way
            ax.set_title(f"{name}: {AXES[k]}  ({int(flagged.sum())} of {int(judged.sum())} flagged)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.suptitle(
        (title + ": " if title else "") + "red = not localizable along the axis, dark = localizable, "
        "line = the path (m)",
        fontsize=9,
    )
    fig.tight_layout()
    _save(fig, path, 110)
