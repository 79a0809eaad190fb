"""One's own scans: `l3e judge` and `l3e sensor`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from l3e_env.config.detector_spec import DETECTOR_GRAMMAR, detector_spec

from .options import CommandError, add_device_option, add_rerun_option, sensor_name


def _judge_usage_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the combination of `l3e judge`'s options, or None."""
    from l3e_env.io.ouster import is_capture

    if bool(args.scans) == bool(args.bag):
        return "give scan files or --bag, not both and not neither"
    if not args.bag and (args.topic or args.every != 1 or args.start is not None or args.end is not None):
        return "--topic, --every, --start and --end read a recording: give --bag"
    if not args.bag and (args.path_plot or args.pose_topic):
        return "--path-plot and --pose-topic read the path from a bag: give --bag"
    if args.bag and is_capture(args.bag) and (args.topic or args.path_plot or args.pose_topic):
        return "--topic, --path-plot and --pose-topic read a ROS bag, not an Ouster capture"
    captures = [args.bag] if args.bag else list(args.scans)
    if args.sensor_index is not None and not any(is_capture(c) for c in captures):
        return "--sensor-index chooses the sensor of an Ouster capture (.osf, .pcap): none is given"
    return None


def _gravity(text: str | None):
    """--gravity's up direction(s): one vector X,Y,Z, or a text file of one X Y Z row per scan; None where
    not given. CommandError naming what is wrong."""
    import numpy as np

    if text is None:
        return None
    parts = text.split(",")
    if len(parts) == 3 and not Path(text).exists():
        try:
            return np.array([float(v) for v in parts])
        except ValueError:
            raise CommandError(f"--gravity {text!r}: three numbers X,Y,Z, or a file of one per scan") from None
    path = Path(text)
    if not path.is_file():
        raise CommandError(f"--gravity {text!r}: give X,Y,Z (the up direction in the sensor's frame) or a text file")
    try:
        with path.open() as f:
            delimiter = "," if "," in f.readline() else None
        rows = np.loadtxt(path, delimiter=delimiter, ndmin=2, comments="#")
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise CommandError(f"--gravity {path}: not a text file of X Y Z rows ({exc})") from None
    if rows.ndim != 2 or rows.shape[1] != 3 or not len(rows):
        raise CommandError(f"--gravity {path}: one X Y Z row per scan, got an array of shape {rows.shape}")
    return rows


def _judge_all(args: argparse.Namespace, scans, specs: list[str]) -> tuple[list, str | None]:
    """Every scan judged and printed as it is (an unreadable one named, and the next one read); returns
    the judgements and the sensor the scans were read as."""
    from l3e_env.config import LidarConfig
    from l3e_env.experiments.judge import JudgeOptions, format_judgement, judge_scans
    from l3e_env.experiments.rerun_log import MAX_SCAN_POINTS

    sensor = [args.sensor]

    def recognised(pattern, how: str) -> None:
        if pattern is None:
            sensor[0] = LidarConfig().model
            print(
                f"sensor: {how}; scanmc takes it as a {LidarConfig().model} and answers unknown for scans of "
                "another (give --sensor: a name, a pattern file or an Ouster's metadata JSON)",
                flush=True,
            )
        else:
            sensor[0] = pattern.name
            print(f"sensor: {how} (give --sensor to choose it)", flush=True)

    judgements = []
    for j in judge_scans(
        scans,
        specs,
        LidarConfig(model=args.sensor) if args.sensor else None,
        JudgeOptions(args.seed, args.workers, _gravity(args.gravity), args.device, MAX_SCAN_POINTS * bool(args.rerun)),
        on_sensor=recognised,
        sensor_index=args.sensor_index,
    ):
        judgements.append(j)
        stamp = "" if j.stamp is None else f"[t = {j.stamp:.3f} s] "
        print(stamp + format_judgement(j), file=sys.stderr if j.error else sys.stdout, flush=True)
    return judgements, sensor[0]


def _judge_path_plot(args: argparse.Namespace, judgements: list, where, route) -> None:
    """The flags along the bag's path; ValueError where it cannot be drawn."""
    import numpy as np

    from l3e_env.experiments.judge_plots import plot_path

    off = int((~np.isfinite(where).all(axis=1)).sum())
    if off:
        print(
            f"l3e judge: {off} scans lie outside the time of {route.topic}'s poses and are left off the map",
            file=sys.stderr,
        )
    plot_path(judgements, where, route.positions, args.path_plot, f"{Path(args.bag).name} on {route.topic}")
    print(f"written: {args.path_plot}")


