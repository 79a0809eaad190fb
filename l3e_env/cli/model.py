"""The classifier: training, Table III, symmetric thresholds, the constraint layer."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .options import add_device_option, sensor_name


def _cmd_train(args: argparse.Namespace) -> int:
    from l3e_env.config import from_dict, load_yaml
    from l3e_env.model.classifier import torch_device
    from l3e_env.model.training import TrainConfig, train

    torch_device(args.device)  # a missing GPU is named before anything is read or written
    cfg = load_yaml(TrainConfig, args.config) if args.config else TrainConfig()
    overrides = {
        k: v
        for k, v in {
            "epochs": args.epochs,
            "seed": args.seed,
            "optimizer": args.optimizer,
            "learning_rate": args.lr,
            "samples_per_epoch": args.samples_per_epoch,
            "threads": args.threads,
            "soft_labels": args.soft_labels,
            "group_dro": args.group_dro,
            "scale_augment": args.scale_augment,
        }.items()
        if v is not None
    }
    model = _asdict(cfg.model)
    if args.init:  # fine-tuning keeps the model settings of the checkpoint it starts from
        from l3e_env.model.classifier import ModelConfig, load_checkpoint
        from l3e_env.model.training import network_config

        start = from_dict(ModelConfig, load_checkpoint(args.init)["model"])
        model, overrides["init"] = _asdict(network_config(start)), args.init
        if start.constraints:
            print(
                f"{args.init} has a constraint layer: its network is fine-tuned without it; fit the layer "
                "again afterwards (l3e fit-constraints)"
            )
    model.update(_model_options(args))
    if args.distilled:  # the distillation sets' places join the training scenes
        from l3e_env.model.training import distilled_scenes

        overrides["train_scenes"] = list(dict.fromkeys([*cfg.train_scenes, *distilled_scenes(args.dataset)]))
    cfg = from_dict(TrainConfig, {**_asdict(cfg), **overrides, "model": model})
    print(
        f"training {cfg.model.architecture} on {' + '.join(args.dataset)} -> {Path(args.out).resolve()} "
        f"({cfg.epochs} epochs of {cfg.samples_per_epoch or 'all'} samples, {cfg.optimizer}, seed {cfg.seed})"
    )
    best = train(args.dataset, args.out, cfg, progress=not args.quiet, device=args.device)
    print(
        f"best epoch {best['best_epoch']}: validation F1 {best.get('val_f1', float('nan')):.3f}, "
        f"accuracy {best.get('val_accuracy', float('nan')):.3f}; thresholds {best.get('thresholds')}"
    )
    print(f"model: {Path(args.out) / 'model.pt'}")
    return 0


def _model_options(args: argparse.Namespace) -> dict:
    """The model settings given on the command line (ModelConfig's fields)."""
    given = {
        "architecture": args.architecture,
        "gravity": args.gravity or None,
        "surface_rows": args.surface_rows or None,
        "sampling": args.sampling,
        "points": args.points,
        "frame": args.frame,
        "pooling": args.pooling,
    }
    return {k: v for k, v in given.items() if v}


def _asdict(cfg) -> dict:
    import dataclasses

    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from l3e_env.experiments.table3 import Table3Options, run_table3
    from l3e_env.model.classifier import DEFAULT_CHECKPOINT, torch_device

    torch_device(args.device)  # a missing GPU is named before anything is read or written
    out = Path(args.out or f"l3e_out/evaluate-{time.strftime('%Y%m%d-%H%M%S')}")
    args.out = str(out)  # the resolved options are written beside it
    options = Table3Options(
        others=args.other or [],
        symmetric=args.symmetric,
        eigen=args.eigen or [],
        dcreg=args.dcreg or [],
        xicp=args.xicp or [],
        drpm=args.drpm or [],
        int8=not args.float32,
        by_family=args.by_family,
        by_region=args.by_region,
        scan_mc=args.scan_mc,
        workers=args.workers,
        draws=args.draws,
        cascade=args.cascade or [],
        device=args.device,
    )
    results = run_table3(args.checkpoint or [DEFAULT_CHECKPOINT], args.dataset, out, options, progress=not args.quiet)
    print(results.table)
    print("written: " + ", ".join(map(str, results.written)))
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from l3e_env.model.training import calibrate_symmetric

    thresholds = calibrate_symmetric(args.checkpoint, args.dataset, args.out, progress=not args.quiet)
    print(f"symmetric thresholds {' '.join(f'{t:.3f}' for t in thresholds)} -> {args.out or args.checkpoint}")
    return 0


def _cmd_fit_constraints(args: argparse.Namespace) -> int:
    from l3e_env.model.training import fit_constraints

    result = fit_constraints(
        args.checkpoint,
        args.dataset,
        args.out,
        beta=args.beta,
        levels=tuple(args.levels),
        progress=not args.quiet,
        frame=args.frame,
    )
    print(f"thresholds {' '.join(f'{t:.3f}' for t in result['thresholds'])} -> {args.out}")
    return 0


def _add_model_options(p: argparse.ArgumentParser) -> None:
    """The model settings `l3e train` takes (ModelConfig)."""
    p.add_argument("--architecture", choices=["resunet", "pointnet"])
    p.add_argument(
        "--gravity",
        action="store_true",
        help="the model also reads the sensor's tilt (the world's up direction in the sensor frame)",
    )
    p.add_argument(
        "--surface-rows",
        action="store_true",
        dest="surface_rows",
        help="each voxel also enters the network with its point-to-plane row [n, p x n] and whether "
        "it is planar (the ResUNet only)",
    )
    p.add_argument(
        "--sampling",
        choices=["points", "voxels"],
        help="draw the input from the scan's points (default) or from one point per voxel",
    )
    p.add_argument("--points", type=int, help="points (or voxels) the model reads from a scan (default 4000)")
    p.add_argument(
        "--frame",
        choices=["sensor", "canonical"],
        help="canonical: each scan read in its canonical mirror/swap view, so that its mirror images and "
        "its turns by 90 and 180 deg about z get the same answer (default: sensor)",
    )
    p.add_argument(
        "--pooling",
        choices=["max", "information"],
        help="information: beside the max-pooled feature, point-to-plane information matrices whose voxels "
        "the network weighs, summed over the scan as ICP's Hessian (the ResUNet only; default: max)",
    )


def _add_train(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the localizability classifier on a labelled dataset (resumable)")
    p.add_argument(
        "--dataset",
        required=True,
        action="append",
        help="dataset folder made by 'l3e dataset generate'; repeat to train on several as one",
    )
    p.add_argument("--out", required=True, help="run folder (an unfinished run there is resumed)")
    p.add_argument("--init", help="model.pt to start from (fine-tuning; its model settings are kept)")
    p.add_argument("--config", help="YAML of TrainConfig (defaults: the shipped model's settings)")
    _add_model_options(p)
    p.add_argument("--epochs", type=int)
    p.add_argument("--samples-per-epoch", type=int, dest="samples_per_epoch")
    p.add_argument("--optimizer", choices=["sgd", "adamw"])
    p.add_argument("--lr", type=float)
    p.add_argument("--threads", type=int, help="torch threads (default 2)")
    add_device_option(p)
    p.add_argument("--seed", type=int)
    p.add_argument(
        "--soft-labels",
        type=float,
        dest="soft_labels",
        help="k > 0: targets sigmoid(k ln(error / threshold)) instead of 0/1 labels",
    )
    p.add_argument(
        "--group-dro",
        type=float,
        dest="group_dro",
        help="eta > 0: weigh the training scene families by group DRO with this step size",
    )
    p.add_argument(
        "--scale-augment",
        type=float,
        dest="scale_augment",
        help="f > 1: scale each training scan by a factor drawn log-uniformly from [1/f, f]",
    )
    p.add_argument(
        "--distilled",
        action="store_true",
        help="also train on the places of the distillation sets (l3e dataset generate --labeller scan, e.g. "
        "--preset distill) among the --dataset folders",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_train)


def _add_detector_options(p: argparse.ArgumentParser) -> None:
    """The training-free detectors `l3e evaluate` scores beside the checkpoints."""
    p.add_argument(
        "--eigen",
        type=float,
        action="append",
        metavar="TAU",
        help="also score the eigenvalue detector at this threshold (Hessian of each scan onto itself); "
        "repeat for several",
    )
    p.add_argument(
        "--dcreg",
        type=float,
        action="append",
        metavar="KAPPA",
        help="also score DCReg's detection at this condition ratio threshold (rotation and translation "
        "decoupled by Schur complements, same Hessian); repeat for several",
    )
    p.add_argument(
        "--xicp",
        type=float,
        action="append",
        metavar="L",
        help="also score X-ICP's localizability analysis at this threshold (correspondences that constrain "
        "an axis squarely; its published configuration's is 300); repeat for several",
    )
    p.add_argument(
        "--drpm",
        type=float,
        action="append",
        metavar="S",
        help="also score DRPM's probabilistic degeneracy test at this signal-to-noise factor (the paper's s, "
        "e.g. 10); repeat for several",
    )
    p.add_argument(
        "--scan-mc",
        type=int,
        default=0,
        dest="scan_mc",
        metavar="M",
        help="also score the scan's own Monte-Carlo estimate with up to M children (no training; "
        "about 50 ms a child, and a scan stops drawing once its axes are settled), on every split "
        "but the training one",
    )
    p.add_argument(
        "--cascade",
        type=float,
        action="append",
        metavar="MARGIN",
        help="also score the first checkpoint checked by --scan-mc's estimate on the scans where an axis "
        "lies within MARGIN (log-odds) of its threshold, as the learned+scanmc detector does "
        "(1 is its default); repeat for several",
    )
    p.add_argument("--workers", type=int, default=1, help="processes for --scan-mc (default 1)")


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="Table III: per-axis scores on train, validation and test, PR curves")
    add_device_option(p)
    p.add_argument(
        "--checkpoint", action="append", help="model.pt of a run; repeat to compare (default: the shipped model)"
    )
    p.add_argument(
        "--dataset",
        action="append",
        help="the dataset(s) the models were trained on, scored by their train, validation and test "
        "splits; repeat to score several as one (may be left out when --other is given)",
    )
    p.add_argument(
        "--other",
        "--other-sensor",
        dest="other",
        action="append",
        help="another dataset, scored whole: another sensor, or scene families never trained on; repeat for several",
    )
    p.add_argument(
        "--by-family",
        action="store_true",
        dest="by_family",
        help="also score each scene family of the test split and of an --other dataset on its own "
        "(e.g. 'mine of test', 'yard of rooms48')",
    )
    p.add_argument(
        "--by-region",
        action="store_true",
        dest="by_region",
        help="also score each named region of a scene there on its own (e.g. 'yard of mine-0', "
        "'tunnel of mine-0', 'quarry of mine-0')",
    )
    _add_detector_options(p)
    p.add_argument(
        "--draws",
        type=int,
        default=1,
        metavar="N",
        help="also score each checkpoint on N draws of the points read from each scan and print the "
        "spread of its mean F1 and accuracy (N times the model's time; default 1: the table's draw)",
    )
    p.add_argument("--out", help="output folder (default: l3e_out/evaluate-<time>)")
    p.add_argument(
        "--symmetric",
        action="store_true",
        help="average each scan's probabilities over its eight mirror/swap views (8x slower)",
    )
    p.add_argument(
        "--float32", action="store_true", help="run the ResUNet's convolutions in float32 instead of int8 (as deployed)"
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_evaluate)


def _add_calibrate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate", help="add symmetric-inference thresholds to a checkpoint, from its validation scenes"
    )
    p.add_argument("--checkpoint", required=True, help="model.pt to complete (rewritten unless --out is given)")
    p.add_argument("--dataset", required=True, action="append", help="the dataset(s) it was trained on")
    p.add_argument("--out", help="write the completed checkpoint here instead")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_calibrate)


