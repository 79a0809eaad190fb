"""The eigenvalue threshold sweep: ATE against tau in several scenes (and against DCReg's kappa, X-ICP's
localizability threshold and DRPM's signal-to-noise factor where asked), with
the learned detector, full ICP and odometry alone as reference lines. It shows whether one tau serves
every scene.

Each scene is driven and registered once; every tau and kappa only re-runs the fusion.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from l3e_env.config import FusionSettings, OdometryConfig
from l3e_env.detection.detectors import (
    DCRegDetector,
    DRPMDetector,
    EigenvalueDetector,
    XICPDetector,
    make_detector,
    registration_of,
)
from l3e_env.detection.pipeline import Keyframes
from l3e_env.sim.odometry import odometry_fusion_config

from .drive import DriveOptions, DriveRecord, record_run, register_sequence
from .fuse import fuse_recording, odometry_only

DEFAULT_TAUS = (10, 20, 30, 50, 70, 90, 110, 150, 200, 300)
DEFAULT_KAPPAS = (3, 5, 10, 20, 50, 100, 300, 1000)
DEFAULT_XICPS = (30, 60, 100, 150, 300)  # X-ICP's localizability threshold (its published 300 among them)
DEFAULT_DRPMS = (1, 3, 10, 30, 100)  # DRPM's signal-to-noise factor s


@dataclass(frozen=True)
class SweepOptions:
    """The thresholds swept (an empty tuple leaves that test out), the detectors drawn as reference lines,
    the drives' seed and every fusion's settings."""

    taus: tuple[float, ...] = DEFAULT_TAUS
    kappas: tuple[float, ...] = DEFAULT_KAPPAS
    xicps: tuple[float, ...] = ()
    drpms: tuple[float, ...] = ()
    references: tuple[str, ...] = ("learned", "none")
    seed: int = 0
    fusion_settings: FusionSettings = FusionSettings()

    def check(self) -> None:
        """ValueError naming a swept threshold its test cannot take (tau <= 0, kappa <= 1, ...), before a drive."""
        for field_name, make, _ in SWEPT:
            for value in getattr(self, field_name):
                try:
                    make(value)
                except ValueError as exc:
                    raise ValueError(f"{field_name}: {exc}") from None


# each swept test: its thresholds' option, the detector made at one threshold, and its row's key
SWEPT = (
    ("taus", EigenvalueDetector, "eigen"),
    ("kappas", DCRegDetector, "dcreg"),
    ("xicps", XICPDetector, "xicp"),
    ("drpms", DRPMDetector, "drpm"),
)


def run_sweep(
    out_dir: str | Path,
    scenes: list[str],
    options: SweepOptions = SweepOptions(),
    recordings: dict[str, str] | None = None,
    progress: bool = True,
) -> dict:
    """Returns {scene: {"taus": [...], "eigen_ate": [...], "kappas": [...], "dcreg_ate": [...], "xicps":
    [...], "xicp_ate": [...], "drpms": [...], "drpm_ate": [...], "<reference>": ate, ...}} and writes
    sweep.json and tau_sweep.png into out_dir (recordings are saved there for re-use)."""
    options.check()
    fusion = odometry_fusion_config(OdometryConfig(), options.fusion_settings)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict] = {}
    for scene in scenes:
        given = (recordings or {}).get(scene)
        rec = DriveRecord.load(given) if given else record_run(scene, DriveOptions(seed=options.seed), progress)
        if not given:
            rec.save(out / f"recording_{scene}.npz")
        refs = [make_detector(r) for r in options.references]
        keyframes = Keyframes(distance=options.fusion_settings.keyframe_distance or 0.0)  # set by its __post_init__
        regs = register_sequence(rec, registration_of(refs), progress, keyframes)
        row: dict = {"fusion": options.fusion_settings.record(), "odometry only": odometry_only(rec).ate}
        for field_name, make, key in SWEPT:
            values = getattr(options, field_name)
            swept = fuse_recording(
                rec, [make(v) for v in values], regs, fusion, progress=False, settings=options.fusion_settings
            )
            row[field_name] = list(map(float, values))
            row[f"{key}_ate"] = [r.ate for r in swept]
            row[f"{key}_flagged"] = [r.masks.mean(axis=0).tolist() for r in swept]
        fused = fuse_recording(rec, refs, regs, fusion, progress=False, settings=options.fusion_settings)
        for name, r in zip(options.references, fused):
            row[name] = r.ate
            row[f"{name}_flagged"] = r.masks.mean(axis=0).tolist()
        results[rec.scene] = row
        if progress:
            print(sweep_line(rec.scene, row, options.references))
    (out / "sweep.json").write_text(json.dumps(results, indent=1))
    plot_sweep(out / "tau_sweep.png", results, options.references)
    return results


def sweep_line(scene: str, row: dict, references: tuple[str, ...]) -> str:
    """One scene's ATE at each threshold of each test and of the references, as a line."""
    parts = [
        ", ".join(f"{key} {v:g}: {a:.2f} m" for v, a in zip(row[field_name], row[f"{key}_ate"]))
        for field_name, _, key in SWEPT
        if row[field_name]
    ]
    parts.append(", ".join(f"{n}: {row[n]:.2f} m" for n in [*references, "odometry only"]))
    return f"{scene}: " + "; ".join(parts)


def beaten_everywhere(results: dict, reference: str = "learned") -> list[float]:
    """The taus whose ATE is at most the reference's in every scene (empty: no single tau does)."""
    taus = next(iter(results.values()))["taus"]
    return [t for i, t in enumerate(taus) if all(r["eigen_ate"][i] <= r[reference] for r in results.values())]


# how each swept test's threshold is named on the plot
SWEPT_LABELS = {
    "eigen": "eigenvalue threshold tau",
    "dcreg": "DCReg condition ratio kappa",
    "xicp": "X-ICP localizability threshold",
    "drpm": "DRPM signal-to-noise factor s",
}


def plot_sweep(path: Path, results: dict, references: tuple[str, ...]) -> None:
    """ATE against each swept test's threshold: a row per test, a column per scene, the references and
    odometry alone as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(results.values()))
    tests = [(field_name, key) for field_name, _, key in SWEPT if first.get(field_name)]
    fig, axes = plt.subplots(
        len(tests), len(results), figsize=(5 * len(results), 3.6 * len(tests)), squeeze=False, sharey="col"
    )
    for j, (scene, row) in enumerate(results.items()):
        for i, (field_name, key) in enumerate(tests):
            ax = axes[i, j]
            handles = ax.plot(row[field_name], row[f"{key}_ate"], "o-", c="tab:blue", label=key)
            for k, name in enumerate([*references, "odometry only"]):
                handles.append(ax.axhline(row[name], ls=["-", "--", ":"][k % 3], c=f"C{k + 1}", label=name))
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(SWEPT_LABELS[key])
            ax.set_ylabel("ATE [m]")
            ax.set_title(scene)
            ax.grid(alpha=0.3, which="both")
            if j == 0:
                ax.legend(handles=handles, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
