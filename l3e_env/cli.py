"""The `l3e` command line: a thin layer over library functions that return results."""
from __future__ import annotations

import argparse
import json
import sys
import time
from importlib.metadata import entry_points
from pathlib import Path

from .config import FusionOptions


def scene_name(text: str) -> str:
    """argparse type: a scene name or mesh path, refused at parse time (before any folder or worker)."""
    from scenes import SceneError, check_scene_name

    try:
        return check_scene_name(text)
    except SceneError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def scene_names(text: str) -> list[str]:
    """argparse type: comma-separated scene names, each checked as `scene_name` does."""
    return [scene_name(name.strip()) for name in text.split(",")]


SENSOR_HELP = "vlp16, vlp16-calibrated, os0-128 or a beam pattern file (.yaml/.json, or an Ouster metadata .json)"
NOISE_HELP = ("draw the odometry's and the LiDAR's noise from streams of their own, so that a drive with another "
              "--sensor or sweep setting has the same odometry noise (default: one stream, the drives the README's "
              "figures were measured on)")


def bias_axes(text: str) -> tuple[str, ...]:
    """argparse type: "none", or comma-separated axes among fusion.bias.BIAS_AXES ("yaw", "yaw,z")."""
    from fusion.bias import BIAS_AXES, check_bias_axes

    axes = () if text.strip() == "none" else tuple(a.strip() for a in text.split(","))
    try:
        check_bias_axes(axes)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected none or distinct axes among {', '.join(BIAS_AXES)} "
                                         f"separated by commas, got {text!r}") from None
    return axes


def add_fusion_options(parser: argparse.ArgumentParser) -> None:
    """--icp-covariance and --odometry-bias, read back by `fusion_options` (`l3e ate`, `l3e sweep`,
    `l3e policy evaluate`)."""
    parser.add_argument("--icp-covariance", choices=["hessian", "fixed"], default="hessian",
                        help="the fusion's ICP information: the registration's Hessian over a fitted residual "
                             "variance (default), or the fixed per-axis sigmas that the figures before it were "
                             "measured with")
    parser.add_argument("--odometry-bias", type=bias_axes, default=(), metavar="AXES",
                        help="estimate the leg odometry's per-metre biases as states of the fusion: yaw, z or "
                             "yaw,z (default none; on the mine's five drives yaw takes the learned mask's ATE "
                             "from 1.93 to 1.64 m, but where ICP's heading is wrong and unmasked, as in the cave, "
                             "it follows ICP further)")


def fusion_options(args: argparse.Namespace) -> FusionOptions:
    """The options that `add_fusion_options` added."""
    return FusionOptions(args.icp_covariance, args.odometry_bias)


def sensor_name(text: str) -> str:
    """argparse type: a registered LiDAR model (vlp16, os0-128 or one added with register_pattern),
    or a beam pattern file."""
    from .lidar import get_pattern

    try:
        return get_pattern(text).name
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def float_list(text: str) -> tuple[float, ...]:
    """argparse type: comma-separated numbers."""
    try:
        return tuple(float(t) for t in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got '{text}'") from None


def add_mesh_options(parser: argparse.ArgumentParser, several: bool = False) -> None:
    """--route, --up-axis and --scale: what it takes to drive a scene given as a mesh file; with
    `several`, also --meshes, a YAML list of meshes with their own."""
    g = parser.add_argument_group("a scene given as a mesh file (OBJ, STL, PLY, GLB, glTF, OFF)")
    if several:
        g.add_argument("--meshes", help="YAML list of mesh scenes: mesh, route (a file or a list), up_axis, scale; "
                                        "paths relative to the YAML's folder (they join the scenes given)")
    g.add_argument("--route", action="append",
                   help="text file of waypoints on the floor, one 'x y z' per line, in the mesh's axes and units "
                        "(needed to drive a mesh); repeat for more paths: the first is the one driven, and labels "
                        "are sampled along all of them (the galleries of a mine)")
    g.add_argument("--up-axis", dest="up_axis", choices=["x", "y", "z"], help="the mesh's up axis (default z)")
    g.add_argument("--scale", type=float, help="metres per mesh unit (default 1; 0.001 for millimetres)")


def mesh_options_given(args: argparse.Namespace) -> list[str]:
    """The mesh options set on the command line, as spelt there."""
    return [f"--{n.replace('_', '-')}" for n in ("route", "up_axis", "scale") if getattr(args, n) is not None]


def scene_params(args: argparse.Namespace, scene: str | None = None) -> dict:
    """make_scene's keyword arguments for `scene` (default args.scene) from the mesh options;
    ValueError where they do not apply."""
    from scenes import is_mesh_path, load_route

    scene = scene or args.scene
    given = mesh_options_given(args)
    if not is_mesh_path(scene):
        if given:
            raise ValueError(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} only for a scene given as "
                             f"a mesh file, not for '{scene}'")
        return {}
    if args.route is None:
        raise ValueError(f"to drive or label the mesh {scene}, give its route: --route FILE (waypoints on its floor)")
    up_axis, scale = args.up_axis or "z", 1.0 if args.scale is None else args.scale
    routes = [load_route(path, up_axis, scale) for path in args.route]
    return {"up_axis": up_axis, "scale": scale, "sampling_paths": [route.tolist() for route in routes]}


