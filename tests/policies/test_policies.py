"""Navigation: free space, localizability maps and their cache, the planner, the fast PPO
environment, PPO checkpoints and full-pipeline episodes, on a small fork."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from l3e_env.config import EnvConfig, FusionSettings, plain, to_dict
from l3e_env.localizability.registration import RegistrationConfig
from policies.context import SceneContext, free_space
from policies.fastenv import FastEnvConfig, MapNavigationEnv
from policies.freespace import FreeSpace, FreeSpaceError, build_free_space, reachable_from
from policies.locmap import LocalizabilityMap, MapBuild, MapCacheError, MapGrid, build_map, get_map
from policies.observation import PolicyView
from policies.planner import Planner, PlanningError, drift_rates
from scenes import make_scene
from scenes.fork import make_fork
from scenes.geometry import box, ground_plane, merge
from scenes.scene import Scene


@pytest.fixture(scope="module")
def small_fork(tmp_path_factory, run_wide):
    """A small fork, its free space (built once a run, by whichever worker comes first) and a map cache
    of this module's own that holds the free space too (its tests build and read maps in it)."""
    from filelock import FileLock

    scene = make_fork(0, corridor_length=10.0, detour=8.0)
    with FileLock(run_wide / "small-fork.lock"):
        space = free_space(scene, run_wide)
    cache = tmp_path_factory.mktemp("maps")
    for built in run_wide.glob(f"{scene.name}-free-*.npz"):
        shutil.copy(built, cache)
    return scene, space, cache


def synthetic_map(space: FreeSpace, masked_region, yaw_bins: int = 4) -> LocalizabilityMap:
    """A map on every free cell: x masked (probability 0.9) inside `masked_region(xy)`, else 0.1."""
    positions = space.free_centers()
    p = np.full((len(positions), yaw_bins, 6), 0.1)
    p[masked_region(positions), :, 0] = 0.9
    return LocalizabilityMap("synthetic", positions, np.arange(yaw_bins) * 2 * np.pi / yaw_bins, p, np.full(6, 0.5))


def test_free_space_matches_the_robot(small_fork):
    scene, space, _ = small_fork
    # the corridor (walls at |y| = 1.5..1.7) is free in the middle and blocked at its walls
    assert space.is_free(np.array([[10.0, 0.0], [10.0, 8.0], [0.0, 0.0]])).all()
    assert not space.is_free(np.array([[10.0, 1.6], [10.0, -1.6]])).any()
    # the ground outside the boundary walls is not reachable from the start
    assert not space.is_free(np.array([10.0, -12.0]))
    clearance = lambda xy: space.clearance[tuple(space.index(np.array(xy)))]  # noqa: E731
    assert clearance([10.0, 0.0]) < clearance([-5.0, 3.0])
    with pytest.raises(FreeSpaceError, match="not in the free space"):
        reachable_from(space, np.array([10.0, 1.6]))


def test_scene_without_free_space_is_refused():
    low = merge([ground_plane(-5, 5, -5, 5), box((0, 0, 0.6), (10, 10, 0.1))])  # a roof through the base
    route = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    scene = Scene("low", low, [route], (0, 0, 0), (1, 0), {"main": route})
    with pytest.raises(FreeSpaceError, match="no cell where the robot can stand"):
        build_free_space(scene, resolution=1.0)


def test_drift_rates_follow_the_odometry_model():
    from l3e_env.config import OdometryConfig

    base = drift_rates()
    assert base.shape == (6,) and (base > 0).all()
    assert base[0] > base[1]  # the stride-scale error drifts along the walking direction only
    worse = drift_rates(OdometryConfig(scale_error_std=0.05))
    assert worse[0] > base[0] and np.allclose(worse[1:], base[1:])


def test_planner_avoids_masked_corridor_and_refuses_bad_goals(small_fork):
    scene, space, _ = small_fork
    corridor = lambda xy: (np.abs(xy[:, 1]) < 1.5) & (xy[:, 0] > 4) & (xy[:, 0] < 16)  # noqa: E731
    locmap = synthetic_map(space, corridor)
    start, goal = scene.start[:2], scene.goal
    short = Planner(space, locmap, lam=0.0).plan(start, goal)
    aware = Planner(space, locmap, lam=100.0).plan(start, goal)
    assert np.abs(short.path[:, 1]).max() < 1.0  # straight through the corridor
    assert np.abs(aware.path[:, 1]).max() > 2.0  # outside the corridor walls (|y| = 1.5 to 1.7)
    assert aware.length > short.length and aware.expected_drift < short.expected_drift
    # drift counted only while masked: the straight path's drift is about the corridor length times k_x
    assert short.expected_drift == pytest.approx(12 * (drift_rates()[0] * 0.9 / 0.9), rel=0.3)
    with pytest.raises(PlanningError, match="inside an obstacle"):
        Planner(space, locmap).plan(start, np.array([10.0, 1.6]))
    with pytest.raises(PlanningError, match="outside the scene's grid"):
        Planner(space, locmap).plan(start, np.array([500.0, 0.0]))
    walled = FreeSpace(space.origin, space.resolution, space.free.copy(), space.ground, space.clearance)
    walled.free[space.index(np.array([18.0, 0.0]))[0], :] = False  # a wall across the whole scene
    walled.free[tuple(space.index(goal))] = True
    with pytest.raises(PlanningError, match="cannot be reached"):
        Planner(walled, None, lam=0.0).plan(start, goal)
    with pytest.raises(ValueError, match="needs a localizability map"):
        Planner(space, None, lam=10.0)


