"""Argument types and option groups that several commands share."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

from l3e_env.config import ATTITUDE_MODES, GROUND_MODES, FusionSettings
from l3e_env.config.sections import KEYFRAME_DISTANCE
from l3e_env.io.mesh_lists import meshes_file


def scene_name(text: str) -> str:
    """argparse type: a scene name or mesh path, refused at parse time (before any folder or worker)."""
    from scenes import SceneError, check_scene_name

    try:
        return check_scene_name(text)
    except SceneError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def scene_names(text: str) -> list[str]:
    """argparse type: comma-separated scene names, each checked as `scene_name` does; 'family-A..B'
    stands for the variants A to B ('bypass-100..149')."""
    names = []
    for part in (p.strip() for p in text.split(",")):
        family, dash, span = part.rpartition("-")
        first, dots, last = span.partition("..")
        if dash and dots:
            if not (first.isdigit() and last.isdigit() and int(first) <= int(last)):
                raise argparse.ArgumentTypeError(
                    f"'{part}': a range of variants is family-FIRST..LAST, such as bypass-100..149"
                )
            names += [scene_name(f"{family}-{k}") for k in range(int(first), int(last) + 1)]
        else:
            names.append(scene_name(part))
    return names


SENSOR_HELP = (
    "a built-in LiDAR (vlp16, vlp16-calibrated, hdl32e, vlp32c, os0-128, os<0|1|2>-<32|64|128>, xt32, "
    "pandar64) or a beam pattern file (.yaml/.json, or an Ouster metadata .json)"
)


def bias_axes(text: str) -> tuple[str, ...]:
    """argparse type: "none", or comma-separated axes among fusion.bias.BIAS_AXES ("yaw", "yaw,z,scale")."""
    from fusion.bias import BIAS_AXES, check_bias_axes

    axes = () if text.strip() == "none" else tuple(a.strip() for a in text.split(","))
    try:
        check_bias_axes(axes)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected none or distinct axes among {', '.join(BIAS_AXES)} separated by commas, got {text!r}"
        ) from None
    return axes


def add_fusion_options(parser: argparse.ArgumentParser) -> None:
    """--attitude, --odometry-bias, --keyframe-distance and --ground, read back by `fusion_settings` (`l3e ate`,
    `l3e sweep`, `l3e policy evaluate`); an option not given takes the one estimator's default
    (`FusionSettings()`)."""
    default = FusionSettings()
    shown = ",".join(default.odometry_bias) or "none"
    parser.add_argument(
        "--mask",
        choices=("mask", "directions", "gate"),
        help="how a flagged axis leaves the ICP factor: mask = its rows and columns on the scan's level axes, "
        "directions = only the information's own directions that lie mostly along it, gate = as mask where "
        "ICP's step along it disagrees with the legs' beyond 3 sigma of theirs, kept where it agrees "
        f"(default: {default.mode})",
    )
    parser.add_argument(
        "--attitude",
        choices=ATTITUDE_MODES,
        help="fuse the IMU's orientation once a second: tilt = roll and pitch, which gravity holds "
        "(no heading: underground a magnetometer reads the rock), full = with the magnetometer's "
        f"heading, none = not at all (default: {default.attitude})",
    )
    parser.add_argument(
        "--odometry-bias",
        type=bias_axes,
        action="extend",
        metavar="AXES",
        help="estimate the leg odometry's biases as states of the fusion: yaw, z (per metre), "
        f"scale (the stride's), comma-separated or repeated, or none (default {shown}; see "
        "docs/decisions.md)",
    )
    parser.add_argument(
        "--keyframe-distance",
        type=float,
        metavar="METRES",
        help="register each scan onto a keyframe renewed every that many metres, from the leg odometry's "
        f"guess (0: each scan onto the one before; default {KEYFRAME_DISTANCE:g} with the graph, 0 with the EKF)",
    )
    parser.add_argument(
        "--ground",
        choices=GROUND_MODES,
        help="plane = each keyframe's fitted ground plane holds the robot's height above and tilt against the "
        "ground patch it stands on (a new patch where the ground the legs walk steps or tilts), none = not "
        "used (default plane with the graph, none with the EKF)",
    )
    parser.add_argument(
        "--detector-every",
        type=int,
        metavar="K",
        help="the detector judges every K-th scan and its answer holds in between: K times less detector "
        f"work, a flag late by at most K-1 steps (default {default.detector_every})",
    )


class CommandError(ValueError):
    """A command's options or inputs that it cannot use: `l3e` prints it as the command's error and exits
    with 2, as it does every library error (the one way a command reports one)."""


def fusion_settings(args: argparse.Namespace) -> FusionSettings:
    """The fusion's settings from the options that `add_fusion_options` added, and from --backend and
    --deskew where the command has them; the one estimator's defaults where an option is not given."""
    default = FusionSettings()
    axes = default.odometry_bias if args.odometry_bias is None else tuple(args.odometry_bias)
    if len(set(axes)) < len(axes):
        raise ValueError(f"--odometry-bias names an axis twice: {', '.join(axes)}")

    def given(name: str) -> Any:
        value = getattr(args, name, None)
        return getattr(default, name) if value is None else value

    mask = getattr(args, "mask", None)
    return FusionSettings(
        backend=given("backend"),
        mode=default.mode if mask is None else mask,
        deskew=given("deskew"),
        attitude=given("attitude"),
        odometry_bias=axes,
        keyframe_distance=getattr(args, "keyframe_distance", None),  # None: the backend's default
        detector_every=given("detector_every"),
        ground=getattr(args, "ground", None),  # None: the backend's default
    )


