"""`l3e policy ...`: localizability maps, planning, PPO training and evaluation of navigation policies.

Registered with the `l3e` command through the `l3e.commands` entry-point group."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from l3e_env.cli.options import (
    SENSOR_HELP,
    add_fusion_options,
    add_mesh_options,
    add_rerun_option,
    fusion_settings,
    mesh_options_given,
    number_between,
    scene_names,
    scene_params,
    sensor_name,
)
from l3e_env.config import EnvConfig
from l3e_env.config.detector_spec import DETECTOR_GRAMMAR, MAP_DETECTORS, parse_detector
from l3e_env.io.mesh_lists import meshes_file

from . import MAP_RESOLUTION

if TYPE_CHECKING:
    from .locmap import LocalizabilityMap


def _scenes_with_params(args: argparse.Namespace, default: tuple[str, ...] = ("bypass",)) -> dict[str, dict]:
    """Each scene (--scene, else `default`) with make_scene's keyword arguments; the mesh options
    describe one mesh scene, named by its absolute path so that an evaluation folder knows it from
    any working folder."""
    from scenes import canonical_scene_name

    if args.meshes:  # the listed meshes, after the scenes given (no default variants then)
        names = [canonical_scene_name(s) for group in args.scene or [] for s in group]
        listed = meshes_file(args.meshes, names, mesh_options_given(args))
        return {**{name: {} for name in names}, **listed}
    names = [canonical_scene_name(s) for group in args.scene or [list(default)] for s in group]
    if len(names) > 1 and mesh_options_given(args):
        raise ValueError(
            "--route, --up-axis and --scale describe one mesh: give it as the only --scene, or list "
            "several meshes in a --meshes file"
        )
    return {name: scene_params(args, name) for name in names}


def _cmd_map(args: argparse.Namespace) -> int:
    from .plots import plot_locmap

    scenes = _scenes_with_params(args)
    out = Path(args.out or "l3e_out/maps")
    args.out = str(out)  # the resolved options are written beside it
    for name, params in scenes.items():
        t0 = time.perf_counter()
        ctx = _context(args, name, params, args.resolution)
        out.mkdir(parents=True, exist_ok=True)  # once there is a map to draw: a refused scene leaves no folder
        figure = out / f"{ctx.scene.name}-{args.detector.replace(':', '')}.png"
        plot_locmap(figure, ctx.scene, ctx.locmap, ctx.space)
        share = " ".join(
            f"{a} {100 * v:.0f}%"
            for a, v in zip(["x", "y", "z", "roll", "pitch", "yaw"], ctx.locmap.masked.mean(axis=(0, 1)))
        )
        print(
            f"{ctx.scene.name}: {len(ctx.locmap.positions)} positions x {len(ctx.locmap.yaws)} headings, "
            f"masked: {share}{_estimated_share(ctx.locmap, args.detector)} ({time.perf_counter() - t0:.0f} s) "
            f"-> {figure}"
        )
    return 0


def _estimated_share(locmap: LocalizabilityMap, detector: str) -> str:
    """For a cascade map, the share of poses that scanmc judged: what the map cost beyond the classifier."""
    if not detector.startswith("learned+scanmc"):
        return ""
    if locmap.estimated is None:
        return "; scanmc's share not recorded in this cached map"
    return f"; scanmc judged {100 * locmap.estimated.mean():.0f}% of the poses"


def _cmd_plan(args: argparse.Namespace) -> int:
    from .planner import Planner
    from .plots import plot_paths

    scenes = _scenes_with_params(args)
    out = Path(args.out or "l3e_out/plans")
    args.out = str(out)  # the resolved options are written beside it
    for name, params in scenes.items():
        ctx = _context(args, name, params, args.resolution)
        start = np.array(args.start, dtype=float) if args.start else ctx.scene.start[:2]
        goal = np.array(args.goal, dtype=float) if args.goal else ctx.scene.goal
        plans = {
            "shortest": Planner(ctx.space, ctx.locmap, lam=0.0).plan(start, goal),
            f"planner (lambda {args.lam:g})": Planner(ctx.space, ctx.locmap, lam=args.lam).plan(start, goal),
        }
        for label, plan in plans.items():
            print(
                f"{ctx.scene.name} {label:22s} length {plan.length:6.1f} m, expected drift {plan.expected_drift:5.2f} m"
            )
        out.mkdir(parents=True, exist_ok=True)  # once there is something to draw: a refused plan leaves no folder
        figure = out / f"{ctx.scene.name}-plans.png"
        plot_paths(
            figure,
            ctx.scene,
            {k: v.path for k, v in plans.items()},
            ctx.space,
            title=f"{ctx.scene.name}: shortest path and localizability-aware plan ({args.detector} map)",
        )
        print(f"  -> {figure}")
    return 0


def non_negative(text: str) -> float:
    """argparse type: a finite number, 0 or more."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number, 0 or more, got {text!r}")
    return value