def test_the_drift_model_along_a_walked_path_is_the_planners_and_is_checked_against_the_error(small_fork):
    from policies.evaluation import Episode, drift_correlation
    from policies.planner import expected_drift_along

    scene, space, _ = small_fork
    corridor = lambda xy: (np.abs(xy[:, 1]) < 1.5) & (xy[:, 0] > 4) & (xy[:, 0] < 16)  # noqa: E731
    locmap = synthetic_map(space, corridor)
    rates = drift_rates()
    for lam in (0.0, 100.0):  # the same sum along the plan's own path, in and out of the corridor
        plan = Planner(space, locmap, lam=lam).plan(scene.start[:2], scene.goal)
        assert expected_drift_along(plan.path, locmap, rates) == pytest.approx(plan.expected_drift, rel=0.05, abs=1e-6)
    assert expected_drift_along(np.zeros((5, 2)), locmap, rates) == 0.0  # standing still drifts nothing

    def episode(expected: float, final: float) -> Episode:
        return Episode("p", "s", 0, True, None, final, final, 1.0, 1, [], expected_drift=expected)

    r, n = drift_correlation([episode(e, 2 * e + 0.1) for e in (0.5, 1.0, 2.0, 3.0)] + [episode(None, 9.0)])
    assert r == pytest.approx(1.0) and n == 4  # an episode without a map's expectation is left out
    assert drift_correlation([episode(1.0, 1.0), episode(2.0, 0.5)]) == (None, 2)  # too few to say


def test_planner_takes_one_cell_squeezes_only_without_a_wider_way():
    from scipy import ndimage

    # an open 20 x 9 grid with a wall at ix = 10; a one-cell gap in it at iy = 1, a three-cell gap at iy = 6
    free = np.ones((21, 9), dtype=bool)
    free[10, :] = False
    free[10, 1] = True
    free[10, 5:8] = True
    space = FreeSpace(np.zeros(2), 0.5, free, np.zeros(free.shape), ndimage.distance_transform_edt(free) * 0.5)
    start, goal = np.array([4.0, 0.5]), np.array([6.0, 0.5])
    through = lambda plan: space.index(plan.path)[space.index(plan.path)[:, 0] == 10, 1]  # noqa: E731
    assert (through(Planner(space, None, lam=0.0, tight_weight=0.0).plan(start, goal)) == 1).all()
    wide = Planner(space, None, lam=0.0).plan(start, goal)
    assert (through(wide) == 6).all()  # the middle of the wide gap, 2.5 m longer
    free[10, 5:8] = False  # only the squeeze is left: still a plan
    narrow = FreeSpace(space.origin, 0.5, free, space.ground, ndimage.distance_transform_edt(free) * 0.5)
    assert (through(Planner(narrow, None, lam=0.0).plan(start, goal)) == 1).all()


def test_map_lookup_interpolates_headings_and_round_trips(tmp_path, small_fork):
    _, space, _ = small_fork
    locmap = synthetic_map(space, lambda xy: xy[:, 0] > 1e9)
    locmap.probabilities[:, 1, 1] = 0.9  # y masked at heading 90 degrees only
    at = locmap.lookup(np.array([[10.0, 0.0]] * 3), np.array([np.pi / 4, np.pi / 2, np.pi]))
    assert at[:, 1] == pytest.approx([0.5, 1.0, 0.0])
    path = tmp_path / "m.npz"
    locmap.save(path)
    again = LocalizabilityMap.load(path)
    assert np.array_equal(again.probabilities, locmap.probabilities) and again.scene == "synthetic"
    assert again.estimated is None  # a map without the record reads back without it
    locmap.estimated = np.zeros(locmap.probabilities.shape[:2], dtype=bool)
    locmap.estimated[::3, 1] = True
    locmap.save(path)
    assert np.array_equal(LocalizabilityMap.load(path).estimated, locmap.estimated)
    path.write_bytes(b"not a map")
    with pytest.raises(MapCacheError, match="not a readable localizability map"):
        LocalizabilityMap.load(path)


@pytest.mark.slow
def test_eigen_map_is_cached_and_a_missing_cache_is_named(small_fork):
    scene, space, cache = small_fork
    with pytest.raises(MapCacheError, match="l3e policy map"):
        get_map(scene, space, "eigen:30", cache, build=False, grid=MapGrid(resolution=4.0))
    said: list[str] = []
    built = get_map(scene, space, "eigen:30", cache, MapBuild(announce=said.append), MapGrid(resolution=4.0))
    assert len(said) == 2 and said[0].startswith(f"building the eigen:30 localizability map of {scene.name} (")
    assert f"cached in {cache}" in said[0] and said[1].startswith("built in ") and said[1].endswith(".npz")
    cached = get_map(scene, space, "eigen:30", cache, build=False, grid=MapGrid(resolution=4.0))
    assert len(said) == 2  # a cached map is read, not announced
    assert np.array_equal(built.probabilities, cached.probabilities, equal_nan=True)
    assert cached.estimated.shape == built.probabilities.shape[:2] and not cached.estimated.any()
    # other ICP settings make another file
    assert cached.meta["registration"] == json.loads(json.dumps(plain(to_dict(RegistrationConfig()))))
    inside = (np.abs(built.positions[:, 1]) < 1.0) & (built.positions[:, 0] > 6) & (built.positions[:, 0] < 14)
    assert inside.any()
    # in the smooth corridor, heading along it (yaw bin 0), x is degenerate; among the pillars it is not
    assert built.masked[inside, 0, 0].mean() == 1.0
    rich = np.abs(built.positions[:, 1] - 8.0) < 0.1
    assert built.masked[rich, 0, 0].mean() < 0.5
    with pytest.raises(ValueError, match="map detector"):
        get_map(scene, space, "none", cache, grid=MapGrid(resolution=4.0))


