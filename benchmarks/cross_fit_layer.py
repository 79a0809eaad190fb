"""Does the constraint layer carry over to unseen families better when it is fitted on logits of
networks that never saw the scan's family (cross-fitting, as in stacked generalisation)?

The shipped layer is fitted on the training scenes, where the network's logits are in-sample and
look better than they will on a family it never saw. Here each training family is held out of one
fold network (trained on the other families), whose logits on that family stand in for the
network's on an unseen one. Three layers, all fed the shipped network's logits at inference, with
thresholds from the validation scenes (F-beta with the checkpoint's beta):
- in-sample: fitted on the shipped network's own logits (the shipped recipe);
- cross-fitted: fitted on the fold networks' held-out logits;
- mean: fitted on the mean of the two.
Printed: accuracy / F1 (means over axes) on the validation scenes, the test families and each scene
family of every --other dataset (families no model was trained on).

Fold networks (the shipped base network's recipe, 16 epochs, about 22 min each):
  l3e train --config benchmarks/cross_fit_fold_a.yaml --dataset data/l3e48b --dataset data/level-b \
    --out runs/oof/netA --epochs 16          (the same with fold_b and runs/oof/netB)
Run: python benchmarks/cross_fit_layer.py --checkpoint runs/resunet-cons2/model.pt \
       --fold runs/oof/netA/model.pt --fold runs/oof/netB/model.pt \
       --dataset data/l3e48b --dataset data/level-b --dataset data/mine-test \
       --other data/rooms48 --other data/rooms-level
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from l3e_env.model.classifier import load_checkpoint, model_from_checkpoint
from l3e_env.model.constraints import AxisStacker, fit_stacker
from l3e_env.data.dataset import DatasetUnion, LabelDataset, open_datasets
from l3e_env.experiments.table3 import family_rows, split_rows
from l3e_env.model.scores import axis_scores, best_thresholds, mean_scores
from l3e_env.model.training import network_parts
from scenes import scene_family


def held_out_logits(folds: list[str], data: LabelDataset | DatasetUnion, rows: np.ndarray, seed: int) -> np.ndarray:
    """Each training row's logits from the one fold network whose training left out its family."""
    scene_of_row = np.asarray(data.manifest["scenes"])[np.asarray(data.arrays["scene"])[rows]]
    out = np.full((len(rows), 6), np.nan)
    for path in folds:
        state = load_checkpoint(path)
        seen = {scene_family(s) for s in state["training"]["train_scenes"]}
        held = np.array([scene_family(s) not in seen for s in scene_of_row])
        if np.isfinite(out[held]).any():
            raise SystemExit(f"{path} leaves out a family that another fold leaves out too")
        out[held] = network_parts(model_from_checkpoint(state, path), data, rows[held], seed)[0]
        print(f"{path}: logits of {held.sum()} held-out rows "
              f"({', '.join(sorted({scene_family(s) for s in scene_of_row[held]}))})", flush=True)
    missing = sorted({scene_family(s) for s in scene_of_row[np.isnan(out[:, 0])]})
    if missing:
        raise SystemExit(f"no fold leaves out the families {missing}: every training family needs one")
    return out


def probabilities(stacker: AxisStacker, logits: np.ndarray, features: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return torch.sigmoid(stacker(torch.as_tensor(logits, dtype=torch.float32),
                                     torch.as_tensor(features, dtype=torch.float32))).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True, help="a model with the constraint layer")
    ap.add_argument("--fold", action="append", required=True, help="a fold network's model.pt; repeat")
    ap.add_argument("--dataset", action="append", required=True, help="repeat to read several as one")
    ap.add_argument("--other", action="append", default=[], help="a dataset of families no model saw; repeat")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(2)

    state = load_checkpoint(args.checkpoint)
    model = model_from_checkpoint(state, args.checkpoint)
    if not model.config.constraints:
        raise SystemExit(f"{args.checkpoint} has no constraint layer (make one with 'l3e fit-constraints')")
    data = open_datasets(args.dataset)
    rows = split_rows(data, state["training"])
    parts = {name: network_parts(model, data, r, args.seed) for name, r in rows.items()}
    labels = {name: data.labels[r] for name, r in rows.items()}
    for folder in args.other:
        other = open_datasets(folder)
        for fam, r in family_rows(other).items():
            name = f"{fam} ({folder})"
            parts[name], labels[name] = network_parts(model, other, r, args.seed), other.labels[r]
    held = held_out_logits(args.fold, data, rows["train"], args.seed)

    beta = float(state.get("threshold_beta", 1.0))
    own, features = parts["train"]
    variants = {"in-sample (shipped recipe)": own, "cross-fitted": held, "mean of the two": (own + held) / 2}
    shown = [name for name in parts if name != "train"]
    print(f"\naccuracy / F1, means over axes; thresholds F{beta:g}-best on the validation scenes")
    print(f"{'layer fitted on':28s}" + "".join(f"{name:>28s}" for name in shown))
    for variant, train_logits in variants.items():
        stacker = fit_stacker(train_logits, features, labels["train"])
        thresholds = best_thresholds(labels["valid"], probabilities(stacker, *parts["valid"]), beta=beta)
        cells = []
        for name in shown:
            scores = mean_scores(axis_scores(labels[name], probabilities(stacker, *parts[name]) > thresholds))
            cells.append(f"{scores['accuracy']:.3f} / {scores['f1']:.3f}")
        print(f"{variant:28s}" + "".join(f"{c:>28s}" for c in cells), flush=True)


if __name__ == "__main__":
    main()
