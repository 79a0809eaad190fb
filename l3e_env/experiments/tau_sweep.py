"""The eigenvalue threshold sweep: ATE against tau in several scenes (and against DCReg's kappa), with
the learned detector, full ICP and odometry alone as reference lines. It shows whether one tau serves
every scene.

Each scene is driven and registered once; every tau and kappa only re-runs the fusion.
"""

from __future__ import annotations

import json
from pathlib import Path

from l3e_env.config import FusionSettings, OdometryConfig
from l3e_env.detection.detectors import DCRegDetector, EigenvalueDetector, make_detector, registration_of
from l3e_env.sim.odometry import odometry_fusion_config

from .drive import DriveRecord, record_run, register_sequence
from .fuse import fuse_recording, odometry_only

DEFAULT_TAUS = (10, 20, 30, 50, 70, 90, 110, 150, 200, 300)
DEFAULT_KAPPAS = (3, 5, 10, 20, 50, 100, 300, 1000)


def run_sweep(
    out_dir: str | Path,
    scenes: list[str],
    taus: tuple[float, ...] = DEFAULT_TAUS,
    references: tuple[str, ...] = ("learned", "none"),
    recordings: dict[str, str] | None = None,
    seed: int = 0,
    progress: bool = True,
    fusion_settings: FusionSettings = FusionSettings(),
    kappas: tuple[float, ...] = DEFAULT_KAPPAS,
) -> dict:
    """Returns {scene: {"taus": [...], "eigen_ate": [...], "kappas": [...], "dcreg_ate": [...],
    "<reference>": ate, ...}} and writes sweep.json and tau_sweep.png into out_dir (recordings are saved
    there for re-use). `kappas`: DCReg's condition ratio thresholds (none: DCReg left out).
    `fusion_settings`: every fusion's."""
    fusion = odometry_fusion_config(OdometryConfig(), fusion_settings)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict] = {}
    for scene in scenes:
        given = (recordings or {}).get(scene)
        rec = DriveRecord.load(given) if given else record_run(scene, seed=seed, progress=progress)
        if not given:
            rec.save(out / f"recording_{scene}.npz")
        refs = [make_detector(r) for r in references]
        regs = register_sequence(rec, registration_of(refs), progress)
        eigen = fuse_recording(rec, [EigenvalueDetector(t) for t in taus], regs, fusion=fusion, progress=False)
        dcreg = fuse_recording(rec, [DCRegDetector(k) for k in kappas], regs, fusion=fusion, progress=False)
        refs = fuse_recording(rec, refs, regs, fusion=fusion, progress=False)
        row = {
            **fusion_settings.record(),
            "taus": list(map(float, taus)),
            "eigen_ate": [r.ate for r in eigen],
            "eigen_flagged": [r.masks.mean(axis=0).tolist() for r in eigen],
            "kappas": list(map(float, kappas)),
            "dcreg_ate": [r.ate for r in dcreg],
            "dcreg_flagged": [r.masks.mean(axis=0).tolist() for r in dcreg],
            "odometry only": odometry_only(rec).ate,
        }
        for name, r in zip(references, refs):
            row[name] = r.ate
            row[f"{name}_flagged"] = r.masks.mean(axis=0).tolist()
        results[rec.scene] = row
        if progress:
            print(
                f"{rec.scene}: "
                + ", ".join(f"tau {t:g}: {a:.2f} m" for t, a in zip(taus, row["eigen_ate"]))
                + "; "
                + ", ".join(f"kappa {k:g}: {a:.2f} m" for k, a in zip(kappas, row["dcreg_ate"]))
                + "; "
                + ", ".join(f"{n}: {row[n]:.2f} m" for n in [*references, "odometry only"])
            )
    (out / "sweep.json").write_text(json.dumps(results, indent=1))
    plot_sweep(out / "tau_sweep.png", results, references)
    return results


def beaten_everywhere(results: dict, reference: str = "learned") -> list[float]:
    """The taus whose ATE is at most the reference's in every scene (empty: no single tau does)."""
    taus = next(iter(results.values()))["taus"]
    return [t for i, t in enumerate(taus) if all(r["eigen_ate"][i] <= r[reference] for r in results.values())]


def plot_sweep(path: Path, results: dict, references: tuple[str, ...]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 4.4), squeeze=False)
    for i, (ax, (scene, row)) in enumerate(zip(axes[0], results.items())):
        handles = ax.plot(row["taus"], row["eigen_ate"], "o-", c="tab:blue", label="eigenvalue detector (tau)")
        for k, name in enumerate([*references, "odometry only"]):
            handles.append(ax.axhline(row[name], ls=["-", "--", ":"][k % 3], c=f"C{k + 1}", label=name))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("eigenvalue threshold tau")
        ax.set_ylabel("ATE [m]")
        ax.set_title(scene)
        ax.grid(alpha=0.3, which="both")
        if row.get("kappas"):  # DCReg's kappa on an axis of its own, along the top
            top = ax.twiny()
            handles += top.plot(row["kappas"], row["dcreg_ate"], "s-", c="tab:purple", label="DCReg (kappa)")
            top.set_xscale("log")
            top.set_xlabel("DCReg condition ratio kappa", color="tab:purple")
        if i == 0:
            ax.legend(handles=handles, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