def sensor_name(text: str) -> str:
    """argparse type: a registered LiDAR model (vlp16, os0-128 or one added with register_pattern),
    or a beam pattern file."""
    from l3e_env.sim.lidar import get_pattern

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
        g.add_argument(
            "--meshes",
            help="YAML list of mesh scenes: mesh, route (a file or a list), up_axis, scale; "
            "paths relative to the YAML's folder (they join the scenes given)",
        )
    g.add_argument(
        "--route",
        action="append",
        help="text file of waypoints on the floor, one 'x y z' per line, in the mesh's axes and units "
        "(needed to drive a mesh); repeat for more paths: the first is the one driven, and labels "
        "are sampled along all of them (the galleries of a mine)",
    )
    g.add_argument("--up-axis", dest="up_axis", choices=["x", "y", "z"], help="the mesh's up axis (default z)")
    g.add_argument("--scale", type=float, help="metres per mesh unit (default 1; 0.001 for millimetres)")
    g.add_argument(
        "--snap-route",
        dest="snap_route",
        action="store_true",
        default=None,
        help="set each waypoint's height to the floor under it (the first upward-facing surface within "
        "2 m above it down to 0.5 m below): for 'x y' routes over a raised or uneven floor",
    )


def mesh_options_given(args: argparse.Namespace) -> list[str]:
    """The mesh options set on the command line, as spelt there."""
    return [
        f"--{n.replace('_', '-')}"
        for n in ("route", "up_axis", "scale", "snap_route")
        if getattr(args, n, None) is not None
    ]


def scene_params(args: argparse.Namespace, scene: str | None = None) -> dict:
    """make_scene's keyword arguments for `scene` (default args.scene) from the mesh options;
    ValueError where they do not apply."""
    from scenes import is_mesh_path, load_route

    scene = scene or args.scene
    given = mesh_options_given(args)
    if not is_mesh_path(scene):
        if given:
            raise ValueError(
                f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} only for a scene given as "
                f"a mesh file, not for '{scene}'"
            )
        return {}
    if args.route is None:
        raise ValueError(f"to drive or label the mesh {scene}, give its route: --route FILE (waypoints on its floor)")
    up_axis, scale = args.up_axis or "z", 1.0 if args.scale is None else args.scale
    routes = [load_route(path, up_axis, scale) for path in args.route]
    return {
        "up_axis": up_axis,
        "scale": scale,
        "sampling_paths": [route.tolist() for route in routes],
        **({"snap_to_floor": True} if getattr(args, "snap_route", None) else {}),
    }


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
        raise ValueError(
            f"one mesh file in --scenes, as --route gives one mesh's route; got {', '.join(meshes)} "
            "(list several meshes with their routes in a --meshes file)"
        )
    if not meshes:
        scene_params(args, (args.scenes or ["the preset's scenes"])[0])  # refuses stray mesh options
        return args.scenes, {}
    params = scene_params(args, meshes[0])
    return [canonical_scene_name(s) for s in args.scenes], {canonical_scene_name(meshes[0]): params}


def number_between(low: float, high: float) -> Callable[[str], float]:
    """argparse type: a finite number from `low` to `high`."""

    def number(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not low <= value <= high:  # NaN fails too
            raise argparse.ArgumentTypeError(f"expected a number from {low:g} to {high:g}, got {text!r}")
        return value

    return number


def add_max_steps(parser: argparse.ArgumentParser) -> None:
    """--max-steps: a short drive (`l3e demo`, `l3e ate`, `l3e record`)."""
    parser.add_argument(
        "--max-steps",
        type=int,
        dest="max_steps",
        help="stop the drive after this many steps of 0.1 s (a short run; default: the route's end)",
    )


def rerun_file(text: str) -> str:
    """--rerun's value: a path ending in .rrd."""
    if not text.lower().endswith(".rrd"):
        raise argparse.ArgumentTypeError(f"a Rerun recording is a .rrd file, got '{text}'")
    return text


def add_rerun_option(parser: argparse.ArgumentParser, what: str) -> None:
    """--rerun FILE.rrd: the run as a Rerun recording (experiments.rerun_log; the `viewer` extra)."""
    parser.add_argument(
        "--rerun",
        type=rerun_file,
        metavar="FILE.rrd",
        help=f"also write {what} as a Rerun recording, opened with 'rerun FILE.rrd' (needs pip install 'l3e[viewer]')",
    )


def add_device_option(parser: argparse.ArgumentParser) -> None:
    """--device: where the network runs (cpu, cuda, auto); the classifier names a missing GPU."""
    parser.add_argument(
        "--device",
        default="cpu",
        help="where the network runs: cpu (default), cuda (or cuda:N; an error where torch sees no GPU), "
        "auto (a GPU where there is one)",
    )