def _cmd_judge(args: argparse.Namespace) -> int:
    import numpy as np

    from l3e_env.experiments.judge import score_legend, write_judgements
    from l3e_env.io.recordings import read_recording
    from l3e_env.io.rosbag import read_path

    if args.device != "cpu":  # a missing GPU is named before any scan is read
        from l3e_env.model.classifier import torch_device

        torch_device(args.device)
    problem = _judge_usage_problem(args)
    if problem:
        raise CommandError(problem)
    if args.rerun:
        from l3e_env.experiments.rerun_log import check_rerun

        check_rerun()  # rerun-sdk missing: said before any scan is judged
    metadata = args.sensor if args.sensor and args.sensor.lower().endswith(".json") else None
    scans = (
        read_recording(args.bag, args.topic, args.every, args.start, args.end, metadata, args.sensor_index)
        if args.bag
        else args.scans
    )
    route = read_path(args.bag, args.pose_topic) if args.bag and (args.path_plot or args.pose_topic) else None
    specs = args.detector or ["learned", "eigen:30", "scanmc"]
    judgements, sensor = _judge_all(args, scans, specs)
    print("scores ('*' flagged):\n" + score_legend(specs))
    where = None if route is None else route.at(np.array([j.stamp for j in judgements], dtype=np.float64))
    if args.json:
        print(f"written: {write_judgements(args.json, judgements, sensor, where)}")
    judged = any(j.predictions for j in judgements)
    if args.plot and judged:
        from l3e_env.experiments.judge_plots import plot_timeline

        plot_timeline(judgements, args.plot)
        print(f"written: {args.plot}")
    if args.path_plot and judged:
        _judge_path_plot(args, judgements, where, route)
    if args.rerun:
        from l3e_env.experiments.rerun_log import log_judged, open_command

        print(f"written: {log_judged(args.rerun, judgements)} (open it with: {open_command(args.rerun)})")
    failed = sum(j.error is not None for j in judgements)
    if not judgements:
        window = " between --start and --end" if args.start is not None or args.end is not None else ""
        topic = f" on topic {args.topic}" if args.topic else ""
        print(f"l3e judge: no scan in the recording{topic}{window}", file=sys.stderr)
    elif failed:
        print(f"l3e judge: {failed} of {len(judgements)} scans could not be read or judged", file=sys.stderr)
    return 2 if failed or not judgements else 0


def _cmd_sensor(args: argparse.Namespace) -> int:
    from l3e_env.experiments.judge import recognise_sensor
    from l3e_env.io.ouster import is_capture
    from l3e_env.io.recordings import read_recording
    from l3e_env.io.scan_files import read_scan
    from l3e_env.sim.patterns import PATTERN_FILES, PATTERNS, describe_pattern, get_pattern, save_pattern

    if bool(args.source) == bool(args.bag):
        raise CommandError("give a sensor (name or pattern file), a scan file or --bag, one of them")
    if args.source and (args.source in PATTERNS or args.source.lower().endswith(PATTERN_FILES)):
        pattern, how = get_pattern(args.source), "as given"
    else:
        recording = args.bag or (args.source if is_capture(args.source) else None)
        if recording is None:
            read_scan(args.source)  # a file that cannot be read is named here
            scans = iter([args.source])
        else:
            scans = read_recording(recording, args.topic, sensor_index=args.sensor_index, one_sensor=True)
        _, found, how = recognise_sensor(scans)
        if found is None:
            raise CommandError(how)
        pattern = found
    print(describe_pattern(pattern) + f"\n  ({how})")
    if args.out:
        print(f"written: {save_pattern(pattern, args.out)} (give it as --sensor)")
    return 0