@pytest.mark.slow
def test_a_map_built_by_two_workers_is_the_same(small_fork):
    scene, space, _ = small_fork
    alone = build_map(scene, space, "eigen:30", MapGrid(resolution=8.0), batch=4)
    shared = build_map(scene, space, "eigen:30", MapGrid(resolution=8.0), batch=4, workers=2)
    assert np.isfinite(alone.probabilities).any() and alone.probabilities[..., 0].size > 3 * 4  # batches for both
    assert np.array_equal(alone.probabilities, shared.probabilities, equal_nan=True)
    with pytest.raises(ValueError, match="workers must be at least 1"):
        build_map(scene, space, "eigen:30", MapGrid(resolution=4.0), workers=0)


@pytest.mark.parametrize("spec", ["dcreg:10", "xicp:100", "drpm:10"])
@pytest.mark.slow
def test_the_classical_tests_make_maps_that_flag_the_smooth_corridor(small_fork, spec):
    scene, space, _ = small_fork
    built = build_map(scene, space, spec, MapGrid(resolution=4.0, yaw_bins=2), batch=4)  # along and against x
    assert built.meta["detector"] == spec.replace(":", "")  # no scan-estimate settings in a classical test's name
    assert set(np.unique(built.probabilities[np.isfinite(built.probabilities)])) <= {0.0, 1.0}
    inside = np.abs(built.positions[:, 1]) < 0.1  # the smooth corridor: heading along it, x slides
    assert inside.any() and built.probabilities[inside, 0, 0].mean() > 0.5


def test_learned_map_gives_probabilities(small_fork):
    scene, space, cache = small_fork
    locmap = get_map(scene, space, "learned", cache, grid=MapGrid(resolution=8.0))
    assert locmap.probabilities.shape == (len(locmap.positions), 4, 6)
    assert np.isfinite(locmap.probabilities).all()
    assert ((locmap.probabilities >= 0) & (locmap.probabilities <= 1)).all()
    assert locmap.meta["detector"].startswith("learned-")


@pytest.fixture()
def fast_env(small_fork):
    scene, space, _ = small_fork
    locmap = synthetic_map(space, lambda xy: (np.abs(xy[:, 1]) < 1.5) & (xy[:, 0] > 4) & (xy[:, 0] < 16))
    return MapNavigationEnv([SceneContext(scene, space, locmap)])


def test_a_policy_walks_facing_its_way_unless_it_may_walk_sideways(fast_env):
    """Without `sideways` the action is (vx, yaw rate): the same walk as the twist without vy; an
    action of the other layout's size is refused by name."""
    facing = MapNavigationEnv(fast_env.contexts, FastEnvConfig(sideways=False))
    assert facing.action_space.shape == (2,) and fast_env.action_space.shape == (3,)
    poses = []
    for env, action in ((facing, [0.7, 0.4]), (fast_env, [0.7, 0.0, 0.4])):
        env.reset(seed=0)
        for _ in range(5):
            *_, info = env.step(np.array(action))
        poses.append(info["pose"])
    np.testing.assert_allclose(poses[0], poses[1])
    with pytest.raises(ValueError, match=r"2 finite numbers \(vx, yaw_rate\)"):
        facing.step(np.array([1.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match=r"3 finite numbers \(vx, vy, yaw_rate\)"):
        fast_env.step(np.array([1.0, 0.0]))


def test_fast_env_rewards_progress_and_penalises_drift(fast_env):
    obs, info = fast_env.reset(seed=0)
    assert fast_env.observation_space.contains(obs)
    with pytest.raises(ValueError, match="finite"):
        fast_env.step(np.array([np.nan, 0, 0]))
    total, drift_steps = 0.0, 0
    for _ in range(200):
        obs, reward, terminated, truncated, info = fast_env.step(np.array([1.0, 0.0, 0.0]))
        assert fast_env.observation_space.contains(obs)
        total += reward
        drift_steps += 0.5 * (info["expected_drift"] > 0)
        if terminated or truncated:
            break
    assert terminated and not truncated  # straight ahead reaches the goal
    assert info["tight_length"] == 0.0  # the corridor's middle is 1.5 m from its walls
    straight = np.hypot(*(fast_env.view.goal - fast_env.contexts[0].scene.start[:2]))
    short = straight - fast_env.config.goal_radius  # it stops at the first 0.5 m decision within the goal radius
    assert short - 1e-6 <= info["path_length"] < short + 0.5
    assert info["expected_drift"] == pytest.approx(12 * drift_rates()[0], rel=0.15)
    # the reward is progress minus lam times that drift (plus the goal, minus step penalties)
    cfg = fast_env.config
    expected = (
        info["path_length"] - cfg.lam * info["expected_drift"] + cfg.goal_reward - cfg.step_penalty * fast_env.decisions
    )
    assert total == pytest.approx(expected, abs=1.0)


def test_fast_env_charges_turning_as_drift(fast_env):
    """Swinging the heading where nothing is masked still costs drift (ICP's per-turn heading error)."""
    fast_env.reset(seed=0)
    cfg = fast_env.config
    _, reward, _, _, info = fast_env.step(np.array([0.0, 0.0, 1.0]))  # turn in place at the full yaw rate
    turned = cfg.robot.max_twist[2] * cfg.robot.dt * cfg.action_repeat
    assert info["path_length"] == 0.0 and info["expected_drift"] == pytest.approx(cfg.turn_drift * turned)
    assert reward == pytest.approx(-cfg.lam * cfg.turn_drift * turned - cfg.step_penalty)
    fast_env.config = dataclasses.replace(cfg, turn_drift=0.0)
    _, reward, _, _, _ = fast_env.step(np.array([0.0, 0.0, -1.0]))
    assert reward == pytest.approx(-cfg.step_penalty)


def test_fast_env_charges_walking_sideways_as_drift(fast_env):
    """The same sideways step costs lateral_drift per metre more than with the term off (ICP's
    heading under a fast diagonal gait); a step forward costs nothing extra."""
    drifts = {}
    for lateral in (0.0, 0.015):
        fast_env.config = dataclasses.replace(fast_env.config, lateral_drift=lateral)
        for action in ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0)):
            fast_env.reset(seed=0)
            _, _, _, _, info = fast_env.step(np.array(action))
            assert not info["blocked"]
            drifts[lateral, action[1]] = info["expected_drift"]
    cfg = fast_env.config
    sideways = cfg.robot.max_twist[1] * cfg.robot.dt * cfg.action_repeat
    assert drifts[0.015, 1.0] - drifts[0.0, 1.0] == pytest.approx(0.015 * sideways)
    assert drifts[0.015, 0.0] == drifts[0.0, 0.0]


