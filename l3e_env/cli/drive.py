"""Driving the scenes: the demo, scene and environment lists, ATE experiments, ROS bag recording, the tau sweep."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from l3e_env.config import DESKEW_SOURCES, FUSION_BACKENDS
from l3e_env.config.detector_spec import DEFAULT_ATE_DETECTORS, DETECTOR_GRAMMAR, detector_spec

from .options import (
    SENSOR_HELP,
    CommandError,
    add_fusion_options,
    add_max_steps,
    add_mesh_options,
    add_rerun_option,
    float_list,
    fusion_settings,
    mesh_options_given,
    scene_name,
    scene_params,
    sensor_name,
)


def _cmd_demo(args: argparse.Namespace) -> int:
    from l3e_env.experiments.demo import run_demo
    from l3e_env.experiments.drive import DriveOptions

    params = scene_params(args)
    out = Path(args.out or f"l3e_out/demo-{time.strftime('%Y%m%d-%H%M%S')}")
    args.out = str(out)  # the resolved options are written beside it
    print(f"writing the demo into {out.resolve()}")
    driving = DriveOptions(args.sensor, args.seed, params, max_steps=args.max_steps)
    from l3e_env.experiments.rerun_log import open_command, rerun_available

    rerun = args.rerun or (out / "drive.rrd" if rerun_available() else None)
    result = run_demo(out, args.scene, driving, args.checkpoint, progress=not args.quiet, rerun=rerun)
    print(f"{result['steps']} steps, goal {'reached' if result['reached_goal'] else 'NOT reached'}")
    from l3e_env.localizability.labels import AXES

    print("share of scans flagged non-localizable by the learned detector:")
    print(f"  {'':8s}" + "".join(f"{a:>7s}" for a in AXES))
    for place, share in result["flagged"].items():
        print(f"  {place:8s}" + "".join(f"{v:7.2f}" for v in share))
    for f in result["files"]:
        print(f"  {f}")
    if rerun is not None:
        print(f"see the drive scan by scan: {open_command(rerun)}")
    return 0 if result["reached_goal"] else 1


def _cmd_scenes(args: argparse.Namespace) -> int:
    from l3e_env.config import RobotConfig
    from l3e_env.sim.follower import route_drive
    from scenes import TEST_SCENES, TRAIN_SCENES, VALIDATION_SCENES, list_scenes, make_scene

    names = args.names or list_scenes()
    for name in names:
        scene = make_scene(name)
        line = scene.summary()
        if scene.routes:
            length, steps = route_drive(scene.route)
            line += f"; its route {length:.0f} m, a drive of about {steps * RobotConfig.dt:.0f} s ({steps} steps)"
        print(line)
    if not args.names:
        print(f"\ntraining environments ({len(TRAIN_SCENES)}): {', '.join(TRAIN_SCENES)}")
        print(f"validation: {', '.join(VALIDATION_SCENES)}")
        print(f"test (families unseen in training): {', '.join(TEST_SCENES)}")
    return 0


def _cmd_envs(args: argparse.Namespace) -> int:
    from l3e_env import ENV_IDS

    for env_id, (scene, steps) in ENV_IDS.items():
        print(f"{env_id:18s} scene '{scene}', at most {steps} steps an episode")
    return 0


def _cmd_ate(args: argparse.Namespace) -> int:
    from l3e_env.experiments.ate import AteOptions, run_ate, run_ate_seeds
    from l3e_env.sim.lidar import DESKEW_STEPS

    # a recording holds its scene's route, axes and scale: a mesh given with it is where the mesh moved to
    params = {} if args.recording and not mesh_options_given(args) else scene_params(args)
    stem = "replay" if args.recording else Path(args.scene).stem  # a replay's scene is the recording's
    out = Path(args.out or f"l3e_out/ate-{stem}-{time.strftime('%Y%m%d-%H%M%S')}")
    args.out = str(out)  # the resolved options are written beside it
    if args.seeds < 1 or (args.seeds > 1 and args.recording):
        raise CommandError("--seeds is 1 or more drives, and a recording is one drive")
    print(f"writing the experiment into {out.resolve()}")
    detectors = args.detector or list(DEFAULT_ATE_DETECTORS)
    options = AteOptions(
        sensor=args.sensor,
        seed=args.seed,
        recording=args.recording,
        scene_params=params,
        workers=args.workers,
        fusion_settings=fusion_settings(args),
        max_steps=args.max_steps,
        baselines=args.baseline or [],
        frontends=args.frontend or ["icp"],
        rerun=args.rerun,
    )
    if args.seeds > 1:
        seeds = range(args.seed, args.seed + args.seeds)
        done = run_ate_seeds(
            out,
            args.scene,
            detectors,
            seeds,
            options,
            on_drive=lambda seed, run: print(
                f"drive {seed - args.seed + 1} of {args.seeds} (seed {seed})\n{run.table()}"
            ),
            progress=not args.quiet,
        )
        print(done.table())
        print("written: " + ", ".join(map(str, done.written)))
        return 0
    run = run_ate(out, args.scene, detectors, options, progress=not args.quiet)
    print(run.table())
    if run.swept:
        turn = "the gyro's rotation over it" if args.deskew == "gyro" else "the odometry's rotation"
        print(
            "the recording's scans are swept over the robot's motion; each was deskewed with the leg "
            f"odometry's mean motion over its last {DESKEW_STEPS} steps, with {turn}, before it was judged "
            "and registered"
        )
    return 0


def record_imu(args: argparse.Namespace):
    """The ImuConfig that `l3e record`'s options ask for; None where --imu-rate is 0."""
    from l3e_env.sim.imu import ImuConfig

    if not args.imu_rate:
        return None
    return ImuConfig(
        rate=args.imu_rate,
        orientation=args.imu_orientation,
        footfall_accel=ImuConfig.footfall_accel if args.imu_footfalls else 0.0,
    )