def _cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    params = scene_params(args)
    out = Path(args.out or f"l3e_out/demo-{time.strftime('%Y%m%d-%H%M%S')}")
    print(f"writing the demo into {out.resolve()}")
    result = run_demo(out, scene=args.scene, sensor=args.sensor, seed=args.seed, progress=not args.quiet,
                      checkpoint=args.checkpoint, scene_params=params)
    print(f"{result['steps']} steps, goal {'reached' if result['reached_goal'] else 'NOT reached'}")
    from .labels import AXES

    print("share of scans flagged non-localizable by the learned detector:")
    print(f"  {'':8s}" + "".join(f"{a:>7s}" for a in AXES))
    for place, share in result["flagged"].items():
        print(f"  {place:8s}" + "".join(f"{v:7.2f}" for v in share))
    for f in result["files"]:
        print(f"  {f}")
    return 0 if result["reached_goal"] else 1


def _cmd_scenes(args: argparse.Namespace) -> int:
    from scenes import TEST_SCENES, TRAIN_SCENES, VALIDATION_SCENES, list_scenes, make_scene

    names = args.names or list_scenes()
    for name in names:
        print(make_scene(name).summary())
    if not args.names:
        print(f"\ntraining environments ({len(TRAIN_SCENES)}): {', '.join(TRAIN_SCENES)}")
        print(f"validation: {', '.join(VALIDATION_SCENES)}")
        print(f"test (families unseen in training): {', '.join(TEST_SCENES)}")
    return 0


def _cmd_envs(args: argparse.Namespace) -> int:
    from . import ENV_IDS

    for env_id, scene in ENV_IDS.items():
        print(f"{env_id:18s} scene '{scene}'")
    return 0


MESH_KEYS = {"mesh", "route", "up_axis", "scale"}


def meshes_file(path: str | Path, scenes: list[str], options: list[str]) -> dict[str, dict]:
    """The meshes a YAML file lists, each as {mesh: FILE, route: FILE or [FILE, ...], up_axis: z,
    scale: 1} with paths relative to the file's folder: absolute mesh path -> make_scene's
    arguments. ValueError naming the entry where one is malformed, or where a mesh or mesh
    options (`options`, as spelt) are also given beside the file."""
    import yaml

    from scenes import canonical_scene_name, is_mesh_path, load_route

    if any(is_mesh_path(s) for s in scenes) or options:
        raise ValueError("--meshes lists the meshes with their routes, axes and scales: give no other mesh scene and "
                         "no --route, --up-axis or --scale beside it")
    path = Path(path)
    try:
        entries = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read the list of meshes ({exc})") from exc
    if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
        raise ValueError(f"{path}: give a list of meshes, each as 'mesh: FILE' and 'route: FILE' (up_axis, scale "
                         "optional)")
    meshes: dict[str, dict] = {}
    for i, entry in enumerate(entries, 1):
        where = f"{path}, mesh {i}"
        if unknown := set(entry) - MESH_KEYS:
            raise ValueError(f"{where}: unknown keys {sorted(unknown)} (known: {sorted(MESH_KEYS)})")
        if "mesh" not in entry or "route" not in entry or not is_mesh_path(str(entry["mesh"])):
            raise ValueError(f"{where}: give 'mesh' (a mesh file) and 'route' (its waypoint file or files)")
        up_axis, scale = str(entry.get("up_axis", "z")), entry.get("scale", 1.0)
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
            raise ValueError(f"{where}: scale is metres per mesh unit, a positive number; got {scale!r}")
        routes = entry["route"] if isinstance(entry["route"], list) else [entry["route"]]
        name = canonical_scene_name(str(path.parent / str(entry["mesh"])))
        if name in meshes:
            raise ValueError(f"{where}: {name} is listed twice (give one mesh its routes as a list)")
        meshes[name] = {"up_axis": up_axis, "scale": float(scale), "sampling_paths": [
            load_route(path.parent / str(r), up_axis, scale).tolist() for r in routes]}
    return meshes


def dataset_scenes(args: argparse.Namespace) -> tuple[list[str] | None, dict[str, dict]]:
    """--scenes with a mesh file's path made absolute (a dataset names its scenes for good), and
    each mesh's make_scene arguments from the mesh options or the --meshes file; ValueError where
    they do not apply."""
    from scenes import canonical_scene_name, is_mesh_path

    meshes = [s for s in args.scenes or [] if is_mesh_path(s)]
    if args.meshes:
        listed = meshes_file(args.meshes, args.scenes or [], mesh_options_given(args))
        return [*(args.scenes or []), *listed], listed
    if len(meshes) > 1:
        raise ValueError(f"one mesh file in --scenes, as --route gives one mesh's route; got {', '.join(meshes)} "
                         "(list several meshes with their routes in a --meshes file)")
    if not meshes:
        scene_params(args, (args.scenes or ["the preset's scenes"])[0])  # refuses stray mesh options
        return args.scenes, {}
    params = scene_params(args, meshes[0])
    return [canonical_scene_name(s) for s in args.scenes], {canonical_scene_name(meshes[0]): params}


