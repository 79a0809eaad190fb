"""Top-view figures: a localizability map per axis, planned paths, and the routes episodes took."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from l3e_env.localizability.labels import AXES  # noqa: E402
from l3e_env.sim.render import wall_points  # noqa: E402
from scenes import Scene  # noqa: E402

from .freespace import FreeSpace  # noqa: E402
from .locmap import LocalizabilityMap  # noqa: E402


def _floor_plan(ax, scene: Scene, space: FreeSpace | None = None) -> None:
    if space is not None:
        lo = space.origin - space.resolution / 2
        hi = lo + np.array(space.shape) * space.resolution
        ax.imshow(
            space.free.T,
            origin="lower",
            extent=(lo[0], hi[0], lo[1], hi[1]),
            cmap="Greys_r",
            vmin=-1.5,
            vmax=1,
            interpolation="nearest",
        )
    walls = wall_points(scene.mesh, 60_000)
    ax.scatter(walls[:, 0], walls[:, 1], s=2, c="0.25", linewidths=0, rasterized=True)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def plot_locmap(path: str | Path, scene: Scene, locmap: LocalizabilityMap, space: FreeSpace | None = None) -> None:
    """Six panels: per axis, the detector's non-localizability score averaged over headings, with a
    short tick per position towards the heading where the detector masks that axis most."""
    fig, axes = plt.subplots(3, 2, figsize=(14, 12), squeeze=False)
    p = np.nanmean(locmap.probabilities, axis=1)
    masked = locmap.masked
    for i, ax in enumerate(axes.ravel()):
        _floor_plan(ax, scene, space)
        sc = ax.scatter(
            locmap.positions[:, 0], locmap.positions[:, 1], c=p[:, i], cmap="magma_r", vmin=0, vmax=1, s=14, marker="s"
        )
        worst = locmap.yaws[np.argmax(masked[:, :, i], axis=1)]
        show = masked[:, :, i].max(axis=1) > 0
        d = 0.6 * np.stack([np.cos(worst), np.sin(worst)], -1)[show]
        ax.quiver(
            *locmap.positions[show].T, *d.T, angles="xy", scale_units="xy", scale=1, width=0.002, color="tab:cyan"
        )
        ax.set_title(f"{AXES[i]}: masked at {100 * masked[:, :, i].mean():.0f}% of poses")
        # the detector's own scale: scanmc's and the cascade's scores are flagged above 0.5, the classifier's
        # probabilities above its stored thresholds
        fig.colorbar(sc, ax=ax, shrink=0.7, label=f"non-localizability (masked above {locmap.thresholds[i]:.2f})")
    judged = (
        ""
        if locmap.estimated is None or not locmap.estimated.any()
        else f"; scanmc judged {100 * locmap.estimated.mean():.0f}% of the poses"
    )
    fig.suptitle(
        f"{scene.name}: localizability map ({len(locmap.positions)} positions x {len(locmap.yaws)} headings{judged})"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_paths(
    path: str | Path,
    scene: Scene,
    paths: dict[str, np.ndarray] | dict[str, list[np.ndarray]],
    space: FreeSpace | None = None,
    title: str = "",
    colors: dict[str, str] | None = None,
) -> None:
    """Named (K, 2+) paths over the floor plan; several paths may share a name (episodes)."""
    fig, ax = plt.subplots(figsize=(12, 6))
    _floor_plan(ax, scene, space)
    colors = colors or {}
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for j, (name, drawn) in enumerate(paths.items()):
        group = drawn if isinstance(drawn, list) else [drawn]
        for k, xy in enumerate(group):
            ax.plot(
                xy[:, 0],
                xy[:, 1],
                color=colors.get(name, cycle[j % len(cycle)]),
                lw=1.2,
                alpha=0.8,
                label=name if k == 0 else None,
            )
    ax.plot(*scene.start[:2], "go", ms=8, label="start")
    ax.plot(*scene.goal, "r*", ms=12, label="goal")
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title(title or scene.name)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_drift_check(
    path: str | Path, points: dict[str, tuple[np.ndarray, np.ndarray]], correlation: float | None
) -> None:
    """The drift the cost model expected of each episode's path against the final error the full
    pipeline measured, one colour a policy; the diagonal is where the two agree."""
    fig, ax = plt.subplots(figsize=(6, 5))
    top = 0.0
    for name, (expected, measured) in points.items():
        ax.scatter(expected, measured, s=18, alpha=0.8, label=name)
        top = max(top, float(np.max(expected, initial=0.0)), float(np.max(measured, initial=0.0)))
    ax.plot([0, top], [0, top], color="0.6", lw=1, ls="--", label="expected = measured")
    ax.set_xlabel("expected drift of the path walked [m] (planner's cost model)")
    ax.set_ylabel("final error of the fused estimate [m]")
    ax.set_title(
        "drift model against the pipeline" + ("" if correlation is None else f" (Pearson r = {correlation:.2f})")
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
