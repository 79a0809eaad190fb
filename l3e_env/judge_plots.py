"""The judgements of a sequence of scans (a bag, or files in order) as a picture: per detector,
which axes are flagged scan by scan, so that the stretch of a run where an axis goes blind
stands out."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .judge import Judgement
from .labels import AXES


def flag_matrix(judgements: list[Judgement], detector: str) -> np.ndarray:
    """(6, scans): 1 flagged, 0 localizable, NaN where the scan was not read or not judged."""
    out = np.full((6, len(judgements)), np.nan)
    for k, j in enumerate(judgements):
        p = j.predictions.get(detector)
        if p is not None and p.known:
            out[:, k] = p.mask
    return out


def plot_timeline(judgements: list[Judgement], path: str | Path) -> None:
    """Rows of axes against time (seconds since the first scan, for a bag) or the scan's place."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(n for j in judgements for n in j.predictions))
    if not names:
        raise ValueError("no scan was judged: nothing to plot")
    stamps = [j.stamp for j in judgements]
    timed = all(s is not None for s in stamps)
    x = np.asarray(stamps, dtype=np.float64) - stamps[0] if timed else np.arange(len(judgements), dtype=np.float64)
    gaps = np.diff(x) if len(x) > 1 else np.ones(1)
    edges = np.concatenate([[x[0] - gaps[0] / 2], (x[:-1] + x[1:]) / 2, [x[-1] + gaps[-1] / 2]])
    cmap = matplotlib.colormaps["Reds"].resampled(2).with_extremes(bad="0.8")
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 1.4 + 1.1 * len(names)), sharex=True, squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        flags = flag_matrix(judgements, name)
        ax.pcolormesh(edges, np.arange(7), np.ma.masked_invalid(flags), cmap=cmap, vmin=0, vmax=1)
        ax.set_yticks(np.arange(6) + 0.5, AXES)
        ax.invert_yaxis()
        ax.set_title(f"{name}: red = not localizable, grey = not judged", fontsize=9, loc="left")
    axes[-1, 0].set_xlabel("seconds since the first scan" if timed else "scan")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
