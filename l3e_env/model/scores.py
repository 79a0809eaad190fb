"""Multi-label classification scores per axis: accuracy, precision, recall, F1, PR curves and
thresholds. Pure numpy (a few lines do not justify scikit-learn as a dependency).

An axis with no positive label and no positive prediction in a split has undefined precision,
recall and F1; they are NaN there and left out of the averages (the count of axes that enter
is reported with them), instead of being counted as 0 or 1.
"""

from __future__ import annotations

import numpy as np

from l3e_env.config.labelling import AXES


def axis_scores(labels: np.ndarray, predicted: np.ndarray) -> dict[str, np.ndarray]:
    """Per-axis accuracy, precision, recall, F1 and support (positives), each (6,)."""
    y = np.asarray(labels, dtype=bool).reshape(-1, 6)
    p = np.asarray(predicted, dtype=bool).reshape(-1, 6)
    tp = (y & p).sum(0).astype(float)
    fp = (~y & p).sum(0).astype(float)
    fn = (y & ~p).sum(0).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(tp + fp > 0, tp / (tp + fp), np.where(tp + fn > 0, 0.0, np.nan))
        recall = np.where(tp + fn > 0, tp / (tp + fn), np.where(tp + fp > 0, 0.0, np.nan))
        f1 = np.where(2 * tp + fp + fn > 0, 2 * tp / (2 * tp + fp + fn), np.nan)
    return {
        "accuracy": (y == p).mean(0) if len(y) else np.full(6, np.nan),
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "support": y.sum(0),
    }


def mean_scores(scores: dict[str, np.ndarray]) -> dict[str, float]:
    """Averages over the axes where each score is defined."""
    return {
        k: float(np.nanmean(v)) if np.isfinite(v).any() else float("nan") for k, v in scores.items() if k != "support"
    }


# A test set is scored per axis on the axes with at least this many positives (fewer, and one scan
# moves the F1 by hundredths), and by the micro-averaged F1 over every axis (`micro_f1`).
MIN_POSITIVES = 30


def micro_f1(labels: np.ndarray, predicted: np.ndarray) -> float:
    """F1 of every axis decision pooled (true and false positives and negatives summed over axes and
    scans): each decision counts alike, so an axis with few positives cannot swing it as it swings a
    mean over axes. NaN without a positive label or prediction."""
    y = np.asarray(labels, dtype=bool)
    p = np.asarray(predicted, dtype=bool)
    tp, wrong = int((y & p).sum()), int((y != p).sum())
    return 2 * tp / (2 * tp + wrong) if tp + wrong else float("nan")


def mean_interval(
    labels: np.ndarray, predicted: np.ndarray, resamples: int = 1000, level: float = 0.95, seed: int = 0
) -> dict[str, tuple[float, float]]:
    """Bootstrap interval (scans drawn with replacement) of each averaged score, of the micro-F1
    ("micro_f1") and of each axis's F1 ("f1 x" ... "f1 yaw"): how far a score can move on another
    draw of test scans."""
    y = np.asarray(labels, dtype=bool).reshape(-1, 6)
    p = np.asarray(predicted, dtype=bool).reshape(-1, 6)
    rng = np.random.default_rng(seed)
    draws: dict[str, list[float]] = {}
    for _ in range(resamples):
        rows = rng.integers(0, len(y), len(y))
        scores = axis_scores(y[rows], p[rows])
        found = {**mean_scores(scores), "micro_f1": micro_f1(y[rows], p[rows])}
        found.update({f"f1 {axis}": float(scores["f1"][a]) for a, axis in enumerate(AXES)})
        for k, v in found.items():
            draws.setdefault(k, []).append(v)
    tail = 100 * (1 - level) / 2
    return {
        k: (float(np.nanpercentile(v, tail)), float(np.nanpercentile(v, 100 - tail)))
        if np.isfinite(v).any()
        else (float("nan"), float("nan"))
        for k, v in draws.items()
    }