def test_policy_train_takes_the_sideways_cost_and_a_resumed_run_keeps_it(tmp_path, monkeypatch, capsys):
    """And its drift weight: a second stage run without the options trains as the first did."""
    from l3e_env.cli.main import main

    given = []

    def fake_train(out, contexts, detector, training, config, progress):
        given.append((config.lateral_drift, config.lam, config.sideways))
        (Path(out) / "policy.json").parent.mkdir(parents=True, exist_ok=True)
        (Path(out) / "policy.json").write_text(json.dumps({"fast_env": plain(dataclasses.asdict(config))}))
        return {"timesteps": training.timesteps}

    monkeypatch.setattr("policies.ppo.train_ppo", fake_train)
    monkeypatch.setattr("policies.context.scene_context", lambda *args, **kwargs: None)
    run = ["policy", "train", "--scene", "fork-0", "--quiet", "--out"]
    assert main([*run, str(tmp_path / "a"), "--lateral-drift", "0.015", "--lam", "20"]) == 0
    assert main([*run, str(tmp_path / "a")]) == 0  # the second stage, resumed
    assert main([*run, str(tmp_path / "a"), "--lam", "30"]) == 0  # a given option wins
    assert main([*run, str(tmp_path / "b"), "--lateral-drift", "0", "--no-sideways"]) == 0
    assert main([*run, str(tmp_path / "b")]) == 0  # resumed: still without the cost
    assert main([*run, str(tmp_path / "c")]) == 0  # a new run: the defaults
    assert given == [
        (0.015, 20.0, True),
        (0.015, 20.0, True),
        (0.015, 30.0, True),
        (0.0, 50.0, False),
        (0.0, 50.0, False),
        (0.015, 50.0, True),
    ]
    for option in ("--lateral-drift", "--lam"):
        for bad in ("-0.1", "nan", "much"):
            with pytest.raises(SystemExit):
                main([*run, str(tmp_path / "d"), option, bad])
            assert "expected a finite number, 0 or more" in capsys.readouterr().err


def test_fast_env_blocks_at_walls(fast_env):
    fast_env.reset(seed=0)
    blocked = False
    for _ in range(40):  # sideways to the right, 10 m: into the boundary wall
        _, _, _, _, info = fast_env.step(np.array([0.0, -1.0, 0.0]))
        blocked |= info["blocked"]
    assert blocked  # the boundary wall at y = -8 stops it
    assert fast_env.view.space.is_free(np.array(info["pose"][:2]))
    # walking on along the wall brushes past it: penalised per metre, beyond the step penalty
    cfg, before = fast_env.config, info
    _, reward, _, _, info = fast_env.step(np.array([1.0, 0.0, 0.0]))
    walked = info["tight_length"] - before["tight_length"]
    assert walked == pytest.approx(0.5, abs=0.01) and not info["blocked"]
    gained = before["distance_to_go"] - info["distance_to_go"]
    assert reward == pytest.approx(gained - cfg.tight_penalty * walked - cfg.step_penalty)


def test_policy_view_sees_the_corridor_ahead(small_fork):
    scene, space, _ = small_fork
    locmap = synthetic_map(space, lambda xy: (np.abs(xy[:, 1]) < 1.5) & (xy[:, 0] > 4) & (xy[:, 0] < 16))
    view = PolicyView(space, locmap, scene.goal)
    before = view(3.0, 0.0, 0.0)  # facing the corridor's mouth
    drift = before[PolicyView.drift_ahead]
    assert drift[0] > 0.3 and drift[4] == pytest.approx(0.0, abs=0.05)  # into the corridor; left is open ground
    inside = view(8.0, 0.0, 0.0)[PolicyView.ranges]
    assert inside[0] > 0.9 and inside[4] < 0.2  # free ahead along the corridor; its wall 1.5 m to the left
    assert view.distance_to_go(scene.start[:2]) == pytest.approx(np.linalg.norm(scene.goal - scene.start[:2]), rel=0.05)
    # the shortest way runs straight into the corridor; the localizability-aware way turns off before it,
    # and with lam = 0 both are the same
    assert before[3] == pytest.approx(1.0) and abs(before[PolicyView.aware][1]) > 0.5
    blind = PolicyView(space, locmap, scene.goal, lam=0.0)(3.0, 0.0, 0.0)
    np.testing.assert_allclose(blind[PolicyView.aware], blind[3:5], atol=1e-6)


