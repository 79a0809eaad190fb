"""`l3e policy evaluate`: seeded episodes of navigation policies with the full pipeline (LiDAR,
detector, ICP and fusion in the loop of NavigationEnv). By default every policy steers on the fused
estimate, the pose the robot believes, so that a policy that walks where localization fails
pays for it in its ATE and may miss the goal; `steer_on="truth"` steers on the true pose and
still measures the fused estimate's error, separating route choice from getting lost.

Per episode: success (the true pose within the goal radius where the episode ended: steering on
the estimate, the robot stops where it believes the goal is, as a robot does, and is judged
there; steering on the truth, on arrival; within the time limit), whether it took the scene's
feature-rich route, final and mean position error of the fused estimate against ground truth,
path length, and (with `recovery`) how often the robot backed off a wedge. With `avoid` the
policies keep off what the live scan shows ahead (l3e_env.sim.avoidance), as a robot's local
planner does, so that an estimate a metre off turns a wall ahead into a detour round it."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from l3e_env.config import EnvConfig, FusionSettings, OdometryConfig, settings_changed
from l3e_env.core.transforms import yaw_of
from l3e_env.core.workers import process_context, worker_start
from l3e_env.envs import NavigationEnv, check_env_config
from l3e_env.sim.avoidance import FreeHeadings
from l3e_env.sim.follower import RouteFollower
from l3e_env.sim.odometry import odometry_fusion_config

from . import MAP_RESOLUTION
from .context import SceneContext, scene_context
from .locmap import MapBuild, MapGrid
from .observation import PolicyView
from .planner import Planner, drift_rates, expected_drift_along, route_of

ROUTE_POLICIES = ("shortest", "planner")  # route followers on a plan; "ppo:<folder>" is the learned one
POLICY_KINDS = (*ROUTE_POLICIES, "ppo:<policy folder or zip>")


@dataclass
class Episode:
    policy: str
    scene: str
    seed: int
    success: bool
    rich_route: bool | None  # kept out of the degenerate corridor; None where the scene marks none
    final_ate: float  # m, fused estimate against ground truth at the end
    mean_ate: float  # m, RMS over the episode
    path_length: float  # m, ground truth
    steps: int
    trajectory: list  # ground-truth (x, y) every 5 steps
    recoveries: int = 0  # times the robot backed off a wedge (with recovery on)
    # m, the planner's drift model summed along the path walked (the evaluation's detector map, the
    # environment's odometry): what the cost model expects of this route, beside final_ate
    expected_drift: float | None = None
    planned_drift: float | None = None  # m, the same model over the plan a route policy follows
    # m, the fused estimate less the truth at the end, (x, y, z) in the world: arrival is judged
    # across the ground, so its horizontal part is what a stop on the estimate misses by
    final_offset: list | None = None


class BackOff:
    """A wedged robot's recovery, as navigation stacks have one: once the controller's commands
    have been blocked `after` steps in a row, the reverse of its last command for `steps` steps,
    then the controller again. Without it a policy that pushes into a corner stays there."""

    def __init__(self, controller: Callable, after: int = 10, steps: int = 10):
        if after < 1 or steps < 1:
            raise ValueError(f"after and steps must be at least 1, got {after} and {steps}")
        self.controller, self.after, self.steps = controller, after, steps
        self.blocked = self.backing = self.recoveries = 0
        self.recovering = False
        self.last = np.zeros(3, dtype=np.float32)

    def __call__(self, T: np.ndarray, i: int, obstacles: np.ndarray | None = None) -> np.ndarray:
        self.recovering = self.backing > 0
        if self.recovering:
            self.backing -= 1
            return -self.last
        self.last = np.asarray(self.controller(T, i, obstacles), dtype=np.float32)
        return self.last

    def observe(self, blocked: bool) -> None:
        """After each step; a block while backing off does not count."""
        if self.recovering:
            return
        self.blocked = self.blocked + 1 if blocked else 0
        if self.blocked >= self.after:
            self.backing, self.blocked = self.steps, 0
            self.recoveries += 1


def avoided_corridor(trajectory: np.ndarray, scene) -> bool | None:
    """Whether a path kept out of the scene's degenerate 'corridor' region (the fork's smooth
    corridor); for scenes without one, whether it kept closer to the 'rich' route than to the
    'short' one (mean point-to-polyline distance); None for a scene with neither (a user's mesh)."""
    if "corridor" in scene.regions:
        x0, y0, x1, y1 = scene.regions["corridor"]
        xy = trajectory[:, :2]
        return not bool(((xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)).any())
    if not {"rich", "short"} <= set(scene.routes):
        return None

    def mean_distance(route: np.ndarray) -> float:
        return float(np.linalg.norm(trajectory[:, None, :2] - route[None, :, :2], axis=2).min(axis=1).mean())

    return mean_distance(scene.routes["rich"]) < mean_distance(scene.routes["short"])


def check_policy(policy: str) -> None:
    """Raises a ValueError for an unknown policy name, a PolicyCheckpointError for a PPO policy that
    cannot be loaded."""
    if policy.startswith("ppo:"):
        from .ppo import PPOPolicy

        PPOPolicy(policy.partition(":")[2])
    elif policy not in ROUTE_POLICIES:
        raise _unknown_policy(policy)


def _unknown_policy(policy: str) -> ValueError:
    return ValueError(f"unknown policy '{policy}'; use one of {', '.join(POLICY_KINDS)}")


@dataclass(frozen=True)
class MapSource:
    """Where a controller finds its scene and localizability map: the scene by name (with make_scene's
    arguments), the map of `detector` in `cache_dir` with positions `resolution` m apart, built already."""

    scene: str
    detector: str = "learned"
    cache_dir: str | Path | None = None
    scene_params: dict | None = None
    resolution: float = MAP_RESOLUTION

    @property
    def grid(self) -> MapGrid:
        return MapGrid(resolution=self.resolution)

    def context(self, detector: str | None = None) -> SceneContext:
        """The scene with the map of `detector` (this source's own by default)."""
        return scene_context(
            self.scene, detector or self.detector, self.cache_dir, False, self.grid, scene_params=self.scene_params
        )


class _FollowRoute:
    """A route policy's controller: its follower along the planned route (`route`, ground points (K, 3))."""

    def __init__(self, route: np.ndarray, avoid: FreeHeadings | None):
        self.follower, self.route = RouteFollower(route, avoid=avoid), route

    def __call__(self, T: np.ndarray, i: int, obstacles: np.ndarray | None) -> np.ndarray:
        return self.follower(T, obstacles)


def make_controller(
    policy: str,
    source: MapSource,
    lam: float,
    odometry: OdometryConfig | None = None,
    context: SceneContext | None = None,
    avoid: FreeHeadings | None = None,
) -> tuple[Callable[[np.ndarray, int, np.ndarray | None], np.ndarray], float | None]:
    """A function (T_w_b estimate, step index, the scan's obstacles or None) -> normalised twist, for
    one scene, and for a route policy the drift its plan is expected to cost (`odometry`: the
    environment's leg odometry, whose noise model gives the drift rates; `context`: the scene with
    the source's map, where the caller holds it; `avoid`: the local layer that keeps off the
    obstacles, None to follow the policy blind)."""
    if policy in ROUTE_POLICIES:
        ctx = context or source.context()
        plan = Planner(ctx.space, ctx.locmap, lam=lam if policy == "planner" else 0.0, odometry=odometry).plan(
            ctx.scene.start[:2], ctx.scene.goal
        )
        return _FollowRoute(route_of(plan, ctx.space), avoid), plan.expected_drift
    if policy.startswith("ppo:"):
        from .ppo import PPOPolicy

        model = PPOPolicy(policy.partition(":")[2])
        ctx = source.context(model.meta.get("detector", source.detector))
        view = PolicyView(ctx.space, ctx.built_map, ctx.scene.goal, float(model.meta["fast_env"]["lam"]))
        held = {"action": np.zeros(3, dtype=np.float32)}

        def act(T: np.ndarray, i: int, obstacles: np.ndarray | None) -> np.ndarray:
            if i % model.action_repeat == 0:
                held["action"] = model(view(T[0, 3], T[1, 3], yaw_of(T)))
            if avoid is None or obstacles is None:
                return held["action"]
            return avoid.guard(held["action"], obstacles)

        return act, None
    raise _unknown_policy(policy)


STEER_ON = ("estimate", "truth")


@dataclass(frozen=True)
class EvalOptions:
    """How an evaluation's episodes run (the fusion's backend and the rest as `fusion_settings` say; its
    detector is `detector`, the maps'). All but `workers` and `cache_dir` go into its settings.json,
    and a resumed evaluation must match them. `lam`: the planner's weight of expected drift; `steer_on`:
    the pose the robot steers and stops on (STEER_ON); `recovery`: a wedged robot backs off (BackOff);
    `avoid`: the policies keep off the obstacles the scan shows ahead (FreeHeadings), both None: as the
    folder's episodes so far, else on; `scene_params`: make_scene's arguments by scene name;
    `stop_radius`: steering on the estimate, the robot stops once its estimate is this close to the
    goal (EnvConfig.stop_radius), and succeeds where its true pose is within the goal radius;
    `map_resolution`: the metres between the maps' positions (`l3e policy map --resolution`). `rerun`:
    each episode run also written as a Rerun recording FILE-<policy>-<scene>-<seed>.rrd beside it."""

    episodes: int = 50
    seed: int = 0
    detector: str = "learned"
    cache_dir: str | Path | None = None
    lam: float = 50.0
    workers: int = 1
    steer_on: str = "estimate"
    fusion_settings: FusionSettings = field(default_factory=FusionSettings)
    recovery: bool | None = None
    avoid: bool | None = None
    scene_params: dict[str, dict] = field(default_factory=dict)
    stop_radius: float = EnvConfig().stop_radius
    map_resolution: float = MAP_RESOLUTION
    rerun: str | None = None

    def source(self, scene: str) -> MapSource:
        return MapSource(scene, self.detector, self.cache_dir, self.scene_params.get(scene), self.map_resolution)


@dataclass(frozen=True)
class EpisodeJob:
    """One episode to run: a policy in a scene with an environment seed, under the evaluation's options."""

    policy: str
    scene: str
    seed: int
    options: EvalOptions

    @property
    def key(self) -> tuple[str, str, int]:
        return self.policy, self.scene, self.seed


def run_episode(job: EpisodeJob) -> Episode:
    """The episode, driven through the full pipeline: the robot steers on its fused estimate (or on the
    truth), and success is judged where it stops."""
    import torch

    torch.set_num_threads(1)
    options, source = job.options, job.options.source(job.scene)
    env = NavigationEnv(
        scene=job.scene,
        scene_params=source.scene_params or {},
        arrival=options.steer_on,
        stop_radius=options.stop_radius,
        fusion={**asdict(options.fusion_settings), "enabled": True, "detector": options.detector},
    )
    try:
        ctx = source.context()
        local = FreeHeadings() if options.avoid is not False else None
        steer, planned = make_controller(job.policy, source, options.lam, env.config.odometry, ctx, local)
        controller = BackOff(steer)
        log = _episode_log(job, env, ctx, getattr(steer, "route", None)) if options.rerun else None
        path, length, info = _drive(env, controller, job, local, log)
        expected = expected_drift_along(path, ctx.built_map, drift_rates(env.config.odometry))
        offset = info["fused_T_w_b"][:3, 3] - info["T_w_b"][:3, 3]
        return Episode(
            job.policy,
            job.scene,
            job.seed,
            bool(info["terminated"]) and info["distance_to_goal"] <= env.config.goal_radius,
            avoided_corridor(path, env.scene),
            float(np.linalg.norm(offset)),
            float(info["running_ate"]),
            length,
            env.steps,
            path.round(2).tolist(),
            controller.recoveries,
            expected,
            planned,
            offset.round(4).tolist(),
        )
    finally:
        env.close()


def _episode_log(job: EpisodeJob, env: NavigationEnv, ctx: SceneContext, route: np.ndarray | None):
    """The episode's Rerun recording (experiments.rerun_log), its scene, localizability map and a route
    policy's planned route logged."""
    from l3e_env.experiments.ate_tables import file_stem
    from l3e_env.experiments.rerun_log import DriveLog

    assert job.options.rerun is not None
    base = Path(job.options.rerun)
    log = DriveLog(base.with_stem(f"{base.stem}-{file_stem(job.policy)}-{job.scene}-{job.seed}"), job.scene, ["fused"])
    log.scene(env.scene.mesh)
    built = ctx.built_map
    flagged = np.nanmean(built.probabilities >= built.thresholds, axis=(1, 2))  # share of headings and axes
    log.map(np.c_[built.positions, np.full(len(built.positions), env.robot.T_w_b[2, 3])], flagged)
    if route is not None:
        log.plan(route)
    return log


def _drive(
    env: NavigationEnv, controller: BackOff, job: EpisodeJob, local: FreeHeadings | None, log=None
) -> tuple[np.ndarray, float, dict[str, Any]]:
    """The episode's steps until it ends: the true path (every fifth step), its length and the last
    step's info (with whether the episode terminated); each step written into `log` where given."""
    _, info = env.reset(seed=job.seed)
    trail, length, terminated, truncated = [info["T_w_b"][:2, 3]], 0.0, False, False
    while not (terminated or truncated):
        previous = info["T_w_b"][:3, 3]
        pose = info["fused_T_w_b"] if job.options.steer_on == "estimate" else info["T_w_b"]
        obstacles = (
            None if local is None else FreeHeadings.obstacles(env.scan.points, env.robot.T_b_s, env.config.robot)
        )
        _, _, terminated, truncated, info = env.step(controller(pose, env.steps, obstacles))
        if job.options.recovery is not False:
            controller.observe(info["blocked"])
        length += float(np.linalg.norm(info["T_w_b"][:3, 3] - previous))
        if env.steps % 5 == 0:
            trail.append(info["T_w_b"][:2, 3])
        if log is not None:
            log.step(_step(env, info))
    if log is not None:
        log.close()
    trail.append(info["T_w_b"][:2, 3])
    return np.array(trail), length, {**info, "terminated": terminated}


def _step(env: NavigationEnv, info: dict[str, Any]):
    from l3e_env.experiments.rerun_log import StepLog

    fused = info["fused_T_w_b"]
    known = info.get("localizability_known", False)
    return StepLog(
        env.steps,
        env.steps * env.config.robot.dt,
        info["T_w_b"],
        {"fused": fused},
        env.scan.points,
        fused @ env.robot.T_b_s,
        info["localizability_probabilities"] if known else None,
        info["localizability_mask"] if known else None,
    )


def summarize(episodes: list[Episode]) -> list[dict[str, Any]]:
    rows = []
    for name in dict.fromkeys(e.policy for e in episodes):
        group = [e for e in episodes if e.policy == name]
        marked = [e.rich_route for e in group if e.rich_route is not None]
        expected = [e.expected_drift for e in group if e.expected_drift is not None]
        horizontal = [float(np.hypot(*e.final_offset[:2])) for e in group if e.final_offset is not None]
        rows.append(
            {
                "policy": name,
                "episodes": len(group),
                "success": float(np.mean([e.success for e in group])),
                "rich_route": float(np.mean(marked)) if marked else None,
                "expected_drift": float(np.mean(expected)) if expected else None,
                "final_ate": float(np.mean([e.final_ate for e in group])),
                "final_xy": float(np.mean(horizontal)) if horizontal else None,
                "mean_ate": float(np.mean([e.mean_ate for e in group])),
                "path_length": float(np.mean([e.path_length for e in group])),
                "recoveries": int(sum(e.recoveries for e in group)),
            }
        )
    return rows


def drift_correlation(episodes: list[Episode]) -> tuple[float | None, int]:
    """Pearson's r between the drift the cost model expected of each episode's path and the final
    error measured, over the episodes that have both (None with fewer than three or no spread)."""
    pairs = np.array([(e.expected_drift, e.final_ate) for e in episodes if e.expected_drift is not None])
    if len(pairs) < 3 or np.ptp(pairs[:, 0]) == 0 or np.ptp(pairs[:, 1]) == 0:
        return None, len(pairs)
    return float(np.corrcoef(pairs.T)[0, 1]), len(pairs)


def format_rows(rows: list[dict[str, Any]]) -> str:
    head = (
        f"{'policy':28s} {'episodes':>8s} {'success':>8s} {'rich route':>10s} {'expected':>9s} {'final ATE':>10s} "
        f"{'of it, xy':>9s} {'mean ATE':>9s} {'path [m]':>9s} {'backed off':>10s}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        rich = "n/a" if r["rich_route"] is None else f"{r['rich_route']:.0%}"
        expected = "n/a" if r.get("expected_drift") is None else f"{r['expected_drift']:.2f}"
        xy = "n/a" if r.get("final_xy") is None else f"{r['final_xy']:.2f}"
        lines.append(
            f"{r['policy'][:28]:28s} {r['episodes']:8d} {r['success']:8.0%} {rich:>10s} {expected:>9s} "
            f"{r['final_ate']:10.2f} {xy:>9s} {r['mean_ate']:9.2f} {r['path_length']:9.1f} {r['recoveries']:10d}"
        )
    return "\n".join(lines)


def finished_episodes(log: Path) -> dict[tuple[str, str, int], Episode]:
    """The episodes a folder's log holds, by (policy, scene, seed); a line cut by a kill is skipped."""
    done = {}
    if log.exists():
        for line in log.read_text().splitlines():
            try:
                e = Episode(**json.loads(line))
            except (json.JSONDecodeError, TypeError):
                continue
            done[(e.policy, e.scene, e.seed)] = e
    return done


def run_episodes(
    jobs: list[EpisodeJob], done: dict[tuple[str, str, int], Episode], log: Path, workers: int, progress: bool
) -> None:
    """The jobs not yet `done`, over `workers` processes, each episode appended to the log (and to
    `done`) as it finishes."""
    todo = [j for j in jobs if j.key not in done]
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="episodes", unit="ep", disable=not progress)
    with open(log, "a") as f:

        def record(e: Episode) -> None:
            done[(e.policy, e.scene, e.seed)] = e
            f.write(json.dumps(asdict(e)) + "\n")
            f.flush()
            bar.update()

        if workers > 1 and len(todo) > 1:
            with process_context([__name__]).Pool(workers, initializer=worker_start) as pool:
                for e in pool.imap_unordered(run_episode, todo):
                    record(e)
        else:
            for job in todo:
                record(run_episode(job))
    bar.close()


def _remove_unstarted(out: Path, created: bool) -> None:
    """An evaluation's settings and empty log, and its folder where the evaluation made it and it is
    empty now."""
    for name in ("settings.json", "episodes.jsonl"):
        (out / name).unlink(missing_ok=True)
    if created and not any(out.iterdir()):
        out.rmdir()


def evaluate_policies(
    out: str | Path,
    policies: list[str],
    scenes: list[str],
    options: EvalOptions | None = None,
    progress: bool = True,
    announce: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Episode i of every policy runs on scenes[i % len(scenes)] with environment seed options.seed + i.
    Writes episodes.jsonl, summary.json, summary.txt, routes.png and drift.png (the drift model's
    expectation of each path against the final error measured) into `out`; a killed evaluation resumes
    where it stopped, with the settings it started with. `announce` is told of each map built first."""
    options = options or EvalOptions()
    _check_evaluation(policies, options)
    out = Path(out)
    _build_maps(policies, scenes, options, progress, announce)
    settings_file = out / "settings.json"
    held = json.loads(settings_file.read_text()) if settings_file.exists() else None
    options = replace(
        options,
        recovery=(held or {}).get("recovery", True) if options.recovery is None else options.recovery,
        avoid=(held or {}).get("avoid", True) if options.avoid is None else options.avoid,
    )
    jobs = [
        EpisodeJob(p, scenes[i % len(scenes)], options.seed + i, options)
        for i in range(options.episodes)
        for p in policies
    ]
    run = _run_record(options)  # also in summary.json
    settings = {**run, **({"scene_params": options.scene_params} if options.scene_params else {})}
    if held is not None and held != settings:
        raise ValueError(
            f"{out} holds episodes run with other settings ({settings_changed(held, settings)}); use another folder"
        )
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    settings_file.write_text(json.dumps(settings))
    log = out / "episodes.jsonl"
    done = finished_episodes(log)
    t0 = time.perf_counter()
    try:
        run_episodes(jobs, done, log, options.workers, progress)
    except BaseException:
        if held is None and not done:  # failed before its first episode: nothing that looks like a result
            _remove_unstarted(out, created)
        raise
    results = [done[j.key] for j in jobs]
    rows = summarize(results)
    extra = {"scenes": scenes, "episodes": options.episodes, "seed": options.seed, **run}
    _write_summary(out, results, rows, {**extra, "seconds": round(time.perf_counter() - t0, 1)})
    _plot_evaluation(out, results, policies, scenes[0], options)
    return rows


def _check_evaluation(policies: list[str], options: EvalOptions) -> None:
    """Bad options and policies fail here, not in every episode, and before the maps are built (minutes)."""
    if options.steer_on not in STEER_ON:
        raise ValueError(f"steer_on must be one of {STEER_ON}, got {options.steer_on!r}")
    check_env_config(replace(EnvConfig(), stop_radius=options.stop_radius))
    odometry_fusion_config(OdometryConfig(), options.fusion_settings)
    for policy in policies:
        check_policy(policy)
    if options.rerun:
        from l3e_env.experiments.rerun_log import check_rerun

        check_rerun()


def _build_maps(
    policies: list[str],
    scenes: list[str],
    options: EvalOptions,
    progress: bool,
    announce: Callable[[str], None] | None = None,
) -> None:
    """Every map the episodes read, built here once, not in every worker: the evaluation detector's
    (expected_drift weighs every policy's episodes with it) and each PPO policy's own."""
    detectors = {_ppo_detector(p, options.detector) if p.startswith("ppo:") else options.detector for p in policies}
    for name in dict.fromkeys(scenes):
        for d in sorted(detectors | {options.detector}):
            source, build = options.source(name), MapBuild(progress=progress, announce=announce)
            scene_context(name, d, source.cache_dir, build, source.grid, progress, source.scene_params)


def _run_record(options: EvalOptions) -> dict[str, Any]:
    """What the episodes' results depend on, as settings.json and summary.json hold it."""
    return {
        "detector": options.detector,
        "lam": options.lam,
        "steer_on": options.steer_on,
        "arrival": options.steer_on,
        "stop_radius": options.stop_radius,
        "map_resolution": options.map_resolution,
        "fusion": {**options.fusion_settings.record(), "enabled": True, "detector": options.detector},
        "recovery": options.recovery,
        "avoid": options.avoid,
    }


def _write_summary(out: Path, results: list[Episode], rows: list[dict[str, Any]], run: dict[str, Any]) -> None:
    """summary.json (the rows, the drift check and the run's settings) and summary.txt."""
    r, paired = drift_correlation(results)
    check = {"pearson_r": r, "episodes": paired}
    (out / "summary.json").write_text(json.dumps({"rows": rows, "drift_check": check, **run}, indent=2))
    words = (
        "n/a (fewer than three episodes or no spread)" if r is None else f"Pearson r = {r:.2f} over {paired} episodes"
    )
    (out / "summary.txt").write_text(format_rows(rows) + f"\nexpected drift against final ATE: {words}\n")


def _plot_evaluation(out: Path, results: list[Episode], policies: list[str], first: str, options: EvalOptions) -> None:
    """drift.png (each path's expected drift against its final error) and routes.png (the routes taken
    on the first scene)."""
    from .plots import plot_drift_check, plot_paths

    r, _ = drift_correlation(results)
    plot_drift_check(
        out / "drift.png",
        {
            p: (
                np.array([e.expected_drift for e in results if e.policy == p and e.expected_drift is not None]),
                np.array([e.final_ate for e in results if e.policy == p and e.expected_drift is not None]),
            )
            for p in policies
        },
        r,
    )
    ctx = scene_context(first, None, options.cache_dir, scene_params=options.scene_params.get(first))
    plot_paths(
        out / "routes.png",
        ctx.scene,
        {p: [np.array(e.trajectory) for e in results if e.policy == p and e.scene == first] for p in policies},
        ctx.space,
        title=f"{first}: routes taken (episodes on this variant)",
    )


def _ppo_detector(policy: str, default: str) -> str:
    from .ppo import recorded_detector

    folder = Path(policy.partition(":")[2])
    return recorded_detector(folder if folder.is_dir() else folder.parent, default)
