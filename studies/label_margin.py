"""How close to their thresholds do the labels lie, and how well must a model predict the mean
registration error to reach a given F1?

Run: python studies/label_margin.py --dataset data/l3e48b --dataset data/level-b --dataset data/mine-test
     [--checkpoint PATH] [--noise 0.1,0.2,0.3,0.5] [--draws 200] [--plot margin.png]

A label is e > threshold on one axis's mean registration error e over the M children. An estimator
that knew e exactly would score F1 1 (the reference in the same run); one whose estimate is
e * exp(N(0, sigma^2)) scores less, and the more of a split's labels lie near their thresholds, the
less. For the train, validation and test scenes of the classifier's split this prints how many
positives lie within 1.25x of the threshold, the F1 and accuracy such noisy estimators score
(averaged over the axes as in Table III, and over --draws draws of the noise), and the sigma at
which the mean F1 falls to 0.70, the issue's target.

Then the checkpoint's own probabilities on each split (default: the shipped model): mean F1 at its
stored thresholds; at the thresholds best for that very split (no threshold choice can do better
with these probabilities); AUROC per axis (how well they rank, whatever the threshold); and the
"equivalent sigma", the noise of the estimator with the same mean F1 at the stored thresholds; and
how many of its false flags lie far from the threshold (where no label noise can excuse them);
the mean F1 it would score with x and y exact and its other axes as they are (what the rarer axes
cost the mean); and, as a model-free score, the AUROC of the sensor's tilt from the vertical (what
an IMU knows) per axis.
"""

from __future__ import annotations

import argparse

import numpy as np

from l3e_env.data.dataset import error_ratios, open_datasets
from l3e_env.experiments.table3 import split_rows
from l3e_env.localizability.labels import AXES
from l3e_env.model.classifier import Classifier, up_vector
from l3e_env.model.scores import auroc, axis_scores, best_thresholds, mean_scores
from l3e_env.model.training import predict_dataset

TARGET_F1 = 0.70
SIGMA_GRID = np.round(np.arange(0.0, 3.001, 0.05), 2)


