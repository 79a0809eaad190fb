"""Labelled datasets: `l3e dataset generate` and `l3e dataset stats`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from l3e_env.config import DATASET_PRESETS, LABELLERS

from .options import SENSOR_HELP, add_mesh_options, dataset_scenes, scene_names, sensor_name


def _cmd_dataset_generate(args: argparse.Namespace) -> int:
    from l3e_env.data.dataset import format_statistics
    from l3e_env.data.generation import config_for, generate

    scenes, params = dataset_scenes(args)
    overrides = {
        "scenes": scenes,
        "scene_params": params or None,
        "parents_per_scene": args.parents,
        "seed": args.seed,
        "lidar": {"model": args.sensor} if args.sensor else None,
        "labels": {"children": args.children} if args.children else None,
        "labeller": args.labeller,
    }
    config = config_for(args.preset, **overrides)
    print(
        f"dataset -> {Path(args.out).resolve()}: {len(config.scenes)} scenes x {config.parents_per_scene} parents, "
        f"{_children(config)}, {config.lidar.model}, seed {config.seed}, "
        f"{args.workers} workers ({args.backend})"
    )
    manifest = generate(
        args.out, config, workers=args.workers, backend=args.backend, ray_address=args.address, progress=not args.quiet
    )
    print(
        f"{manifest['count']} labelled parents, {len(manifest['failures'])} failed "
        f"({manifest['generation_seconds_last_run']} s this run)"
    )
    for failure in manifest["failures"][:3]:
        print(f"  failed: {failure['scene']} parent {failure['parent']}: {failure['reason']}")
    print(format_statistics(manifest["statistics"]))
    if manifest["count"] == 0:
        print(
            f"l3e dataset generate: no parent could be labelled in {args.out}; the failures above say why "
            "(a mesh's scale or route, a sensor that sees nothing)",
            file=sys.stderr,
        )
        return 2
    return 0


def _children(config) -> str:
    if config.labeller == "scan":
        return f"labelled by each scan's own estimate (at most {config.scan_mc.children} children)"
    return f"M = {config.labels.children}"


def _cmd_dataset_stats(args: argparse.Namespace) -> int:
    from l3e_env.data.dataset import LabelDataset, format_statistics, label_statistics

    data = LabelDataset(args.folder)
    print(
        f"{args.folder}: {len(data)} parents, sensor {data.manifest['sensor']}, "
        f"scenes {', '.join(data.manifest['scenes'])}"
    )
    print(format_statistics(label_statistics(data.labels)))  # the arrays' own, not the manifest's word
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dataset", help="Monte-Carlo localizability labels")
    dsub = p.add_subparsers(dest="dataset_command", required=True)
    g = dsub.add_parser("generate", help="generate or resume a labelled dataset")
    g.add_argument("--out", required=True, help="dataset folder (an unfinished one is resumed)")
    g.add_argument(
        "--preset",
        choices=DATASET_PRESETS,
        default="small",
        help="small: a first look; paper: the paper's protocol; level: operating poses "
        "(level, heading along or across the paths); distill: many places of the training families, "
        "each scan labelled by its own estimate (a distillation set for training); random, random-32, "
        "random-128: randomised places (scenes.composition) seen by a VLP-16, a 32-beam and a 128-beam "
        "sensor, each scan labelled by its own estimate",
    )
    g.add_argument(
        "--labeller",
        choices=LABELLERS,
        help="scene: children ray-cast in the scene (the Monte-Carlo labels); scan: the scan's own "
        "estimate, no scene needed beyond the scan (training only, never a test set)",
    )
    g.add_argument(
        "--scenes",
        type=scene_names,
        help="comma-separated scene names (overrides the preset); one may be a mesh file, with --route",
    )
    g.add_argument("--parents", type=int, help="parents per scene")
    g.add_argument("--children", type=int, help="M, children per parent (paper: 200)")
    g.add_argument("--sensor", type=sensor_name, help=SENSOR_HELP)
    g.add_argument("--seed", type=int)
    g.add_argument("--workers", type=int, default=2)
    g.add_argument("--backend", choices=["local", "ray"], default="local")
    g.add_argument("--address", help="Ray cluster address (default: start a local Ray instance)")
    g.add_argument("--quiet", action="store_true")
    add_mesh_options(g, several=True)
    g.set_defaults(func=_cmd_dataset_generate)
    g = dsub.add_parser("stats", help="label statistics of a dataset")
    g.add_argument("folder")
    g.set_defaults(func=_cmd_dataset_stats)