def _cmd_dataset_generate(args: argparse.Namespace) -> int:
    from .dataset import config_for, format_statistics, generate

    scenes, params = dataset_scenes(args)
    overrides = {
        "scenes": scenes,
        "scene_params": params or None,
        "parents_per_scene": args.parents,
        "seed": args.seed,
        "lidar": {"model": args.sensor} if args.sensor else None,
        "labels": {"children": args.children} if args.children else None,
    }
    config = config_for(args.preset, **overrides)
    print(f"dataset -> {Path(args.out).resolve()}: {len(config.scenes)} scenes x {config.parents_per_scene} parents, "
          f"M = {config.labels.children}, {config.lidar.model}, seed {config.seed}, "
          f"{args.workers} workers ({args.backend})")
    manifest = generate(args.out, config, workers=args.workers, backend=args.backend, ray_address=args.address,
                        progress=not args.quiet)
    print(f"{manifest['count']} labelled parents, {len(manifest['failures'])} failed "
          f"({manifest['generation_seconds_last_run']} s this run)")
    for failure in manifest["failures"][:3]:
        print(f"  failed: {failure['scene']} parent {failure['parent']}: {failure['reason']}")
    print(format_statistics(manifest["statistics"]))
    return 0


def _cmd_dataset_stats(args: argparse.Namespace) -> int:
    from .dataset import LabelDataset, format_statistics

    data = LabelDataset(args.folder)
    print(f"{args.folder}: {len(data)} parents, sensor {data.manifest['sensor']}, "
          f"scenes {', '.join(data.manifest['scenes'])}")
    print(format_statistics(data.manifest["statistics"]))
    return 0


def _cmd_ate(args: argparse.Namespace) -> int:
    from .experiment import format_seed_table, format_table, run_experiment, summarize_seeds
    from .experiment_plots import plot_seeds
    from .lidar import DESKEW_STEPS

    # a recording holds its scene's route, axes and scale: a mesh given with it is where the mesh moved to
    params = {} if args.recording and not mesh_options_given(args) else scene_params(args)
    stem = "replay" if args.recording else Path(args.scene).stem  # a replay's scene is the recording's
    out = Path(args.out or f"l3e_out/ate-{stem}-{time.strftime('%Y%m%d-%H%M%S')}")
    if args.seeds < 1 or (args.seeds > 1 and args.recording):
        print("l3e ate: --seeds is 1 or more drives, and a recording is one drive", file=sys.stderr)
        return 2
    if args.separate_noise and args.recording:
        print("l3e ate: a recording keeps the noise it was driven with; --separate-noise is for "
              "`l3e record` or a new drive", file=sys.stderr)
        return 2
    streams = "separate" if args.separate_noise else "shared"
    print(f"writing the experiment into {out.resolve()}")
    detectors = args.detector or ["none", "eigen:30", "eigen:110", "oracle"]
    if args.seeds > 1:
        runs = {}
        for seed in range(args.seed, args.seed + args.seeds):
            print(f"drive {seed - args.seed + 1} of {args.seeds} (seed {seed})")
            runs[seed] = run_experiment(out / f"seed-{seed}", args.scene, detectors, sensor=args.sensor, seed=seed,
                                        progress=not args.quiet, backend=args.backend, scene_params=params,
                                        workers=args.workers, noise_streams=streams, attitude=args.attitude,
                                        fusion_options=fusion_options(args))
            print(format_table(runs[seed]))
        summary = summarize_seeds(runs)
        (out / "seeds.json").write_text(json.dumps(summary, indent=1))
        plot_seeds(out / "seeds.png", summary)
        print(format_seed_table(summary))
        print(f"written: {out / 'seeds.json'}, {out / 'seeds.png'}")
        return 0
    rows = run_experiment(out, args.scene, detectors, sensor=args.sensor, seed=args.seed, recording=args.recording,
                          progress=not args.quiet, backend=args.backend, scene_params=params, workers=args.workers,
                          deskew=args.deskew, noise_streams=streams, attitude=args.attitude,
                          fusion_options=fusion_options(args))
    print(format_table(rows))
    if json.loads((out / "results.json").read_text()).get("swept"):
        turn = "the gyro's rotation over it" if args.deskew == "gyro" else "the odometry's rotation"
        print("the recording's scans are swept over the robot's motion; each was deskewed with the leg "
              f"odometry's mean motion over its last {DESKEW_STEPS} steps, with {turn}, before it was judged "
              "and registered")
    return 0


