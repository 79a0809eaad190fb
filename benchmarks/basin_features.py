"""Does the constraint that survives the children's perturbation rank the labels better than the
whole scan's Hessian? A test of the constraint layer's inputs, with the shipped network as it is.

Run: python benchmarks/basin_features.py --dataset data/l3e48 --dataset data/level --dataset data/mine-test
     [--other data/rooms16] [--checkpoint C] [--cache basin.npz]

A child starts up to 10 deg (one sigma) of yaw and 5 deg of roll and pitch away from its parent, so a
surface r metres off starts some 0.17 r metres from where it belongs, and the registration's first
stage pairs points no further apart than 2 m. Far surfaces then pull ICP towards wrong pairs, which the
scan's Hessian, summed over every planar voxel whatever its range, does not know. The "basin" Hessian
weighs each planar voxel by the chance that its displacement under the children's rotation sigmas
stays within the first stage's correspondence distance (both read from the dataset's manifest):
erf(d / (sqrt(2) s)), s^2 = s_roll^2 (y^2 + z^2) + s_pitch^2 (x^2 + z^2) + s_yaw^2 (x^2 + y^2) + sum of
the translation sigmas squared. Its twelve features per level (log diag(H^-1), log eigenvalues) at the
shipped layer's levels (0.2 and 0.4 m voxels), and three range features (log median range, share of
points beyond 10 and 20 m), are added to the shipped layer's inputs. Per-axis logistic layers are fitted
on the training scans (l3e_env.model.constraints.fit_stacker, as `l3e fit-constraints` does), with and
without the network's logit; thresholds F1-best on the validation scans; every split is scored.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy.special import erf
from tqdm import tqdm

from l3e_env.model.classifier import DEFAULT_CHECKPOINT, load_checkpoint, model_from_checkpoint, model_input
from l3e_env.model.constraints import coarser_means, fit_stacker, hessian_features, surface_rows
from l3e_env.data.dataset import open_datasets
from l3e_env.localizability.labels import AXES
from l3e_env.model.scores import auroc, axis_scores, best_thresholds, mean_scores
from l3e_env.model.sparse import Level, voxelize
from l3e_env.model.training import split_indices
from scenes import TEST_SCENES, TRAIN_SCENES, VALIDATION_SCENES

LEVELS = 2  # the shipped layer's levels: 0.2 and 0.4 m voxels


def basin_sigmas(manifest: dict) -> tuple[np.ndarray, float, float]:
    """(roll, pitch, yaw) child sigmas in radians, the translation sigmas' squared sum and the first
    stage's correspondence distance, from a dataset's settings (a union lists its parts' labels)."""
    labels = manifest["settings"]["labels"]
    sigmas = {tuple(part["child_sigma"]) for part in (labels if isinstance(labels, list) else [labels])}
    if len(sigmas) != 1:
        raise SystemExit(f"the datasets' children are drawn with different sigmas: {sorted(sigmas)}")
    sigma = np.asarray(sigmas.pop(), dtype=np.float64)
    reach = float(manifest["settings"]["registration"]["max_correspondence_distance"][0])
    return np.radians(sigma[3:]), float((sigma[:3] ** 2).sum()), reach


def basin_hessians(level: Level, means: np.ndarray, batch_size: int, rotation: np.ndarray, translation: float,
                   reach: float) -> np.ndarray:
    """(B, 6, 6) point-to-plane Hessians over the planar voxels, each weighed by the chance that the
    children's perturbation leaves it within the correspondence distance."""
    rows = surface_rows(level, torch.from_numpy(means)).numpy().astype(np.float64)
    x, y, z = means.T
    spread = np.sqrt(rotation[0] ** 2 * (y**2 + z**2) + rotation[1] ** 2 * (x**2 + z**2)
                     + rotation[2] ** 2 * (x**2 + y**2) + translation)
    weight = erf(reach / (np.sqrt(2.0) * spread)) * rows[:, 6]  # 0 where the voxel is not planar
    groups = level.coords[:, 0].numpy()
    out = np.zeros((batch_size, 6, 6))
    for b in range(batch_size):
        j = rows[groups == b, :6]
        out[b] = (j * weight[groups == b, None]).T @ j
    return out


@torch.inference_mode()
def row_inputs(model, data, rows: np.ndarray, seed: int = 0, batch_size: int = 16) -> dict[str, np.ndarray]:
    """The network's logits, the shipped layer's features, the basin features and the range features
    of `rows`, each scan's points drawn as `l3e evaluate` draws them (seeded by (seed, row))."""
    rotation, translation, reach = basin_sigmas(data.manifest)
    out = {"logits": np.zeros((len(rows), 6)), "shipped": np.zeros((len(rows), 12 * LEVELS)),
           "basin": np.zeros((len(rows), 12 * LEVELS)), "range": np.zeros((len(rows), 3))}
    for start in tqdm(range(0, len(rows), batch_size), desc="features", leave=False):
        chunk = rows[start:start + batch_size]
        batch = [model_input(data.scan(int(i)), model.config, np.random.default_rng([seed, int(i)])) for i in chunk]
        logits, shipped = model.parts(batch, None, constraints=True)
        at = slice(start, start + len(chunk))
        out["logits"][at], out["shipped"][at] = logits.numpy(), shipped.numpy()
        level, means, _ = voxelize(batch, model.config.voxel)
        points = means.numpy().astype(np.float64)
        for k in range(LEVELS):
            hessians = basin_hessians(level, points, len(chunk), rotation, translation, reach)
            out["basin"][at, 12 * k:12 * (k + 1)] = hessian_features(hessians)
            if k + 1 < LEVELS:
                level, points = coarser_means(level, points)
        ranges = [np.linalg.norm(p.numpy(), axis=1) for p in batch]
        out["range"][at] = [(np.log(np.median(r)), (r > 10).mean(), (r > 20).mean()) for r in ranges]
    out["labels"] = np.asarray(data.labels[rows], dtype=np.float64)
    return out


VARIANTS = {"shipped inputs": ("shipped",), "+ basin": ("shipped", "basin"),
            "+ basin + range": ("shipped", "basin", "range")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", action="append", required=True, help="the splits' datasets, in order")
    parser.add_argument("--other", action="append", default=[], help="a dataset scored whole (unseen families)")
    parser.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    parser.add_argument("--cache", type=Path, help="npz of the inputs: written once, read after")
    args = parser.parse_args()
    if args.cache and args.cache.exists():
        with np.load(args.cache) as z:
            splits = {s: {k.split("/")[1]: z[k] for k in z.files if k.startswith(s + "/")}
                      for s in {k.split("/")[0] for k in z.files}}
    else:
        model = model_from_checkpoint(load_checkpoint(args.checkpoint), args.checkpoint)
        data = open_datasets(args.dataset)
        rows = {"train": TRAIN_SCENES, "valid": VALIDATION_SCENES, "test": TEST_SCENES}
        splits = {s: row_inputs(model, data, split_indices(data, scenes)) for s, scenes in rows.items()}
        for folder in args.other:
            other = open_datasets([folder])
            splits[Path(folder).name] = row_inputs(model, other, np.arange(len(other)))
        if args.cache:
            np.savez(args.cache, **{f"{s}/{k}": v for s, d in splits.items() for k, v in d.items()})
    names = list(splits)
    print(f"{'inputs':34s}" + "".join(f"{s + ' F1/acc':>16s}" for s in names)
          + "   test F1 " + " ".join(f"{a:>5s}" for a in AXES) + "   test AUROC")
    for with_logit in (True, False):
        for variant, parts in VARIANTS.items():
            inputs = {s: (d["logits"] * with_logit, np.concatenate([d[p] for p in parts], axis=1))
                      for s, d in splits.items()}
            stacker = fit_stacker(*inputs["train"], splits["train"]["labels"]).double()
            with torch.no_grad():
                probs = {s: torch.sigmoid(stacker(torch.as_tensor(lg), torch.as_tensor(f))).numpy()
                         for s, (lg, f) in inputs.items()}
            thresholds = best_thresholds(splits["valid"]["labels"], probs["valid"], beta=1.0)
            cells = [mean_scores(axis_scores(splits[s]["labels"], probs[s] > thresholds)) for s in names]
            test = axis_scores(splits["test"]["labels"], probs["test"] > thresholds)["f1"]
            ranks = [auroc(splits["test"]["labels"][:, a], probs["test"][:, a]) for a in range(6)]
            label = f"{variant}{'' if with_logit else ', no network logit'}"
            print(f"{label:34s}" + "".join(f"{c['f1']:>10.3f}/{c['accuracy']:.3f}" for c in cells)
                  + "   " + " ".join(f"{v:5.2f}" for v in np.nan_to_num(test))
                  + "   " + " ".join(f"{v:.2f}" for v in ranks))


if __name__ == "__main__":
    main()