def _add_fit_constraints(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit-constraints",
        help="add a per-axis logistic layer over the network's logits and the "
        "scan's point-to-plane Hessian, fitted on the training scenes",
    )
    p.add_argument("--checkpoint", required=True, help="a trained ResUNet model.pt (left as it is)")
    p.add_argument("--dataset", required=True, action="append", help="the dataset(s) it was trained on")
    p.add_argument("--out", required=True, help="the new checkpoint")
    p.add_argument("--beta", type=float, help="F-beta of the validation thresholds (default: the checkpoint's)")
    p.add_argument(
        "--levels",
        type=int,
        nargs="+",
        default=[0, 1],
        help="ResUNet levels whose Hessian features the layer reads (0: 0.2 m voxels, 1: 0.4 m; default 0 1)",
    )
    p.add_argument(
        "--frame",
        choices=["sensor", "canonical"],
        help="the view the model reads, the layer fitted in it (default: the checkpoint's; see l3e train)",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_fit_constraints)


def _cmd_adapt(args: argparse.Namespace) -> int:
    from l3e_env.experiments.adapt import AdaptOptions, adapt, describe

    given = {
        "checkpoint": args.checkpoint,
        "sensor": args.sensor,
        "place": args.place,
        "every": args.every,
        "max_scans": args.max_scans,
        "children": args.children,
        "epochs": args.epochs,
        "samples_per_epoch": args.samples_per_epoch,
        "learning_rate": args.lr,
        "workers": args.workers,
        "seed": args.seed,
        "device": args.device,
        "replay": tuple(args.replay) if args.replay else None,
        "replay_share": args.replay_share,
    }
    options = AdaptOptions(**{k: v for k, v in given.items() if v is not None})
    for line in describe(adapt(args.scans, args.out, options, progress=not args.quiet)):
        print(line)
    return 0