def record_imu(args: argparse.Namespace):
    """The ImuConfig that `l3e record`'s options ask for; None where --imu-rate is 0."""
    from .imu import ImuConfig

    if not args.imu_rate:
        return None
    return ImuConfig(rate=args.imu_rate, orientation=args.imu_orientation,
                     footfall_accel=ImuConfig.footfall_accel if args.imu_footfalls else 0.0)


def _cmd_record(args: argparse.Namespace) -> int:
    from .experiment import record_run
    from .rosbag import BagError, BagRecorder

    params = scene_params(args)
    if not args.imu_rate >= 0:
        print(f"l3e record: --imu-rate must be 0 (no IMU) or more, got {args.imu_rate}", file=sys.stderr)
        return 2
    try:
        bag = BagRecorder(args.out, ros2=args.ros2, imu=record_imu(args), seed=args.seed)
    except BagError as exc:
        print(f"l3e record: {exc}", file=sys.stderr)
        return 2
    rec = record_run(args.scene, args.sensor, args.seed, progress=not args.quiet, scene_params=params, on_step=bag,
                     sweep=args.sweep, noise_streams="separate" if args.separate_noise else "shared")
    print(f"written: {bag.close()} ({bag.steps} scans)")
    if args.recording:
        Path(args.recording).parent.mkdir(parents=True, exist_ok=True)
        rec.save(args.recording)
        print(f"written: {args.recording} (l3e ate --recording {args.recording} fuses this same drive)")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from .config import from_dict, load_yaml
    from .training import TrainConfig, train

    cfg = load_yaml(TrainConfig, args.config) if args.config else TrainConfig()
    overrides = {k: v for k, v in {"epochs": args.epochs, "seed": args.seed, "optimizer": args.optimizer,
                                   "learning_rate": args.lr, "samples_per_epoch": args.samples_per_epoch,
                                   "threads": args.threads, "soft_labels": args.soft_labels,
                                   "group_dro": args.group_dro, "scale_augment": args.scale_augment}.items()
                 if v is not None}
    model = _asdict(cfg.model)
    if args.init:  # fine-tuning keeps the model settings of the checkpoint it starts from
        from .classifier import ModelConfig, load_checkpoint
        from .training import network_config

        start = from_dict(ModelConfig, load_checkpoint(args.init)["model"])
        model, overrides["init"] = _asdict(network_config(start)), args.init
        if start.constraints:
            print(f"{args.init} has a constraint layer: its network is fine-tuned without it; fit the layer "
                  "again afterwards (l3e fit-constraints)")
    if args.architecture:
        model["architecture"] = args.architecture
    if args.gravity:
        model["gravity"] = True
    if args.surface_rows:
        model["surface_rows"] = True
    if args.sampling:
        model["sampling"] = args.sampling
    if args.points:
        model["points"] = args.points
    cfg = from_dict(TrainConfig, {**_asdict(cfg), **overrides, "model": model})
    print(f"training {cfg.model.architecture} on {' + '.join(args.dataset)} -> {Path(args.out).resolve()} "
          f"({cfg.epochs} epochs of {cfg.samples_per_epoch or 'all'} samples, {cfg.optimizer}, seed {cfg.seed})")
    best = train(args.dataset, args.out, cfg, progress=not args.quiet)
    print(f"best epoch {best['best_epoch']}: validation F1 {best.get('val_f1', float('nan')):.3f}, "
          f"accuracy {best.get('val_accuracy', float('nan')):.3f}; thresholds {best.get('thresholds')}")
    print(f"model: {Path(args.out) / 'model.pt'}")
    return 0


def _asdict(cfg) -> dict:
    import dataclasses

    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .classifier import DEFAULT_CHECKPOINT
    from .evaluation import evaluate

    out = Path(args.out or f"l3e_out/evaluate-{time.strftime('%Y%m%d-%H%M%S')}")
    results = evaluate(args.checkpoint or [DEFAULT_CHECKPOINT], args.dataset, out, others=args.other,
                       progress=not args.quiet, symmetric=args.symmetric, eigen=args.eigen, int8=not args.float32,
                       by_family=args.by_family, by_region=args.by_region, scan_mc=args.scan_mc, workers=args.workers,
                       draws=args.draws, cascade=args.cascade)
    print(results["table"])
    print("written: " + ", ".join(results["written"]))
    return 0


def _cmd_sensor(args: argparse.Namespace) -> int:
    from .judge import ScanFileError, read_scan, recognise_sensor
    from .patterns import PATTERN_FILES, PATTERNS, describe_pattern, get_pattern, save_pattern
    from .rosbag import BagError, read_bag

    if bool(args.source) == bool(args.bag):
        print("l3e sensor: give a sensor (name or pattern file), a scan file or --bag, one of them", file=sys.stderr)
        return 2
    if args.source and (args.source in PATTERNS or args.source.lower().endswith(PATTERN_FILES)):
        pattern, how = get_pattern(args.source), "as given"
    else:
        try:
            if not args.bag:
                read_scan(args.source)  # a file that cannot be read is named here
            scans = read_bag(args.bag, args.topic) if args.bag else iter([args.source])
        except (BagError, ScanFileError) as exc:
            print(f"l3e sensor: {exc}", file=sys.stderr)
            return 2
        _, pattern, how = recognise_sensor(scans)
        if pattern is None:
            print(f"l3e sensor: {how}", file=sys.stderr)
            return 2
    print(describe_pattern(pattern) + f"\n  ({how})")
    if args.out:
        print(f"written: {save_pattern(pattern, args.out)} (give it as --sensor)")
    return 0