def _cmd_record(args: argparse.Namespace) -> int:
    from l3e_env.experiments.drive import DriveOptions, record_run
    from l3e_env.io.rosbag import BagRecorder

    params = scene_params(args)
    if not args.imu_rate >= 0:
        raise CommandError(f"--imu-rate must be 0 (no IMU) or more, got {args.imu_rate}")
    from l3e_env.io.rosbag import bag_size_bound
    from l3e_env.sim.follower import route_drive
    from l3e_env.sim.patterns import get_pattern
    from scenes import make_scene

    if args.rerun:
        from l3e_env.experiments.rerun_log import check_rerun

        check_rerun()  # rerun-sdk missing: said before the drive
    pattern = get_pattern(args.sensor)
    scene = make_scene(args.scene, **params)  # built once: the size estimate and the drive share it
    if not args.still >= 0:
        raise CommandError(f"--still is 0 s or more, got {args.still}")
    from l3e_env.config import RobotConfig

    steps = min(route_drive(scene.route)[1] + int(round(args.still / RobotConfig.dt)), args.max_steps or 10**9)
    size = bag_size_bound(pattern.n_beams * pattern.n_azimuth, steps + 1, args.sweep)
    shown = f"{size / 2**30:.1f} GiB" if size >= 2**30 else f"{size / 2**20:.0f} MiB"
    print(f"recording about {steps + 1} scans of {pattern.name}: the bag's scans take up to {shown}", flush=True)
    bag = BagRecorder(args.out, ros2=args.ros2, imu=record_imu(args), seed=args.seed)  # a BagError: the command's
    try:
        options = DriveOptions(args.sensor, args.seed, params, args.sweep, args.max_steps, args.still)
        rec = record_run(args.scene, options, not args.quiet, scene_object=scene, on_step=bag)
        written = bag.close()
    except BaseException:
        bag.abort()  # no half-written bag beside the name
        raise
    print(f"written: {written} ({bag.steps} scans)")
    if args.recording:
        Path(args.recording).parent.mkdir(parents=True, exist_ok=True)
        rec.save(args.recording)
        print(f"written: {args.recording} (l3e ate --recording {args.recording} fuses this same drive)")
    if args.rerun:
        from l3e_env.experiments.fuse import odometry_only
        from l3e_env.experiments.rerun_log import log_drive, open_command

        log_drive(args.rerun, scene.mesh, rec, [odometry_only(rec)], RobotConfig.dt)
        print(f"written: {args.rerun} (the drive and the legs' estimate; open it with: {open_command(args.rerun)})")
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from l3e_env.experiments.tau_sweep import DEFAULT_KAPPAS, DEFAULT_TAUS, SweepOptions, beaten_everywhere, run_sweep

    out = Path(args.out or f"l3e_out/sweep-{time.strftime('%Y%m%d-%H%M%S')}")
    args.out = str(out)  # the resolved options are written beside it
    print(f"writing the sweep into {out.resolve()}")
    taus = args.taus or DEFAULT_TAUS
    recordings = dict(r.split("=", 1) for r in args.recording or [])
    options = SweepOptions(
        taus=tuple(taus),
        kappas=DEFAULT_KAPPAS if args.kappas is None else tuple(args.kappas),
        xicps=tuple(args.xicps or ()),
        drpms=tuple(args.drpms or ()),
        fusion_settings=fusion_settings(args),
    )
    results = run_sweep(out, args.scene or ["tunnel", "field", "office"], options, recordings, not args.quiet)
    best = beaten_everywhere(results, "learned")
    print(
        "taus at least as good as the learned detector in every scene: "
        + (", ".join(f"{t:g}" for t in best) if best else "none")
    )
    print(f"plot: {out / 'tau_sweep.png'}")
    return 0


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="drive the mine route and save a top view and scan pictures")
    p.add_argument("--out", help="output folder (default: l3e_out/demo-<time>)")
    p.add_argument("--scene", type=scene_name, default="mine", help="scene name (default: mine)")
    p.add_argument("--sensor", type=sensor_name, default="vlp16", help=SENSOR_HELP)
    p.add_argument("--seed", type=int, default=0)
    add_max_steps(p)
    p.add_argument("--checkpoint", help="classifier checkpoint (default: the shipped model)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_rerun_option(p, "the drive (default: drive.rrd in the output folder, where rerun-sdk is installed)")
    add_mesh_options(p)
    p.set_defaults(func=_cmd_demo)


def _add_scenes(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenes", help="list scenes and the train/validation/test split")
    p.add_argument("names", nargs="*", type=scene_name, help="scene names to describe (default: all families)")
    p.set_defaults(func=_cmd_scenes)


def _add_envs(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("envs", help="list the registered Gymnasium environment ids")
    p.set_defaults(func=_cmd_envs)


def _add_odometry_options(p: argparse.ArgumentParser) -> None:
    """The external LiDAR odometries `l3e ate` runs as rows of their own or as the fusion's front end."""
    p.add_argument(
        "--baseline",
        action="append",
        choices=["kiss-icp", "genz-icp"],
        help="also run this external LiDAR odometry on the drive's scans, with its authors' defaults, as a "
        "row of its own; repeat for both (needs pip install 'l3e[baselines]')",
    )
    p.add_argument(
        "--frontend",
        action="append",
        choices=["icp", "kiss-icp", "genz-icp"],
        help="the LiDAR steps the fusion takes: scan-to-scan ICP (default) or an external odometry's "
        "relative motions, masked by the detectors and fused with the legs alike; repeat to fuse every "
        "detector with each (rows '<detector> @<front end>')",
    )


def _add_ate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ate", help="drive a route once, fuse with each detector, compare ATE")
    p.add_argument("--scene", type=scene_name, default="mine")
    p.add_argument(
        "--detector",
        action="append",
        type=detector_spec,
        help=f"{DETECTOR_GRAMMAR}; repeat for several (default: {', '.join(DEFAULT_ATE_DETECTORS)})",
    )
    p.add_argument("--backend", choices=FUSION_BACKENDS, default="graph", help="iSAM2 smoother or filterpy EKF")
    _add_odometry_options(p)
    p.add_argument("--sensor", type=sensor_name, default="vlp16", help=SENSOR_HELP)
    p.add_argument("--seed", type=int, default=0)
    add_max_steps(p)
    p.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="drive N times, seeds --seed ... --seed + N - 1, and summarise each detector's ATE over them",
    )
    p.add_argument("--recording", help="evaluate a saved recording.npz instead of driving again")
    p.add_argument(
        "--deskew",
        choices=DESKEW_SOURCES,
        default="gyro",
        help="a swept recording's scans are deskewed with the leg odometry's motion, turned by the "
        "gyro's rotation (default) or the odometry's own",
    )
    add_fusion_options(p)
    p.add_argument("--out", help="output folder (default: l3e_out/ate-<scene>-<time>)")
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes that judge the route with scanmc before the fusion (default 1)",
    )
    p.add_argument("--quiet", action="store_true")
    add_rerun_option(p, "the drive, its scans and each row's estimate, flags and error (FILE-seed-N.rrd with --seeds)")
    add_mesh_options(p)
    p.set_defaults(func=_cmd_ate)


def _add_record(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="drive a route once and write it as a ROS bag: full scans, leg odometry, "
        "ground truth (needs pip install 'l3e[bag]')",
    )
    p.add_argument("--out", required=True, help="the bag: a .bag file (ROS 1), or a folder with --ros2")
    p.add_argument("--ros2", action="store_true", help="write a ROS 2 bag (sqlite3) instead of ROS 1")
    p.add_argument("--scene", type=scene_name, default="mine")
    p.add_argument("--sensor", type=sensor_name, default="vlp16", help=SENSOR_HELP)
    p.add_argument("--seed", type=int, default=0)
    add_max_steps(p)
    p.add_argument("--recording", help="also save the drive as a recording.npz for l3e ate --recording")
    add_rerun_option(p, "the drive, its scans and the legs' estimate")
    p.add_argument("--imu-rate", type=float, default=200.0, help="rate of /imu in Hz (default 200; 0: no IMU)")
    p.add_argument(
        "--imu-orientation",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="write a nine-axis unit's orientation in /imu (default), or none as a six-axis unit",
    )
    p.add_argument(
        "--sweep",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="sweep each revolution over the step's motion and write each point's time, as a spinning "
        "sensor on a moving robot does (default), or take each revolution at one pose",
    )
    p.add_argument(
        "--still",
        type=float,
        default=3.0,
        metavar="SECONDS",
        help="the robot first stands still this long, so that a LiDAR-inertial odometry's IMU initialiser "
        "sees gravity alone (default 3 s, DLIO's calibration time; FAST-LIO needs less; 0: none)",
    )
    p.add_argument(
        "--imu-footfalls",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="jolt /imu at each footfall while walking, as a legged robot's body rings (default), or not",
    )
    p.add_argument("--quiet", action="store_true")
    add_mesh_options(p)
    p.set_defaults(func=_cmd_record)


def _add_sweep(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sweep", help="ATE against the eigenvalue threshold in several scenes, with the learned detector as reference"
    )
    p.add_argument("--scene", type=scene_name, action="append", help="repeat; default tunnel, field, office")
    p.add_argument("--taus", type=float_list, help="comma-separated thresholds (default 10 ... 300)")
    p.add_argument(
        "--kappas",
        type=float_list,
        help="comma-separated condition ratio thresholds of DCReg, swept beside tau (default 3 ... 1000)",
    )
    p.add_argument(
        "--xicps",
        type=float_list,
        help="comma-separated localizability thresholds of X-ICP to sweep as well (e.g. 30,60,100,150,300)",
    )
    p.add_argument(
        "--drpms",
        type=float_list,
        help="comma-separated signal-to-noise factors of DRPM to sweep as well (e.g. 1,3,10,30,100)",
    )
    p.add_argument("--recording", action="append", help="SCENE=recording.npz to skip driving that scene")
    add_fusion_options(p)
    p.add_argument("--out", help="output folder (default: l3e_out/sweep-<time>)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_sweep)


def register(sub: argparse._SubParsersAction) -> None:
    _add_demo(sub)
    _add_scenes(sub)
    _add_envs(sub)
    _add_ate(sub)
    _add_record(sub)
    _add_sweep(sub)