def _add_judging_options(p: argparse.ArgumentParser) -> None:
    """`l3e judge`'s detectors, sensor and up direction."""
    p.add_argument(
        "--detector",
        action="append",
        type=detector_spec,
        help=f"{DETECTOR_GRAMMAR} (not oracle: it needs a scene); repeat for several (default: learned, "
        "eigen:30 and scanmc). In a place unlike the simulated training scenes the accurate one is scanmc "
        "(ICP on the scan's own mesh: a second or two a scan on one core, against the network's tens of "
        "milliseconds) or learned+scanmc (scanmc where the network is unsure); l3e adapt teaches the network "
        "a place from its own scans",
    )
    p.add_argument(
        "--sensor",
        type=sensor_name,
        help="the LiDAR that took the scans, for scanmc's beams: vlp16, os0-128 or a beam pattern file "
        "(.yaml/.json, or an Ouster metadata .json); default: recognised from the scans",
    )
    p.add_argument(
        "--sensor-index",
        type=int,
        metavar="I",
        help="judge only the I-th sensor's scans of an Ouster capture of several (default: every sensor's, "
        "each with its own beams)",
    )
    p.add_argument(
        "--gravity",
        metavar="X,Y,Z|FILE",
        help="the up direction (against gravity) in the sensor's frame, which the answers' axes are levelled "
        "by: one vector (--gravity=-0.2,0,1 where a number is negative), or a text file of one X Y Z row per "
        "scan (default: a bag's own IMU, turned into the cloud's frame by its /tf_static; else each scan's "
        "ground plane's fit)",
    )


def _add_judge(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "judge",
        help="judge your own scans (files or a ROS bag): along which axes would scan-to-scan registration fail there",
    )
    p.add_argument(
        "scans",
        nargs="*",
        metavar="SCAN",
        help="scan files in the sensor's frame: .npy .npz .bin (KITTI) .ply .pcd .xyz .txt .csv, "
        "or Ouster captures (.osf .pcap), every scan of them",
    )
    g = p.add_argument_group(
        "a recording instead of files: a ROS bag (needs pip install 'l3e[bag]') or an "
        "Ouster capture (also needs pip install --no-deps ouster-sdk==1.0.1)"
    )
    g.add_argument(
        "--bag",
        help="a ROS 1 .bag file, a ROS 2 bag folder (sqlite3 or mcap), or an Ouster .osf or "
        ".pcap (a .pcap's metadata JSON beside it or given as --sensor)",
    )
    g.add_argument("--topic", help="the bag's sensor_msgs/PointCloud2 topic (default: the only one)")
    g.add_argument("--every", type=int, default=1, help="judge every N-th scan (default 1: all)")
    g.add_argument("--start", type=float, help="seconds after the recording's start to begin at")
    g.add_argument("--end", type=float, help="seconds after the recording's start to stop at")
    g.add_argument("--path-plot", help="also draw the judged scans on a map of the bag's path into this image")
    g.add_argument(
        "--pose-topic",
        help="the path's topic: nav_msgs/Odometry, geometry_msgs/PoseStamped or "
        "PoseWithCovarianceStamped (default: the only Odometry topic); it also "
        "writes each scan's position into --json",
    )
    _add_judging_options(p)
    p.add_argument("--seed", type=int, default=0, help="seed of scanmc's children")
    p.add_argument("--workers", type=int, default=1, help="scans judged side by side in processes (default 1)")
    add_device_option(p)
    p.add_argument("--json", help="also write the scores here")
    p.add_argument("--plot", help="also draw the flagged axes scan by scan (over time for a bag) into this image")
    add_rerun_option(p, "each scan (in its level frame, coloured by its flags) and each detector's scores")
    p.set_defaults(func=_cmd_judge)


def _add_sensor(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sensor",
        help="show a LiDAR's beam pattern, or recognise it from a scan or a bag and "
        "save it as a pattern file for --sensor",
    )
    p.add_argument(
        "source",
        nargs="?",
        help="a sensor name, a pattern file, a scan file to recognise it from, or "
        "an Ouster capture (.osf .pcap) to read it from the metadata",
    )
    p.add_argument("--bag", help="recognise it from this ROS bag's first scans (or an Ouster capture's metadata)")
    p.add_argument("--topic", help="the bag's PointCloud2 topic (default: the only one)")
    p.add_argument("--sensor-index", type=int, metavar="I", help="the sensor of an Ouster capture of several")
    p.add_argument("--out", help="write the pattern here (.yaml or .json)")
    p.set_defaults(func=_cmd_sensor)


def register(sub: argparse._SubParsersAction) -> None:
    _add_judge(sub)
    _add_sensor(sub)