def _cmd_judge(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from .config import LidarConfig
    from .judge import format_judgement, judge_scans, judgement_record, score_legend
    from .rosbag import BagError, read_bag, read_path

    if bool(args.scans) == bool(args.bag):
        print("l3e judge: give scan files or --bag, not both and not neither", file=sys.stderr)
        return 2
    if not args.bag and (args.topic or args.every != 1 or args.start is not None or args.end is not None):
        print("l3e judge: --topic, --every, --start and --end read a bag: give --bag", file=sys.stderr)
        return 2
    if not args.bag and (args.path_plot or args.pose_topic):
        print("l3e judge: --path-plot and --pose-topic read the path from a bag: give --bag", file=sys.stderr)
        return 2
    try:
        scans = read_bag(args.bag, args.topic, args.every, args.start, args.end) if args.bag else args.scans
        route = read_path(args.bag, args.pose_topic) if args.bag and (args.path_plot or args.pose_topic) else None
    except BagError as exc:
        print(f"l3e judge: {exc}", file=sys.stderr)
        return 2
    specs = args.detector or ["learned", "eigen:30", "scanmc"]
    sensor = [args.sensor]

    def recognised(pattern, how: str) -> None:
        if pattern is None:
            sensor[0] = LidarConfig().model
            print(f"sensor: {how}; scanmc takes it as a {LidarConfig().model} and answers unknown for scans of "
                  "another (give --sensor: a name, a pattern file or an Ouster's metadata JSON)", flush=True)
        else:
            sensor[0] = pattern.name
            print(f"sensor: {how} (give --sensor to choose it)", flush=True)

    judgements = []  # printed as each scan is judged; an unreadable scan is named and the next one read
    for j in judge_scans(scans, specs, LidarConfig(model=args.sensor) if args.sensor else None, seed=args.seed,
                         workers=args.workers, on_sensor=recognised):
        judgements.append(j)
        stamp = "" if j.stamp is None else f"[t = {j.stamp:.3f} s] "
        print(stamp + format_judgement(j), file=sys.stderr if j.error else sys.stdout, flush=True)
    print("scores ('*' flagged):\n" + score_legend(specs))
    where = None if route is None else route.at(np.array([j.stamp for j in judgements], dtype=np.float64))
    if args.json:
        records = [judgement_record(j, sensor[0]) for j in judgements]
        for record, position in zip(records, [] if where is None else where):
            record["position"] = [float(v) for v in position] if np.isfinite(position).all() else None
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(records, indent=1) + "\n")
        print(f"written: {args.json}")
    if args.plot and any(j.predictions for j in judgements):
        from .judge_plots import plot_timeline

        plot_timeline(judgements, args.plot)
        print(f"written: {args.plot}")
    if args.path_plot and any(j.predictions for j in judgements):
        from .judge_plots import plot_path

        off = int((~np.isfinite(where).all(axis=1)).sum())
        if off:
            print(f"l3e judge: {off} scans lie outside the time of {route.topic}'s poses and are left off the map",
                  file=sys.stderr)
        try:
            plot_path(judgements, where, route.positions, args.path_plot, f"{Path(args.bag).name} on {route.topic}")
            print(f"written: {args.path_plot}")
        except ValueError as exc:
            print(f"l3e judge: {exc}", file=sys.stderr)
            return 2
    failed = sum(j.error is not None for j in judgements)
    if not judgements:
        print("l3e judge: no scan in the bag between --start and --end", file=sys.stderr)
    elif failed:
        print(f"l3e judge: {failed} of {len(judgements)} scans could not be read or judged", file=sys.stderr)
    return 2 if failed or not judgements else 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from .training import calibrate_symmetric

    thresholds = calibrate_symmetric(args.checkpoint, args.dataset, args.out, progress=not args.quiet)
    print(f"symmetric thresholds {' '.join(f'{t:.3f}' for t in thresholds)} -> {args.out or args.checkpoint}")
    return 0