@pytest.mark.slow
def test_ppo_trains_resumes_and_refuses_other_observations(tmp_path, small_fork):
    pytest.importorskip("stable_baselines3")
    from policies.ppo import OBSERVATION, PolicyCheckpointError, PPOPolicy, PPOTraining, recorded_detector, train_ppo

    scene, space, cache = small_fork
    contexts = [SceneContext(scene, space, get_map(scene, space, "eigen:30", cache, grid=MapGrid(resolution=4.0)))]
    out = tmp_path / "ppo"
    first = train_ppo(out, contexts, "eigen:30", PPOTraining(512, n_envs=2), FastEnvConfig(), progress=False)
    assert first["timesteps"] >= 512 and (out / "last.pt").exists() and not list(out.glob("*.zip"))
    resumed = train_ppo(out, contexts, "eigen:30", PPOTraining(1024, n_envs=2), progress=False)
    assert resumed["timesteps"] >= 1024
    assert (out / "progress.csv").exists() and (out / "monitor.csv").exists()
    assert list(out.glob("events.out.tfevents.*")), "the TensorBoard log beside the CSV one"
    assert (out / "resume-1.monitor.csv").exists()  # the resumed run keeps its own episode log
    policy = PPOPolicy(out)
    action = policy(np.zeros(PolicyView.size, dtype=np.float32))
    assert action.shape == (3,) and np.all(np.abs(action) <= 1)
    meta = json.loads((out / "policy.json").read_text())
    assert [h["from_timestep"] for h in meta["history"]] == [0, first["timesteps"]]  # both stages recorded
    assert meta["action"] == ["vx", "vy", "yaw_rate"]
    meta["action"] = ["vx", "vy", "yaw_rate", "pitch_rate"]
    (out / "policy.json").write_text(json.dumps(meta))
    with pytest.raises(PolicyCheckpointError, match="trained with actions"):
        PPOPolicy(out)
    meta["observation"]["size"] = 99
    (out / "policy.json").write_text(json.dumps(meta))
    with pytest.raises(PolicyCheckpointError, match="observation"):
        PPOPolicy(out)
    with pytest.raises(PolicyCheckpointError, match="no policy.pt"):
        PPOPolicy(tmp_path / "nowhere")
    # policy.json's structure and the weights' values, each named with the file
    good = json.loads(json.dumps(meta))
    good["action"], good["observation"] = ["vx", "vy", "yaw_rate"], json.loads(json.dumps(OBSERVATION))
    without = {k: v for k, v in good.items() if k != "fast_env"}
    for broken, words in (
        ([good], "holds a list, not the mapping"),
        (without, "fast_env.action_repeat must be a whole number of 1 or more, got None"),
        ({**good, "fast_env": {**good["fast_env"], "action_repeat": 0}}, "fast_env.action_repeat must be .* got 0"),
        ({**good, "net_arch": "wide"}, "net_arch must be a list of layer widths"),
        ({**good, "detector": 5}, "detector 5 is no detector this version runs"),
        ({**good, "detector": "bogus"}, "detector 'bogus' is no detector this version runs"),
    ):
        (out / "policy.json").write_text(json.dumps(broken))
        with pytest.raises(PolicyCheckpointError, match=f"policy.json: {words}"):
            PPOPolicy(out)
        if "detector" in broken:  # the evaluation reads the policy's detector through the same check
            with pytest.raises(PolicyCheckpointError, match=f"policy.json: {words}"):
                recorded_detector(out, "learned")
    (out / "policy.json").write_text(json.dumps(good))
    import torch

    weights = torch.load(out / "policy.pt", weights_only=True)
    first_key = next(iter(weights))
    weights[first_key] = torch.full_like(weights[first_key], float("nan"))
    torch.save(weights, out / "policy.pt")
    with pytest.raises(PolicyCheckpointError, match=f"policy.pt: non-finite weights in {first_key}"):
        PPOPolicy(out)


@pytest.mark.slow
def test_teacher_walks_the_aware_direction_and_ppo_starts_from_its_clone(tmp_path, small_fork):
    pytest.importorskip("stable_baselines3")
    from policies.ppo import PPOPolicy, PPOTraining, WarmStart, demonstrations, teacher_action, train_ppo

    obs = np.zeros((3, PolicyView.size), dtype=np.float32)
    obs[:, PolicyView.aware] = [[1.0, 0.0], [0.0, 1.0], [np.cos(-0.3), np.sin(-0.3)]]
    np.testing.assert_allclose(teacher_action(obs), [[1, 0, 0], [0, 0, 1], [np.cos(0.3), 0, -0.45]], atol=1e-6)
    np.testing.assert_allclose(teacher_action(obs, sideways=False), [[1, 0], [0, 1], [np.cos(0.3), -0.45]], atol=1e-6)
    scene, space, cache = small_fork
    contexts = [SceneContext(scene, space, get_map(scene, space, "eigen:30", cache, grid=MapGrid(resolution=4.0)))]
    warm = WarmStart(episodes=2, epochs=300)  # a few samples: more passes
    walking = FastEnvConfig(sideways=False)  # (vx, yaw rate)
    observations, actions, returns = demonstrations(contexts, walking, warm)
    assert len(observations) == len(actions) == len(returns) > 20 and np.isfinite(returns).all()
    np.testing.assert_allclose(actions, teacher_action(observations, sideways=False))  # the teacher's own twist
    gaps = {}
    for name, start in (("warm", warm), ("cold", None)):
        # no PPO step after it: the network as cloned (or as drawn)
        train_ppo(tmp_path / name, contexts, "eigen:30", PPOTraining(0, n_envs=1, warm=start), walking, progress=False)
        policy = PPOPolicy(tmp_path / name)
        twists = np.array([policy(o) for o in observations[:200]])
        assert not twists[:, 1].any()  # (vx, yaw rate): it never walks sideways
        gaps[name] = float(np.abs(twists[:, [0, 2]] - actions[:200]).mean())
    assert gaps["warm"] < 0.05 and gaps["cold"] > 0.2, gaps
    record = json.loads((tmp_path / "warm" / "policy.json").read_text())["warm_start"]
    assert record["samples"] == len(observations) and record["action_mse"] < 0.005
    assert json.loads((tmp_path / "cold" / "policy.json").read_text())["warm_start"] is None


