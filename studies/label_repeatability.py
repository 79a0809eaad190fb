"""How repeatable are the Monte-Carlo labels? The ceiling any classifier's scores meet.

Run: python studies/label_repeatability.py --dataset data/l3e48 [--scenes mine-0,cave-0,cave-1]
     [--children 200] [--workers 2] [--seed 1] [--out errors.npz] [--translation 0.1,0.05,0.04]

Each parent pose of the chosen scenes is labelled again with the dataset's own sensor, label and
registration settings, but with another draw of the M children (and of the range noise). The
second labels are then scored against the stored ones exactly as a classifier is: per-axis
accuracy and F1, averaged over the axes as in Table III. A classifier that predicted the second
draw perfectly would score this against the first, so a test F1 far above it would be luck.
The reference in the same run is the stored labels scored against themselves (1.0).
--translation repeats the comparison with other x/y/z label thresholds (both draws relabelled
from their stored mean errors), to see which threshold gives labels that repeat.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from tqdm import tqdm

from l3e_env.config import LidarConfig, from_dict
from l3e_env.data.dataset import LabelDataset
from l3e_env.data.generation import scene_tools
from l3e_env.localizability.labels import AXES, LabelConfig, label_parent
from l3e_env.localizability.registration import RegistrationConfig, RegistrationError
from l3e_env.model.scores import axis_scores, mean_scores
from l3e_env.model.training import split_indices
from scenes import TEST_SCENES


def relabel(job: tuple[str, np.ndarray, tuple[int, int], dict, int]) -> np.ndarray:
    """Mean registration errors (6,) of one parent pose with a fresh draw of children."""
    scene_name, T_w_p, seed, settings, children = job
    _, _, lidar = scene_tools(scene_name, from_dict(LidarConfig, settings["lidar"]))
    labels = from_dict(LabelConfig, {**settings["labels"], "children": children})
    registration = from_dict(RegistrationConfig, settings["registration"])
    try:
        return label_parent(lidar, T_w_p, np.random.default_rng(seed), labels, registration).errors
    except RegistrationError:
        return np.full(6, np.nan)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--scenes", default=",".join(TEST_SCENES))
    ap.add_argument("--children", type=int, default=None, help="default: the dataset's M")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", help="save both draws' mean errors here (.npz)")
    ap.add_argument("--translation", default="", help="other x/y/z thresholds to compare, in m, comma-separated")
    args = ap.parse_args()

    data = LabelDataset(args.dataset)
    settings = data.manifest["settings"]
    children = args.children or settings["labels"]["children"]
    names = data.manifest["scenes"]
    scene_of_row = np.asarray(data.arrays["scene"])
    poses = data.poses
    thresholds = data.label_config.threshold_vector()
    rows = split_indices(data, args.scenes.split(","))
    jobs = [(names[scene_of_row[i]], poses[i], (args.seed, int(i)), settings, children) for i in rows]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        errors = np.array(list(tqdm(pool.map(relabel, jobs, chunksize=4), total=len(jobs), desc="relabelling")))
    seconds = time.perf_counter() - t0
    ok = np.isfinite(errors).all(axis=1)
    if args.out:
        np.savez(args.out, rows=rows, stored=data.errors[rows], again=errors, thresholds=thresholds)
    first, second = data.labels[rows][ok], (errors[ok] > thresholds).astype(np.uint8)

    print(
        f"{args.dataset}: {ok.sum()} parents of {args.scenes} relabelled with M = {children} "
        f"in {seconds:.0f} s ({(~ok).sum()} could not be registered)"
    )
    same = mean_scores(axis_scores(first, first))
    scores = axis_scores(first, second)
    means = mean_scores(scores)
    print(f"{'axis':6s} {'pos 1st':>8s} {'pos 2nd':>8s} {'accuracy':>9s} {'F1':>6s} {'error corr':>11s}")
    for a, axis in enumerate(AXES):
        corr = np.corrcoef(data.errors[rows][ok, a], errors[ok, a])[0, 1]
        print(
            f"{axis:6s} {first[:, a].sum():8d} {second[:, a].sum():8d} {scores['accuracy'][a]:9.3f} "
            f"{scores['f1'][a]:6.3f} {corr:11.3f}"
        )
    print(
        f"mean   accuracy {means['accuracy']:.3f} F1 {means['f1']:.3f}  (reference, stored vs stored: "
        f"accuracy {same['accuracy']:.3f} F1 {same['f1']:.3f}; ratio F1 {means['f1'] / same['f1']:.2f})"
    )
    for t in filter(None, args.translation.split(",")):
        other = thresholds.copy()
        other[:3] = float(t)
        a, b = data.errors[rows][ok] > other, errors[ok] > other
        s = axis_scores(a, b)
        m = mean_scores(s)
        print(
            f"x/y/z threshold {float(t):.3f} m: positives {a[:, :3].sum(0)} / {b[:, :3].sum(0)}, "
            f"F1 x/y/z {np.round(s['f1'][:3], 3)}, mean over axes accuracy {m['accuracy']:.3f} F1 {m['f1']:.3f}"
        )


if __name__ == "__main__":
    main()