def pr_curve(labels: np.ndarray, probabilities: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision, recall and the threshold at each distinct probability (predict p > threshold
    is evaluated as p >= t for the t listed), highest threshold first."""
    y = np.asarray(labels, dtype=bool)
    p = np.asarray(probabilities, dtype=float)
    order = np.argsort(-p, kind="stable")
    y, p = y[order], p[order]
    last = np.r_[np.flatnonzero(np.diff(p)), len(p) - 1]  # last index of each distinct value
    tp = np.cumsum(y)[last].astype(float)
    fp = (last + 1 - tp).astype(float)
    positives = max(int(y.sum()), 1)
    return tp / (tp + fp), tp / positives, p[last]


def auroc(labels: np.ndarray, scores: np.ndarray) -> float:
    """Area under the ROC curve of one axis: the chance that a positive scores above a negative
    (ties count half); how well the scores rank, whatever the threshold. NaN without both classes."""
    y = np.asarray(labels, dtype=bool)
    s = np.asarray(scores, dtype=float)
    positives, negatives = int(y.sum()), int((~y).sum())
    if positives == 0 or negatives == 0:
        return float("nan")
    _, inverse, counts = np.unique(s, return_inverse=True, return_counts=True)
    first = np.cumsum(counts) - counts  # tied scores share the mean of their ranks
    ranks = (first + (counts + 1) / 2.0)[inverse]
    return float((ranks[y].sum() - positives * (positives + 1) / 2.0) / (positives * negatives))


def best_thresholds(
    labels: np.ndarray, probabilities: np.ndarray, default: float = 0.5, beta: float = 1.0
) -> np.ndarray:
    """Per axis, the threshold that maximises F-beta (beta > 1 weighs recall more) on the given
    (validation) set; `default` where the axis has no positive label. Returned as values for
    `p > threshold`: midway between the chosen probability and the next lower one, so that it is
    robust to tiny shifts."""
    labels = np.asarray(labels, dtype=bool).reshape(-1, 6)
    probabilities = np.asarray(probabilities, dtype=float).reshape(-1, 6)
    out = np.full(6, default)
    for a in range(6):
        if not labels[:, a].any():
            continue
        precision, recall, thresholds = pr_curve(labels[:, a], probabilities[:, a])
        with np.errstate(invalid="ignore", divide="ignore"):
            f = np.nan_to_num((1 + beta**2) * precision * recall / (beta**2 * precision + recall))
        i = int(np.argmax(f))
        lower = thresholds[i + 1] if i + 1 < len(thresholds) else 0.0
        out[a] = 0.5 * (thresholds[i] + lower)
    return out


def format_table(
    rows: dict[str, dict[str, dict[str, np.ndarray]]],
    digits: int = 3,
    intervals: dict[tuple[str, str], dict[str, tuple[float, float]]] | None = None,
    per_block: int = 8,
) -> str:
    """A Table III layout: one column per (model, split), rows are score x axis plus the mean
    (and its bootstrap interval where given), and the count of positives per axis. Past
    `per_block` columns the table goes on in another block below, so that it fits a terminal."""
    columns = [(m, s) for m, splits in rows.items() for s in splits]
    width = max(14, *(len(m) + 2 for m, _ in columns), *(len(s) + 2 for _, s in columns))
    blocks = [columns[i : i + per_block] for i in range(0, len(columns), per_block)]
    return "\n\n".join(_table_block(rows, block, width, digits, intervals) for block in blocks)


def _table_block(
    rows: dict[str, dict[str, dict[str, np.ndarray]]],
    columns: list[tuple[str, str]],
    width: int,
    digits: int,
    intervals: dict[tuple[str, str], dict[str, tuple[float, float]]] | None,
) -> str:
    lines = [
        f"{'':16s}" + "".join(f"{m:>{width}s}" for m, _ in columns),
        f"{'':16s}" + "".join(f"{s:>{width}s}" for _, s in columns),
    ]
    for score in ("accuracy", "f1", "precision", "recall"):
        for a, axis in enumerate([*AXES, "mean"]):
            cells = []
            for m, s in columns:
                sc = rows[m][s]
                v = mean_scores(sc)[score] if axis == "mean" else sc[score][a]
                cells.append(f"{'n/a' if not np.isfinite(v) else f'{v:.{digits}f}':>{width}s}")
            lines.append(f"{score + ' ' + axis:16s}" + "".join(cells))
        if intervals:
            cells = []
            for column in columns:
                lo, hi = intervals.get(column, {}).get(score, (np.nan, np.nan))
                text = f"{lo:.{digits}f}-{hi:.{digits}f}" if np.isfinite(lo) else "n/a"
                cells.append(f"{text:>{width}s}")
            lines.append(f"{score + ' 95% CI':16s}" + "".join(cells))
    for a, axis in enumerate(AXES):
        lines.append(
            f"{'positives ' + axis:16s}" + "".join(f"{int(rows[m][s]['support'][a]):>{width}d}" for m, s in columns)
        )
    return "\n".join(lines)