def _cmd_train(args: argparse.Namespace) -> int:
    from .ppo import TRAIN_VARIANTS, PPOTraining, WarmStart, require_sb3, resumed_config, train_ppo

    require_sb3()  # before minutes of maps, not after
    scenes = _scenes_with_params(args, tuple(TRAIN_VARIANTS))
    print(f"PPO on {', '.join(scenes)} (fast map environment, {args.detector} maps) -> {Path(args.out).resolve()}")
    contexts = [_context(args, name, params) for name, params in scenes.items()]
    config = resumed_config(args.out, lam=args.lam, lateral_drift=args.lateral_drift, sideways=args.sideways)
    training = PPOTraining(args.timesteps, args.seed, args.envs, WarmStart() if args.warm_start else None)
    summary = train_ppo(args.out, contexts, args.detector, training, config, progress=not args.quiet)
    print(f"{summary['timesteps']} steps; policy: {Path(args.out) / 'policy.pt'}; logs: progress.csv, monitor.csv")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import EvalOptions, evaluate_policies, format_rows
    from .ppo import EVAL_VARIANTS

    scenes = _scenes_with_params(args, tuple(EVAL_VARIANTS))
    out = Path(args.out or f"l3e_out/policy-eval-{time.strftime('%Y%m%d-%H%M%S')}")
    args.out = str(out)  # the resolved options are written beside it
    print(
        f"{args.episodes} episodes per policy on {', '.join(scenes)}, full pipeline ({args.detector} detector) "
        f"-> {out.resolve()}"
    )
    options = EvalOptions(
        episodes=args.episodes,
        seed=args.seed,
        detector=args.detector,
        cache_dir=args.cache_dir,
        lam=args.lam,
        workers=args.workers,
        steer_on=args.steer_on,
        stop_radius=args.stop_radius,
        map_resolution=args.resolution,
        fusion_settings=fusion_settings(args),
        recovery=args.recovery,
        avoid=args.avoid,
        scene_params={k: v for k, v in scenes.items() if v},
        rerun=args.rerun,
    )
    rows = evaluate_policies(out, args.policy or ["shortest", "planner"], list(scenes), options, not args.quiet, _say)
    print(format_rows(rows))
    print(f"routes: {out / 'routes.png'}")
    return 0


def _context(args: argparse.Namespace, name: str, params: dict | None, resolution: float | None = None):
    """The scene with the map of the command's detector on its sensor's grid, built where not cached."""
    from .context import scene_context
    from .locmap import MapBuild

    grid = map_grid(args.sensor, resolution)
    build = MapBuild(getattr(args, "workers", 1), not args.quiet, _say)
    return scene_context(name, args.detector, args.cache_dir, build, grid, not args.quiet, params)


def map_grid(sensor: str, resolution: float | None = None):
    """The maps' grid for a sensor (and a spacing of mapped positions; the default where None)."""
    from l3e_env.config import LidarConfig

    from .locmap import MapGrid

    return MapGrid(resolution=resolution or MAP_RESOLUTION, lidar=LidarConfig(model=sensor))


def map_detector(text: str) -> str:
    """argparse type: a detector spec a map can use (any but 'none')."""
    try:
        parse_detector(text, allowed=MAP_DETECTORS, what="map detector")
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _say(message: str) -> None:
    print(message, flush=True)