def _add_adapt(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "adapt",
        help="fine-tune the classifier on a place's own scans, labelled by scanmc (measured not to help on the "
        "place's other scenes: judge a new place with scanmc or learned+scanmc first, docs/classifier.md)",
    )
    p.add_argument(
        "--scans",
        required=True,
        help="the place's scans: a folder of scan files, an Ouster capture (.osf .pcap) or a ROS bag (at least 20)",
    )
    p.add_argument(
        "--out", required=True, help="run folder; model.pt is the adapted model (an unfinished run is resumed)"
    )
    p.add_argument("--checkpoint", help="the model to adapt (default: the shipped model); trained on the scans' sensor")
    p.add_argument("--sensor", type=sensor_name, help="the scans' sensor (default: a recording's own, else recognised)")
    p.add_argument("--place", help="the place's name among the model's training scenes (default: the folder's name)")
    p.add_argument("--every", type=int, help="of a recording, every k-th scan (default 1)")
    p.add_argument("--max-scans", type=int, dest="max_scans", help="at most this many scans (default 240)")
    p.add_argument("--children", type=int, help="scanmc's children per scan, at most (default 60)")
    p.add_argument("--epochs", type=int, help="fine-tuning epochs (default 6)")
    p.add_argument("--samples-per-epoch", type=int, dest="samples_per_epoch", help="default 160")
    p.add_argument("--lr", type=float, help="the fine-tune's learning rate (default 3e-4)")
    p.add_argument("--workers", type=int, help="processes labelling scans side by side (default 2)")
    p.add_argument(
        "--replay",
        action="append",
        metavar="DATASET",
        help="a labelled dataset whose scans of the model's own training places are replayed beside the "
        "place's, so that the model is not taught the place alone; repeat (default: none)",
    )
    p.add_argument(
        "--replay-share",
        type=float,
        dest="replay_share",
        help="the replayed scans' share of each epoch's samples (default 0.5)",
    )
    p.add_argument("--seed", type=int)
    add_device_option(p)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_adapt)


def register(sub: argparse._SubParsersAction) -> None:
    _add_train(sub)
    _add_adapt(sub)
    _add_evaluate(sub)
    _add_calibrate(sub)
    _add_fit_constraints(sub)