def _cmd_fit_constraints(args: argparse.Namespace) -> int:
    from .training import fit_constraints

    result = fit_constraints(args.checkpoint, args.dataset, args.out, beta=args.beta, levels=tuple(args.levels),
                             progress=not args.quiet)
    print(f"thresholds {' '.join(f'{t:.3f}' for t in result['thresholds'])} -> {args.out}")
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from .sweep import DEFAULT_TAUS, beaten_everywhere, run_sweep

    out = Path(args.out or f"l3e_out/sweep-{time.strftime('%Y%m%d-%H%M%S')}")
    print(f"writing the sweep into {out.resolve()}")
    taus = args.taus or DEFAULT_TAUS
    recordings = dict(r.split("=", 1) for r in args.recording or [])
    results = run_sweep(out, args.scene or ["tunnel", "field", "office"], taus, recordings=recordings,
                        progress=not args.quiet, fusion_options=fusion_options(args))
    best = beaten_everywhere(results, "learned")
    print("taus at least as good as the learned detector in every scene: " + (", ".join(f"{t:g}" for t in best)
                                                                             if best else "none"))
    print(f"plot: {out / 'tau_sweep.png'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .config import ATTITUDE_MODES

    parser = argparse.ArgumentParser(prog="l3e", description="Learned LiDAR localizability in simulation (L3E).")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="drive the mine route and save a top view and scan pictures")
    p.add_argument("--out", help="output folder (default: l3e_out/demo-<time>)")
    p.add_argument("--scene", type=scene_name, default="mine", help="scene name (default: mine)")
    p.add_argument("--sensor", type=sensor_name, default="vlp16", help=SENSOR_HELP)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint", help="classifier checkpoint (default: the shipped model)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_mesh_options(p)
    p.set_defaults(func=_cmd_demo)
    p = sub.add_parser("scenes", help="list scenes and the train/validation/test split")
    p.add_argument("names", nargs="*", type=scene_name, help="scene names to describe (default: all families)")
    p.set_defaults(func=_cmd_scenes)
    p = sub.add_parser("dataset", help="Monte-Carlo localizability labels")
    dsub = p.add_subparsers(dest="dataset_command", required=True)
    g = dsub.add_parser("generate", help="generate or resume a labelled dataset")
    g.add_argument("--out", required=True, help="dataset folder (an unfinished one is resumed)")
    g.add_argument("--preset", choices=["small", "paper", "level"], default="small",
                   help="small: a first look; paper: the paper's protocol; level: operating poses "
                        "(level, heading along or across the paths)")
    g.add_argument("--scenes", type=scene_names,
                   help="comma-separated scene names (overrides the preset); one may be a mesh file, with --route")
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
    p = sub.add_parser("ate", help="drive a route once, fuse with each detector, compare ATE")
    p.add_argument("--scene", type=scene_name, default="mine")
    p.add_argument("--detector", action="append",
                   help="none | eigen:<tau> | oracle[:M] | scanmc[:M] | learned[:checkpoint] | "
                        "learned+scanmc[:margin]; repeat for several")
    p.add_argument("--backend", choices=["graph", "ekf"], default="graph", help="iSAM2 smoother or filterpy EKF")
    p.add_argument("--sensor", type=sensor_name, default="vlp16", help=SENSOR_HELP)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", type=int, default=1,
                   help="drive N times, seeds --seed ... --seed + N - 1, and summarise each detector's ATE over them")
    p.add_argument("--recording", help="evaluate a saved recording.npz instead of driving again")
    p.add_argument("--deskew", choices=["gyro", "odometry"], default="gyro",
                   help="a swept recording's scans are deskewed with the leg odometry's motion, turned by the "
                        "gyro's rotation (default) or the odometry's own")
    p.add_argument("--separate-noise", action="store_true",
                   help=NOISE_HELP)
    p.add_argument("--attitude", choices=ATTITUDE_MODES, default="none",
                   help="fuse the IMU's orientation once a second: tilt = roll and pitch, which gravity holds "
                        "(no heading: underground a magnetometer reads the rock), full = with the magnetometer's "
                        "heading; adds a row of the odometry fused with it alone (default: none)")
    add_fusion_options(p)
    p.add_argument("--out", help="output folder (default: l3e_out/ate-<scene>-<time>)")
    p.add_argument("--workers", type=int, default=1,
                   help="processes that judge the route with scanmc before the fusion (default 1)")
    p.add_argument("--quiet", action="store_true")
    add_mesh_options(p)
    p.set_defaults(func=_cmd_ate)
    p = sub.add_parser("record", help="drive a route once and write it as a ROS bag: full scans, leg odometry, "
                                      "ground truth (needs pip install 'l3e[bag]')")
    p.add_argument("--out", required=True, help="the bag: a .bag file (ROS 1), or a folder with --ros2")
    p.add_argument("--ros2", action="store_true", help="write a ROS 2 bag (sqlite3) instead of ROS 1")
    p.add_argument("--scene", type=scene_name, default="mine")
    p.add_argument("--sensor", type=sensor_name, default="vlp16", help=SENSOR_HELP)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--recording", help="also save the drive as a recording.npz for l3e ate --recording")
    p.add_argument("--separate-noise", action="store_true",
                   help=NOISE_HELP)
    p.add_argument("--imu-rate", type=float, default=200.0, help="rate of /imu in Hz (default 200; 0: no IMU)")
    p.add_argument("--imu-orientation", action=argparse.BooleanOptionalAction, default=True,
                   help="write a nine-axis unit's orientation in /imu (default), or none as a six-axis unit")
    p.add_argument("--sweep", action=argparse.BooleanOptionalAction, default=True,
                   help="sweep each revolution over the step's motion and write each point's time, as a spinning "
                        "sensor on a moving robot does (default), or take each revolution at one pose")
    p.add_argument("--imu-footfalls", action=argparse.BooleanOptionalAction, default=True,
                   help="jolt /imu at each footfall while walking, as a legged robot's body rings (default), or not")
    p.add_argument("--quiet", action="store_true")
    add_mesh_options(p)
    p.set_defaults(func=_cmd_record)
    p = sub.add_parser("train", help="train the localizability classifier on a labelled dataset (resumable)")
    p.add_argument("--dataset", required=True, action="append",
                   help="dataset folder made by 'l3e dataset generate'; repeat to train on several as one")
    p.add_argument("--out", required=True, help="run folder (an unfinished run there is resumed)")
    p.add_argument("--init", help="model.pt to start from (fine-tuning; its model settings are kept)")
    p.add_argument("--config", help="YAML of TrainConfig (defaults: the shipped model's settings)")
    p.add_argument("--architecture", choices=["resunet", "pointnet"])
    p.add_argument("--gravity", action="store_true",
                   help="the model also reads the sensor's tilt (the world's up direction in the sensor frame)")
    p.add_argument("--surface-rows", action="store_true", dest="surface_rows",
                   help="each voxel also enters the network with its point-to-plane row [n, p x n] and whether "
                        "it is planar (the ResUNet only)")
    p.add_argument("--sampling", choices=["points", "voxels"],
                   help="draw the input from the scan's points (default) or from one point per voxel")
    p.add_argument("--points", type=int, help="points (or voxels) the model reads from a scan (default 4000)")
    p.add_argument("--epochs", type=int)
    p.add_argument("--samples-per-epoch", type=int, dest="samples_per_epoch")
    p.add_argument("--optimizer", choices=["sgd", "adamw"])
    p.add_argument("--lr", type=float)
    p.add_argument("--threads", type=int, help="torch threads (default 2)")
    p.add_argument("--seed", type=int)
    p.add_argument("--soft-labels", type=float, dest="soft_labels",
                   help="k > 0: targets sigmoid(k ln(error / threshold)) instead of 0/1 labels")
    p.add_argument("--group-dro", type=float, dest="group_dro",
                   help="eta > 0: weigh the training scene families by group DRO with this step size")
    p.add_argument("--scale-augment", type=float, dest="scale_augment",
                   help="f > 1: scale each training scan by a factor drawn log-uniformly from [1/f, f]")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_train)
    p = sub.add_parser("evaluate", help="Table III: per-axis scores on train, validation and test, PR curves")
    p.add_argument("--checkpoint", action="append",
                   help="model.pt of a run; repeat to compare (default: the shipped model)")
    p.add_argument("--dataset", action="append",
                   help="the dataset(s) the models were trained on, scored by their train, validation and test "
                        "splits; repeat to score several as one (may be left out when --other is given)")
    p.add_argument("--other", "--other-sensor", dest="other", action="append",
                   help="another dataset, scored whole: another sensor, or scene families never trained on; "
                        "repeat for several")
    p.add_argument("--by-family", action="store_true", dest="by_family",
                   help="also score each scene family of the test split and of an --other dataset on its own "
                        "(e.g. 'mine of test', 'yard of rooms48')")
    p.add_argument("--by-region", action="store_true", dest="by_region",
                   help="also score each named region of a scene there on its own (e.g. 'yard of mine-0', "
                        "'tunnel of mine-0', 'quarry of mine-0')")
    p.add_argument("--eigen", type=float, action="append", metavar="TAU",
                   help="also score the eigenvalue detector at this threshold (Hessian of each scan onto itself); "
                        "repeat for several")
    p.add_argument("--scan-mc", type=int, default=0, dest="scan_mc", metavar="M",
                   help="also score the scan's own Monte-Carlo estimate with up to M children (no training; "
                        "about 50 ms a child, and a scan stops drawing once its axes are settled), on every split "
                        "but the training one")
    p.add_argument("--cascade", type=float, action="append", metavar="MARGIN",
                   help="also score the first checkpoint checked by --scan-mc's estimate on the scans where an axis "
                        "lies within MARGIN (log-odds) of its threshold, as the learned+scanmc detector does "
                        "(1 is its default); repeat for several")
    p.add_argument("--workers", type=int, default=1, help="processes for --scan-mc (default 1)")
    p.add_argument("--draws", type=int, default=1, metavar="N",
                   help="also score each checkpoint on N draws of the points read from each scan and print the "
                        "spread of its mean F1 and accuracy (N times the model's time; default 1: the table's draw)")
    p.add_argument("--out", help="output folder (default: l3e_out/evaluate-<time>)")
    p.add_argument("--symmetric", action="store_true",
                   help="average each scan's probabilities over its eight mirror/swap views (8x slower)")
    p.add_argument("--float32", action="store_true",
                   help="run the ResUNet's convolutions in float32 instead of int8 (as deployed)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_evaluate)
    p = sub.add_parser("judge", help="judge your own scans (files or a ROS bag): along which axes would "
                                     "scan-to-scan registration fail there")
    p.add_argument("scans", nargs="*", metavar="SCAN",
                   help="scan files in the sensor's frame: .npy .npz .bin (KITTI) .ply .pcd .xyz .txt .csv")
    g = p.add_argument_group("a ROS bag instead of files (needs pip install 'l3e[bag]')")
    g.add_argument("--bag", help="a ROS 1 .bag file or a ROS 2 bag folder (sqlite3 or mcap)")
    g.add_argument("--topic", help="its sensor_msgs/PointCloud2 topic (default: the only one)")
    g.add_argument("--every", type=int, default=1, help="judge every N-th scan (default 1: all)")
    g.add_argument("--start", type=float, help="seconds after the bag's start to begin at")
    g.add_argument("--end", type=float, help="seconds after the bag's start to stop at")
    g.add_argument("--path-plot", help="also draw the judged scans on a map of the bag's path into this image")
    g.add_argument("--pose-topic", help="the path's topic: nav_msgs/Odometry, geometry_msgs/PoseStamped or "
                                        "PoseWithCovarianceStamped (default: the only Odometry topic); it also "
                                        "writes each scan's position into --json")
    p.add_argument("--detector", action="append",
                   help="learned[-sym][:checkpoint] | eigen:<tau> | scanmc[:M] | learned+scanmc[:margin] | none; "
                        "repeat for several (default: learned, eigen:30 and scanmc)")
    p.add_argument("--sensor", type=sensor_name,
                   help="the LiDAR that took the scans, for scanmc's beams: vlp16, os0-128 or a beam pattern file "
                        "(.yaml/.json, or an Ouster metadata .json); default: recognised from the scans")
    p.add_argument("--seed", type=int, default=0, help="seed of scanmc's children")
    p.add_argument("--workers", type=int, default=1, help="scans judged side by side in processes (default 1)")
    p.add_argument("--json", help="also write the scores here")
    p.add_argument("--plot", help="also draw the flagged axes scan by scan (over time for a bag) into this image")
    p.set_defaults(func=_cmd_judge)
    p = sub.add_parser("sensor", help="show a LiDAR's beam pattern, or recognise it from a scan or a bag and "
                                      "save it as a pattern file for --sensor")
    p.add_argument("source", nargs="?", help="a sensor name, a pattern file, or a scan file to recognise it from")
    p.add_argument("--bag", help="recognise it from this ROS bag's first scans")
    p.add_argument("--topic", help="the bag's PointCloud2 topic (default: the only one)")
    p.add_argument("--out", help="write the pattern here (.yaml or .json)")
    p.set_defaults(func=_cmd_sensor)
    p = sub.add_parser("calibrate", help="add symmetric-inference thresholds to a checkpoint, from its validation "
                                         "scenes")
    p.add_argument("--checkpoint", required=True, help="model.pt to complete (rewritten unless --out is given)")
    p.add_argument("--dataset", required=True, action="append", help="the dataset(s) it was trained on")
    p.add_argument("--out", help="write the completed checkpoint here instead")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_calibrate)
    p = sub.add_parser("fit-constraints", help="add a per-axis logistic layer over the network's logits and the "
                                               "scan's point-to-plane Hessian, fitted on the training scenes")
    p.add_argument("--checkpoint", required=True, help="a trained ResUNet model.pt (left as it is)")
    p.add_argument("--dataset", required=True, action="append", help="the dataset(s) it was trained on")
    p.add_argument("--out", required=True, help="the new checkpoint")
    p.add_argument("--beta", type=float, help="F-beta of the validation thresholds (default: the checkpoint's)")
    p.add_argument("--levels", type=int, nargs="+", default=[0, 1],
                   help="ResUNet levels whose Hessian features the layer reads (0: 0.2 m voxels, 1: 0.4 m; "
                        "default 0 1)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_fit_constraints)
    p = sub.add_parser("sweep", help="ATE against the eigenvalue threshold in several scenes, with the learned "
                                     "detector as reference")
    p.add_argument("--scene", type=scene_name, action="append", help="repeat; default tunnel, field, office")
    p.add_argument("--taus", type=float_list, help="comma-separated thresholds (default 10 ... 300)")
    p.add_argument("--recording", action="append", help="SCENE=recording.npz to skip driving that scene")
    add_fusion_options(p)
    p.add_argument("--out", help="output folder (default: l3e_out/sweep-<time>)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_sweep)
    p = sub.add_parser("envs", help="list the registered Gymnasium environment ids")
    p.set_defaults(func=_cmd_envs)
    # packages built on l3e_env (policies: `l3e policy`) add their commands through this entry-point
    # group, so that l3e_env never imports them
    for entry in entry_points(group="l3e.commands"):
        entry.load()(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ValueError, RuntimeError, OSError) as exc:
        print(f"l3e {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