class _Payload:
    """Unpickled, it writes a marker file: what a crafted policy file would do."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "ran"))


def test_a_crafted_policy_folder_runs_no_code_when_loaded_or_resumed(tmp_path, small_fork, capsys):
    """policy.zip (what stable-baselines3's loader would unpickle) is never read; policy.pt and last.pt go
    through torch's weights-only loader, which refuses a pickled object instead of running it."""
    pytest.importorskip("stable_baselines3")
    import base64
    import pickle
    import zipfile

    from l3e_env.cli.main import main
    from policies.ppo import OBSERVATION, PolicyCheckpointError, PPOPolicy, PPOTraining, train_ppo

    marker = tmp_path / "marker"
    folder = tmp_path / "shared-policy"
    folder.mkdir()
    meta = {
        "observation": OBSERVATION,
        "action": ["vx", "yaw_rate"],
        "net_arch": [64, 64],
        "fast_env": {"action_repeat": 1},
    }
    (folder / "policy.json").write_text(json.dumps(meta))
    payload = base64.b64encode(pickle.dumps(_Payload(marker))).decode()
    with zipfile.ZipFile(folder / "policy.zip", "w") as z:  # SB3's layout: cloudpickled entries in `data`
        z.writestr("data", json.dumps({"policy_class": {":type:": "<class>", ":serialized:": payload}}))
    with pytest.raises(PolicyCheckpointError, match="policy.zip is not read"):
        PPOPolicy(folder)
    assert (
        main(
            [
                "policy",
                "evaluate",
                "--policy",
                f"ppo:{folder}",
                "--scene",
                "fork-0",
                "--episodes",
                "1",
                "--out",
                str(tmp_path / "ev"),
                "--quiet",
            ]
        )
        == 2
    )
    (folder / "policy.pt").write_bytes(pickle.dumps(_Payload(marker), protocol=2))
    with pytest.raises(PolicyCheckpointError, match="cannot be read as policy weights"):
        PPOPolicy(folder)
    scene, space, cache = small_fork
    contexts = [SceneContext(scene, space, get_map(scene, space, "eigen:30", cache, grid=MapGrid(resolution=4.0)))]
    (folder / "last.pt").write_bytes(pickle.dumps(_Payload(marker), protocol=2))
    with pytest.raises(PolicyCheckpointError, match="cannot be read as policy weights"):
        train_ppo(folder, contexts, "eigen:30", PPOTraining(256, n_envs=1), FastEnvConfig(), progress=False)
    assert not marker.exists()


@pytest.mark.slow
def test_full_pipeline_evaluation_on_the_small_fork(small_fork, monkeypatch, tmp_path, rerun_table):
    from policies import evaluation
    from policies.evaluation import EvalOptions, MapSource

    scene, space, cache = small_fork
    monkeypatch.setattr("policies.context.make_scene", lambda name: scene)
    monkeypatch.setattr("l3e_env.envs.navigation.make_scene", lambda name, **kw: scene)
    # the legs' biases not estimated, scan to scan: there the corridor's masked axis costs the legs' drift
    plain = FusionSettings()
    rrd = str(tmp_path / "episode.rrd")
    # the map of the other tests, positions 4 m apart (shared where they ran first in this process)
    options = EvalOptions(
        episodes=1,
        detector="eigen:30",
        cache_dir=cache,
        lam=200.0,
        fusion_settings=plain,
        map_resolution=4.0,
        rerun=rrd,
    )
    rows = evaluation.evaluate_policies(tmp_path, ["shortest", "planner"], ["fork-0"], options, progress=False)
    table = rerun_table(tmp_path / "episode-planner-fork-0-0.rrd", "step")  # each episode as a Rerun recording
    entities = {c.split(":")[0] for c in table.column_names}
    assert {"/world/map", "/world/plan", "/world/truth", "/world/estimate/fused", "/world/scan"} <= entities
    assert "/flags/x/flagged" in entities
    shortest, planner = (
        evaluation.Episode(**json.loads(line)) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()
    )
    # through the degenerate corridor the shortest path drifts more: the planner arrives, nearer the truth
    assert planner.success and planner.final_ate < shortest.final_ate
    assert not shortest.rich_route and planner.rich_route
    assert planner.path_length > shortest.path_length
    assert shortest.final_ate > 0 and np.isfinite(planner.mean_ate)
    for episode, row in zip((shortest, planner), rows):  # the end's error, and its part across the ground
        assert episode.final_offset is not None
        assert np.linalg.norm(episode.final_offset) == pytest.approx(episode.final_ate, abs=1e-3)
        assert row["final_xy"] == pytest.approx(np.hypot(*episode.final_offset[:2]), abs=1e-3)
    assert [r["policy"] for r in rows] == ["shortest", "planner"] and rows[1]["rich_route"] == 1.0
    assert (tmp_path / "routes.png").stat().st_size > 10_000 and "rich route" in (tmp_path / "summary.txt").read_text()
    settings = json.loads((tmp_path / "settings.json").read_text())
    assert settings["recovery"] is True and settings["avoid"] is True and settings["lam"] == 200.0
    assert settings["stop_radius"] == EnvConfig().stop_radius  # the environment's own
    assert settings["map_resolution"] == 4.0
    get_map(scene, space, "eigen:30", cache, build=False, grid=MapGrid(resolution=4.0))  # the map it read, cached
    # a second run (or one after a kill) reuses the finished episodes
    monkeypatch.setattr(evaluation, "run_episode", lambda job: pytest.fail(f"episode {job.key} ran again"))
    again = evaluation.evaluate_policies(tmp_path, ["shortest", "planner"], ["fork-0"], options, progress=False)
    assert again == rows
    with pytest.raises(ValueError, match="holds episodes run with"):
        evaluation.evaluate_policies(
            tmp_path, ["shortest"], ["fork-0"], dataclasses.replace(options, steer_on="truth"), progress=False
        )
    with pytest.raises(ValueError, match="odometry_bias takes distinct axes"):
        bad = dataclasses.replace(options, fusion_settings=FusionSettings(odometry_bias=("roll",)))
        evaluation.evaluate_policies(tmp_path / "bad", ["shortest"], ["fork-0"], bad)
    assert not (tmp_path / "bad").exists()
    for radius in (0.0, 1.5):
        with pytest.raises(ValueError, match="stop_radius must be above 0 and at most the goal radius"):
            evaluation.evaluate_policies(tmp_path / "bad", ["shortest"], ["fork-0"], EvalOptions(stop_radius=radius))
    assert not (tmp_path / "bad").exists()
    # a run whose first episode fails leaves nothing that looks like a result
    monkeypatch.setattr(evaluation, "run_episodes", lambda *a: (_ for _ in ()).throw(RuntimeError("episode 0 died")))
    with pytest.raises(RuntimeError, match="episode 0 died"):
        evaluation.evaluate_policies(tmp_path / "dies", ["shortest"], ["fork-0"], options, progress=False)
    assert not (tmp_path / "dies").exists()
    with pytest.raises(ValueError, match="unknown policy"):
        evaluation.make_controller("wander", MapSource("fork-0", "eigen:30", cache), 50.0)
    # a wrong policy is named before any map is built or any folder written
    monkeypatch.setattr(evaluation, "scene_context", lambda *a, **k: pytest.fail("a map was looked up first"))
    for policy, message in (("wander", "unknown policy"), (f"ppo:{tmp_path / 'none'}", "none: no policy.pt")):
        with pytest.raises((ValueError, RuntimeError), match=message):
            evaluation.evaluate_policies(tmp_path / "bad", ["shortest", policy], ["fork-0"], options)
    assert not (tmp_path / "bad").exists()


def test_back_off_reverses_the_last_command_after_blocked_steps():
    from policies.evaluation import BackOff

    commands = iter(np.array([[1.0, 0.5, 0.2], [0.3, 0.0, 0.0], [0.0, 1.0, 0.0]] * 20, dtype=np.float32))
    back_off = BackOff(lambda T, i, obstacles: next(commands), after=3, steps=2)
    actions = []
    for blocked in [True, True, False, True, True, True, True, True, False, False]:
        actions.append(back_off(np.eye(4), len(actions)))
        back_off.observe(blocked)
    actions = np.array(actions)
    # three blocked steps in a row (the 4th to 6th) start it: the 6th command reversed, twice; a
    # block while backing off does not count; then the controller again
    np.testing.assert_allclose(actions[6], -actions[5])
    np.testing.assert_allclose(actions[7], -actions[5])
    np.testing.assert_allclose(actions[8], [1.0, 0.5, 0.2], rtol=1e-6)  # the next command
    assert back_off.recoveries == 1
    with pytest.raises(ValueError, match="at least 1"):
        BackOff(lambda T, i, obstacles: np.zeros(3), after=0)


def test_policy_commands_are_registered(capsys):
    from l3e_env.cli.main import main

    with pytest.raises(SystemExit):
        main(["policy", "--help"])
    text = capsys.readouterr().out
    for command in ("map", "plan", "train", "evaluate"):
        assert command in text


@pytest.mark.slow
def test_a_users_mesh_is_mapped_and_planned(tmp_path, capsys):
    """A 32 m roofed corridor (STL, z up, metres) with its route as 'x y' lines: the corridor axis is free."""
    import trimesh

    from l3e_env.cli.main import main

    parts = [trimesh.creation.box(extents) for extents in ([32, 4, 0.2], [32, 0.2, 3], [32, 0.2, 3], [32, 4, 0.2])]
    for part, offset in zip(parts, ([16, 0, -0.1], [16, 2, 1.5], [16, -2, 1.5], [16, 0, 3.1])):
        part.apply_translation(offset)
    trimesh.util.concatenate(parts).export(tmp_path / "corridor.stl")
    (tmp_path / "route.txt").write_text("5 0\n27 0\n")
    mesh_args = [
        "--scene",
        str(tmp_path / "corridor.stl"),
        "--route",
        str(tmp_path / "route.txt"),
        "--detector",
        "eigen:30",
        "--cache-dir",
        str(tmp_path / "cache"),
        "--out",
        str(tmp_path),
        "--quiet",
    ]
    assert main(["policy", "map", "--resolution", "4", *mesh_args]) == 0
    assert (tmp_path / "corridor-eigen30.png").stat().st_size > 10_000
    masked = capsys.readouterr().out.split("masked:")[1]
    assert masked.split()[:4] == ["x", "50%", "y", "50%"]  # along the corridor at two of the four headings
    assert main(["policy", "plan", "--resolution", "4", *mesh_args]) == 0
    planned = capsys.readouterr().out
    assert "corridor shortest" in planned and "building" not in planned  # the map just built, read from the cache
    outside = ["policy", "plan", *mesh_args, "--goal", "500", "500", "--out", str(tmp_path / "refused")]
    assert main(outside) == 2 and not (tmp_path / "refused").exists()  # issue 98: no empty folder left behind
    capsys.readouterr()
    assert main(["policy", "map", *mesh_args, "--scene", "fork-0"]) == 2
    assert "describe one mesh" in capsys.readouterr().err
    # several meshes from a list, each with its own route: the same corridor, and a copy of it
    (tmp_path / "copy").mkdir()
    (tmp_path / "copy" / "tube.stl").write_bytes((tmp_path / "corridor.stl").read_bytes())
    (tmp_path / "list.yaml").write_text(
        "- mesh: corridor.stl\n  route: route.txt\n- mesh: copy/tube.stl\n  route: [route.txt]\n"
    )
    listed = ["--meshes", str(tmp_path / "list.yaml"), "--resolution", "4", *mesh_args[4:]]
    assert main(["policy", "map", *listed]) == 0
    printed = [line for line in capsys.readouterr().out.splitlines() if "masked:" in line]
    assert [line.split(":")[0] for line in printed] == ["corridor", "tube"]
    assert all(line.split("masked:")[1].split()[:4] == ["x", "50%", "y", "50%"] for line in printed)
    assert main(["policy", "map", *listed, "--route", str(tmp_path / "route.txt")]) == 2
    assert "give no other mesh scene" in capsys.readouterr().err


@pytest.mark.slow
def test_a_users_mesh_is_driven_by_the_policies(cad_corridor, tmp_path, capsys, monkeypatch):
    """`l3e policy evaluate` in a y-up millimetre corridor: the episodes, the map and the resumption
    use the mesh's route, axes and scale; its scene marks no corridor, so 'rich route' is n/a."""
    from l3e_env.cli.main import main

    mesh, route = cad_corridor
    monkeypatch.chdir(mesh.parent)  # the mesh given by a relative path
    args = [
        "policy",
        "evaluate",
        "--scene",
        mesh.name,
        "--up-axis",
        "y",
        "--scale",
        "0.001",
        "--episodes",
        "1",
        "--detector",
        "eigen:30",
        "--cache-dir",
        str(tmp_path / "cache"),
        "--out",
        str(tmp_path / "ev"),
        "--quiet",
    ]
    assert main([*args, "--route", str(route)]) == 0
    (episode,) = [
        json.loads(line)
        for line in (tmp_path / "ev" / "episodes.jsonl").read_text().splitlines()
        if json.loads(line)["policy"] == "shortest"
    ]
    assert episode["success"] and episode["rich_route"] is None and 6.0 < episode["path_length"] < 9.0
    assert episode["trajectory"][-1][0] > 7.0  # driven along the corridor, in metres
    assert episode["scene"] == str(mesh.resolve())  # named for good, as datasets and recordings name it
    summary = (tmp_path / "ev" / "summary.txt").read_text()
    assert summary.splitlines()[2].split()[3] == "n/a"
    np.savetxt(tmp_path / "other.csv", [[1000.0, 0, 0], [6000, 0, 0]])
    assert main([*args, "--route", str(tmp_path / "other.csv")]) == 2  # the folder's episodes had another route
    assert "holds episodes run with other settings (scene_params." in capsys.readouterr().err
    assert main([*args, "--route", str(route), "--odometry-bias", "yaw"]) == 2  # the default's yaw,scale
    assert "other settings (fusion.odometry_bias ['yaw', 'scale'], now ['yaw'])" in capsys.readouterr().err
    assert main([*args, "--route", str(route), "--keyframe-distance", "0"]) == 2
    assert "other settings (fusion.keyframe_distance 4.0, now 0.0)" in capsys.readouterr().err
    assert main([*args, "--route", str(route), "--no-recovery"]) == 2  # the recovery is on by default
    assert "other settings (recovery True, now False)" in capsys.readouterr().err
    assert main([*args, "--route", str(route), "--recovery"]) == 0
    assert main([*args, "--route", str(route), "--no-avoid"]) == 2  # the local layer too
    assert "other settings (avoid True, now False)" in capsys.readouterr().err
    settings = json.loads((tmp_path / "ev" / "settings.json").read_text())
    assert (
        settings["fusion"].pop("odometry_bias") == ["yaw", "scale"]
        and settings.pop("recovery") is True
        and settings["avoid"] is True
    )
    (tmp_path / "ev" / "settings.json").write_text(json.dumps(settings))  # a folder that does not say its options
    assert main([*args, "--route", str(route)]) == 2
    err = capsys.readouterr().err
    assert "other settings (fusion.odometry_bias None, now ['yaw', 'scale'], recovery None, now True)" in err
    biased = [*args[:-3], "--out", str(tmp_path / "ev-bias"), "--quiet", "--route", str(route)]
    assert main([*biased, "--odometry-bias", "yaw", "--policy", "shortest"]) == 0
    summary = json.loads((tmp_path / "ev-bias" / "summary.json").read_text())
    assert summary["fusion"]["odometry_bias"] == ["yaw"] and summary["rows"][0]["success"] == 1.0
    (same_drive,) = [json.loads(line) for line in (tmp_path / "ev-bias" / "episodes.jsonl").read_text().splitlines()]
    assert same_drive["mean_ate"] != episode["mean_ate"]  # the same drive: the option reached the fusion


def test_fork_variants_differ():
    a, b = make_scene("fork-100"), make_scene("fork-101")
    assert a.goal[0] != b.goal[0] or np.abs(a.routes["rich"][:, 1]).max() != np.abs(b.routes["rich"][:, 1]).max()


def test_policy_train_without_the_rl_extra_says_so_before_building_maps(monkeypatch, tmp_path, capsys):
    import sys

    from l3e_env.cli.main import main

    monkeypatch.setitem(sys.modules, "stable_baselines3", None)  # as if not installed
    monkeypatch.setattr("policies.context.scene_context", lambda *a, **k: pytest.fail("a map was built first"))
    assert main(["policy", "train", "--scene", "fork-0", "--out", str(tmp_path / "ppo"), "--quiet"]) == 2
    assert "PPO needs stable-baselines3: pip install -e '.[rl]'" in capsys.readouterr().err


def test_a_policy_training_refused_while_it_is_set_up_leaves_no_folder(tmp_path):
    pytest.importorskip("stable_baselines3")
    from policies.ppo import train_ppo

    with pytest.raises(ValueError, match="at least one scene context"):
        train_ppo(tmp_path / "run", [], progress=False)
    assert not (tmp_path / "run").exists()