def _add_map(psub: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    g = psub.add_parser("map", parents=[common], help="build (or load) and plot localizability maps")
    g.add_argument(
        "--scene",
        type=scene_names,
        action="append",
        help="scene names, comma-separated or repeated (default: bypass, the family's first variant)",
    )
    g.add_argument(
        "--detector", default="learned", type=map_detector, help=f"{DETECTOR_GRAMMAR}, not none (default: learned)"
    )
    _add_resolution(g)
    g.add_argument("--out", help="folder for the plots (default: l3e_out/maps)")
    g.add_argument("--workers", type=int, default=1, help="processes that build a map not yet cached")
    add_mesh_options(g, several=True)
    g.set_defaults(func=_cmd_map)


def _add_resolution(g: argparse.ArgumentParser) -> None:
    """--resolution: the spacing of the maps' positions, one option for map, plan and evaluate (a map
    built by `policy map --resolution R` is the one the others read with the same R)."""
    g.add_argument(
        "--resolution", type=float, default=MAP_RESOLUTION, help="metres between mapped positions (default %(default)g)"
    )


def _add_plan(psub: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    g = psub.add_parser("plan", parents=[common], help="shortest path and localizability-aware plan, with a plot")
    g.add_argument(
        "--scene", type=scene_names, action="append", help="scene names (default: bypass, the family's first variant)"
    )
    g.add_argument("--detector", default="learned", type=map_detector, help="map detector (default: learned)")
    g.add_argument("--lam", type=float, default=50.0, help="weight of expected drift against length (default 50)")
    g.add_argument(
        "--start", type=number_between(-1e5, 1e5), nargs=2, metavar=("X", "Y"), help="default: the scene's start"
    )
    g.add_argument("--goal", type=float, nargs=2, metavar=("X", "Y"), help="default: the scene's goal")
    g.add_argument("--out", help="folder for the plots (default: l3e_out/plans)")
    _add_resolution(g)
    g.add_argument("--workers", type=int, default=1, help="processes that build a map not yet cached")
    add_mesh_options(g, several=True)
    g.set_defaults(func=_cmd_plan)


def _add_train(psub: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    g = psub.add_parser("train", parents=[common], help="train a PPO navigation policy on bypass variants (resumable)")
    g.add_argument("--out", required=True, help="run folder (an unfinished run there is resumed)")
    g.add_argument("--scene", type=scene_names, action="append", help="training variants (default: bypass-0..7)")
    g.add_argument("--detector", default="learned", type=map_detector, help="map detector (default: learned)")
    g.add_argument("--timesteps", type=int, default=300_000, help="decisions of 0.5 s (default 300000)")
    g.add_argument(
        "--warm-start",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="a new run first clones the planner's choice (the observation's localizability-aware "
        "direction) from noisy walks of every training scene, then PPO goes on from there "
        "(default: on; a resumed run goes on from its own weights)",
    )
    g.add_argument("--envs", type=int, default=4, help="environments stepped together (default 4)")
    g.add_argument(
        "--lam",
        type=non_negative,
        help="weight of expected drift in the reward (default: a resumed run's own, else 50)",
    )
    g.add_argument(
        "--lateral-drift",
        type=non_negative,
        metavar="M",
        help="expected drift charged per metre walked sideways (default: a resumed run's own, else 0.015)",
    )
    g.add_argument(
        "--sideways",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the policy's action is the twist (vx, vy, yaw rate); with --no-sideways (vx, yaw rate), "
        "walking facing its way as the route followers do (default: a resumed run's own, else on)",
    )
    g.add_argument("--seed", type=int, default=0)
    add_mesh_options(g, several=True)
    g.set_defaults(func=_cmd_train)


def _add_driving_options(g: argparse.ArgumentParser) -> None:
    """How the evaluation's robot drives: its recovery, its local layer, the pose it steers on and
    where it stops."""
    g.add_argument(
        "--recovery",
        action=argparse.BooleanOptionalAction,
        help="a robot blocked for 1 s backs off along its last command reversed for 1 s, then the "
        "policy acts again (default: a resumed folder's own, else on)",
    )
    g.add_argument(
        "--avoid",
        action=argparse.BooleanOptionalAction,
        help="the policies keep off what the live scan shows ahead (a free heading nearest the one "
        "wanted), as a robot's local planner does (default: a resumed folder's own, else on)",
    )
    g.add_argument(
        "--steer-on",
        dest="steer_on",
        choices=["estimate", "truth"],
        default="estimate",
        help="pose the policies steer on (default: the fused estimate); ATE is measured either way",
    )
    g.add_argument(
        "--stop-radius",
        dest="stop_radius",
        type=float,
        default=EnvConfig().stop_radius,
        metavar="METRES",
        help="steering on the estimate, the robot stops once its estimate is this close to the goal; it "
        f"succeeds where its true pose is within {EnvConfig().goal_radius:g} m (default %(default)s)",
    )


def _add_evaluate(psub: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    g = psub.add_parser("evaluate", parents=[common], help="seeded full-pipeline episodes: success, route, ATE, length")
    g.add_argument(
        "--policy",
        action="append",
        help="shortest | planner | ppo:<run folder>; repeat (default: shortest and planner)",
    )
    g.add_argument(
        "--scene",
        type=scene_names,
        action="append",
        help="evaluation variants, comma-separated or repeated, a range as family-A..B such as "
        "bypass-100..149 (default: bypass-100..109; the fork family as fork-100..109)",
    )
    g.add_argument("--episodes", type=int, default=50, help="episodes per policy (default 50)")
    g.add_argument(
        "--detector",
        default="learned",
        type=map_detector,
        help="detector of the fusion and the planner's map (default: learned)",
    )
    g.add_argument("--lam", type=float, default=50.0, help="the planner's drift weight (default 50)")
    _add_resolution(g)
    g.add_argument("--workers", type=int, default=1, help="episodes run in parallel processes")
    _add_driving_options(g)
    add_fusion_options(g)
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--out", help="output folder (default: l3e_out/policy-eval-<time>)")
    add_rerun_option(g, "each episode this run drives (map, paths, scans, flags) as FILE-<policy>-<scene>-<seed>.rrd")
    add_mesh_options(g, several=True)
    g.set_defaults(func=_cmd_evaluate)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("policy", help="navigation: localizability maps, planner, PPO training and evaluation")
    psub = p.add_subparsers(dest="policy_command", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--cache-dir", dest="cache_dir", help="map cache (default: $L3E_CACHE/maps or ~/.cache/l3e/maps)"
    )
    common.add_argument("--sensor", type=sensor_name, default="vlp16", help=SENSOR_HELP)
    common.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_map(psub, common)
    _add_plan(psub, common)
    _add_train(psub, common)
    _add_evaluate(psub, common)