def noisy_scores(ratios: np.ndarray, sigma: float, draws: int, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Per-axis F1 and mean scores of the estimator e * exp(N(0, sigma^2)), averaged over draws."""
    labels = ratios > 1
    f1, means = [], []
    for _ in range(draws if sigma > 0 else 1):
        estimate = ratios * np.exp(rng.normal(0.0, sigma, ratios.shape))
        scores = axis_scores(labels, estimate > 1)
        f1.append(scores["f1"])
        means.append(mean_scores(scores))
    return np.nanmean(f1, axis=0), {k: float(np.mean([m[k] for m in means])) for k in means[0]}


def tilt_deg(poses: np.ndarray) -> np.ndarray:
    """Angle between each sensor's z axis and the world's vertical, degrees."""
    return np.degrees(np.arccos(np.clip(up_vector(poses)[:, 2], -1.0, 1.0)))


def sigma_at(f1_curve: np.ndarray, f1: float) -> float:
    """The sigma of SIGMA_GRID at which the (falling) mean-F1 curve reaches f1; inf if it never falls that low."""
    if f1 < f1_curve[-1]:
        return float("inf")
    return float(np.interp(f1, f1_curve[::-1], SIGMA_GRID[::-1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", action="append", required=True, help="repeat to read several as one")
    ap.add_argument("--checkpoint", help="default: the shipped model")
    ap.add_argument("--noise", default="0.1,0.2,0.3,0.5", help="sigmas to print, comma-separated")
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--plot", help="write mean F1 against sigma per split here (.png)")
    args = ap.parse_args()

    data = open_datasets(args.dataset)
    clf = Classifier.load(args.checkpoint)
    splits = split_rows(data, clf.meta["training"])
    ratios_all = error_ratios(data)
    tilt_all = tilt_deg(data.poses)
    rng = np.random.default_rng(args.seed)
    sigmas = [float(s) for s in args.noise.split(",") if s]
    curves: dict[str, np.ndarray] = {}
    model_f1: dict[str, float] = {}

    print(f"{data.name}: mean errors over label thresholds; noisy estimators over {args.draws} draws")
    for split, rows in splits.items():
        ratios = ratios_all[rows]
        labels = ratios > 1
        near = ((ratios > 1) & (ratios <= 1.25)).sum(0) / np.maximum(labels.sum(0), 1)
        curves[split] = np.array([noisy_scores(ratios, s, args.draws, rng)[1]["f1"] for s in SIGMA_GRID])
        print(f"\n{split}: {len(rows)} scans")
        print(f"  {'':24s}" + "".join(f"{a:>7s}" for a in AXES) + "   mean")
        print(f"  {'positives':24s}" + "".join(f"{n:7d}" for n in labels.sum(0)))
        print(f"  {'of them within 1.25x':24s}" + "".join(f"{v:7.2f}" for v in near))
        for sigma in [0.0, *sigmas]:
            f1, means = noisy_scores(ratios, sigma, args.draws, rng)
            label = "exact estimate (reference)" if sigma == 0 else f"estimate, sigma {sigma:.2f}"
            print(
                f"  {label:24s}"
                + "".join(f"{v:7.2f}" for v in f1)
                + f"   F1 {means['f1']:.3f} accuracy {means['accuracy']:.3f}"
            )
        print(
            f"  mean F1 falls to {TARGET_F1} at sigma {sigma_at(curves[split], TARGET_F1):.2f} "
            f"(the estimate within a factor {np.exp(sigma_at(curves[split], TARGET_F1)):.2f}, one sigma)"
        )

        probs = predict_dataset(clf.model, data, rows, progress=True)
        flagged = probs > clf.thresholds
        stored = axis_scores(labels, flagged)
        own = axis_scores(labels, probs > best_thresholds(labels, probs))
        model_f1[split] = mean_scores(stored)["f1"]
        print(
            f"  {'model, stored thresh.':24s}"
            + "".join(f"{v:7.2f}" for v in stored["f1"])
            + f"   F1 {model_f1[split]:.3f} accuracy {mean_scores(stored)['accuracy']:.3f}"
        )
        print(
            f"  {'model, best for split':24s}"
            + "".join(f"{v:7.2f}" for v in own["f1"])
            + f"   F1 {mean_scores(own)['f1']:.3f} accuracy {mean_scores(own)['accuracy']:.3f}"
        )
        print(f"  {'model AUROC':24s}" + "".join(f"{auroc(labels[:, a], probs[:, a]):7.2f}" for a in range(6)))
        exact_xy = flagged.copy()
        exact_xy[:, :2] = labels[:, :2]
        print(
            f"  {'model, x and y exact':24s}"
            + "".join(f"{v:7.2f}" for v in axis_scores(labels, exact_xy)["f1"])
            + f"   F1 {mean_scores(axis_scores(labels, exact_xy))['f1']:.3f}"
        )
        tilt = tilt_all[rows]
        print(
            f"  {'sensor tilt AUROC':24s}"
            + "".join(f"{auroc(labels[:, a], tilt):7.2f}" for a in range(6))
            + f"   median tilt {np.median(tilt):.1f} deg"
        )
        print(
            f"  the model's mean F1 equals that of an estimate with sigma "
            f"{sigma_at(curves[split], model_f1[split]):.2f}"
        )
        false_flags, misses = flagged & ~labels, ~flagged & labels
        print(
            f"  false flags {false_flags.sum()}, of them {(false_flags & (ratios < 0.5)).sum()} on errors under half "
            f"the threshold; misses {misses.sum()}, of them {(misses & (ratios <= 1.25)).sum()} within 1.25x"
        )

    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for split, curve in curves.items():
            (line,) = ax.plot(SIGMA_GRID, curve, label=f"{split}: noisy estimate of the error")
            ax.axhline(model_f1[split], color=line.get_color(), ls="--", lw=1, label=f"{split}: model")
        ax.axhline(TARGET_F1, color="k", ls=":", lw=1, label=f"target {TARGET_F1}")
        ax.set_xlabel("sigma of ln(estimated error / true mean error)")
        ax.set_ylabel("F1, mean over the six axes")
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
        print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
