"""Figures of the ATE experiment: trajectories over the scene, mask timelines, maps."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from l3e_env.localizability.labels import AXES  # noqa: E402
from l3e_env.sim.render import binned_from_above, wall_points  # noqa: E402


def draw_from_above(ax, points: np.ndarray, values: np.ndarray, cmap: str, cells: int = 800):
    """`points` drawn from above on the matplotlib axes `ax` as one image (render.binned_from_above),
    each cell coloured by its largest value through `cmap`. Returns the image, for a colour bar."""
    grid, extent = binned_from_above(points, values, cells)
    return ax.imshow(grid, extent=extent, origin="lower", cmap=cmap, interpolation="nearest", zorder=0)


def plot_trajectories(path: Path, scene, rec, results) -> None:
    walls = wall_points(scene.mesh, 100_000)
    fig, ax = plt.subplots(figsize=(12, 5))
    ax.scatter(walls[:, 0], walls[:, 1], s=2, c="0.6", linewidths=0, rasterized=True)
    ax.plot(rec.ground_truth[:, 0, 3], rec.ground_truth[:, 1, 3], "k", lw=2, label="ground truth")
    for r in results:
        ax.plot(r.trajectory[:, 0, 3], r.trajectory[:, 1, 3], lw=1.2, label=f"{r.name} (ATE {r.ate:.2f} m)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    # under the map: never over a path, and no search for a free corner among the wall points
    fig.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="lower center", ncol=3)
    ax.set_title(f"{rec.scene}: estimates against ground truth")
    fig.tight_layout(rect=(0, 0.04 + 0.035 * np.ceil((len(results) + 1) / 3), 1, 1))  # the legend's rows
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_timeline(path: Path, results) -> None:
    fig, axes = plt.subplots(len(results), 1, figsize=(12, 1.2 + 1.1 * len(results)), squeeze=False, sharex=True)
    for ax, r in zip(axes[:, 0], results):
        ax.imshow(r.masks.T.astype(float), aspect="auto", cmap="Reds", vmin=0, vmax=1, interpolation="nearest")
        ax.set_yticks(range(6), AXES, fontsize=7)
        ax.set_title(f"{r.name}: non-localizable axes along the route", fontsize=9)
    axes[-1, 0].set_xlabel("step (0.1 s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_map(stem: Path, rec, trajectory: np.ndarray, every: int = 10) -> list[Path]:
    """Scans accumulated at the estimated poses, as PLY and a top view: a corrupted map shows. Returns
    the two files."""
    T_b_s = rec.T_b_s
    pts = [
        rec.scans[k] @ (trajectory[k] @ T_b_s)[:3, :3].T + (trajectory[k] @ T_b_s)[:3, 3]
        for k in range(0, len(rec.scans), every)
    ]
    cloud = np.concatenate(pts)
    trimesh.PointCloud(cloud).export(str(stem) + ".ply")
    fig, ax = plt.subplots(figsize=(12, 5))
    keep = cloud[:, 2] < trajectory[:, 2, 3].max() + 1.0  # below the roof: walls and floor edges
    draw_from_above(ax, cloud[keep], cloud[keep, 2], cmap="viridis")
    ax.set_aspect("equal")
    ax.set_title(f"map from the estimate: {stem.name}")
    fig.tight_layout()
    fig.savefig(str(stem) + ".png", dpi=110)
    plt.close(fig)
    return [Path(str(stem) + ".ply"), Path(str(stem) + ".png")]


def plot_seeds(path: Path, summary: list[dict]) -> None:
    """Each detector's ATE on every drive, one line a drive: a detector that is better on every
    drive is seen to be, whatever the spread between drives."""
    fig, ax = plt.subplots(figsize=(1.6 + 1.1 * len(summary), 4.2))
    names = [r["detector"] for r in summary]
    ate = np.array([r["ate_m"] for r in summary])  # (detectors, seeds)
    for k, seed in enumerate(summary[0]["seeds"]):
        ax.plot(
            range(len(names)),
            ate[:, k],
            "o-",
            color=plt.cm.viridis(k / max(1, ate.shape[1] - 1)),
            alpha=0.7,
            label=f"seed {seed}",
        )
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    ax.set_ylabel("ATE (m)")
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%.3g"))
    ax.set_title(f"ATE over {ate.shape[1]} drives")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_families(path: Path, families) -> None:
    """Per scene family, each row's mean ATE over its drives as a bar and its worst drive as a tick
    (families.FamilyVerdict): where the default stands against its parts, family by family."""
    families = [f for f in families if f.ate]
    rows = [r for r in families[0].ate if r != "odometry only"]
    fig, ax = plt.subplots(figsize=(2.0 + 1.0 * len(families), 4.5))
    width = 0.8 / len(rows)
    for n, row in enumerate(rows):
        x = np.arange(len(families)) + (n - (len(rows) - 1) / 2) * width
        have = [bool(f.ate.get(row)) for f in families]
        means = [f.mean(row) if h else np.nan for f, h in zip(families, have)]
        worst = [f.worst(row) if h else np.nan for f, h in zip(families, have)]
        color = plt.cm.tab10(n)
        ax.bar(x, means, width, color=color, label=row)
        ax.plot(x, worst, "_", color="k", markersize=6)
    ax.set_xticks(range(len(families)), [f.family for f in families], rotation=30, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("ATE (m): mean bar, worst drive tick")
    ax.set_title("every scene family: each row's ATE over its drives")
    ax.legend(fontsize=7, ncol=3)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
