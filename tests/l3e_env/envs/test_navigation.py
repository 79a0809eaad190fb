import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import l3e_env
from fusion import FusionConfig
from l3e_env.core.transforms import inverse
from l3e_env.envs.navigation import NavigationEnv
from l3e_env.localizability.registration import RegistrationConfig
from l3e_env.sim.follower import RouteFollower


def run(env, seed, steps=15):
    obs, info = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        obs, *_ = env.step(np.array([0.8, 0.1, 0.2], dtype=np.float32))
        out.append(obs)
    return out


@pytest.mark.parametrize("env_id", sorted(l3e_env.ENV_IDS))
def test_registered_environments_pass_gymnasiums_checker(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    check_env(env.unwrapped)
    assert env.spec.max_episode_steps == env.unwrapped.max_steps  # TimeLimit and the environment agree
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert (frame != frame[0, 0]).any(axis=-1).mean() > 0.001  # something is drawn
    assert frame.shape[0] % 2 == 0 and frame.shape[1] % 2 == 0  # as video encoders want, whatever the aspect
    assert (frame[-20:, :60] == 0).all(axis=-1).sum() > 60  # the scale bar, black, in the legend strip
    assert info["T_w_b"].shape == (4, 4)
    env.close()


def test_stable_baselines3_checker_accepts_the_environment_and_the_flat_one_without_a_warning():
    import warnings

    from stable_baselines3.common.env_checker import check_env as sb3_check

    from l3e_env.envs.wrappers import FlatObservation

    env = gym.make("l3e/Fork-v0")
    sb3_check(env.unwrapped, warn=False)
    flat = FlatObservation(env)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sb3_check(flat, warn=True)
    assert not [w for w in caught if "shape" in str(w.message)], [str(w.message) for w in caught]
    obs, _ = flat.reset(seed=0)
    image, _ = env.reset(seed=0)
    assert flat.observation_space.contains(obs) and np.array_equal(obs["ranges"], image["ranges"].reshape(-1))
    with pytest.raises(ValueError, match="Dict"):
        FlatObservation(gym.make("CartPole-v1"))


def test_same_seed_same_episode_different_seed_different_noise():
    a, b = gym.make("l3e/Tunnel-v0"), gym.make("l3e/Tunnel-v0")
    ra, rb, rc = run(a, 3), run(b, 3), run(a, 4)
    for oa, ob in zip(ra, rb):
        for key in oa:
            np.testing.assert_array_equal(oa[key], ob[key])
    assert not np.array_equal(ra[-1]["ranges"], rc[-1]["ranges"])
    # observations describe the tunnel: the side walls are about 2.25 m from the axis
    first = ra[0]
    assert first["ranges"].shape == (16, 360) and first["valid"].sum() > 0.9 * 16 * 360
    side = first["ranges"][7, 90]  # -1 deg beam, 90 deg to the left
    assert 2.0 < side < 2.5


def test_bad_actions_raise_clear_errors():
    env = gym.make("l3e/Office-v0").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0, 0], dtype=np.float32))
    with pytest.raises(ValueError, match="outside the action space"):
        env.step(np.array([2.0, 0, 0], dtype=np.float32))
    with pytest.raises(ValueError, match="3 finite numbers"):
        env.step(np.array([0.5, 0.0]))
    with pytest.raises(ValueError, match="unknown option"):
        gym.make("l3e/Office-v0", speed_of_light=1)
    with pytest.raises(ValueError, match="no route"):
        gym.make("l3e/Office-v0", route="scenic")


@pytest.mark.slow
def test_route_follower_reaches_the_goal_and_is_rewarded():
    env = gym.make("l3e/Fork-v0", route="short")
    obs, info = env.reset(seed=1)
    follow = RouteFollower(env.unwrapped.route)
    total, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, info = env.step(follow(info["T_w_b"]))
        total, steps = total + reward, steps + 1
        if terminated or truncated:
            break
    assert terminated and not truncated
    assert info["distance_to_goal"] <= 1.0
    assert total > 50.0  # ~54 m of progress + goal bonus - step penalties
    # dead reckoning has drifted, but not absurdly
    drift = np.linalg.norm(info["odom_T_w_b"][:3, 3] - info["T_w_b"][:3, 3])
    assert 0.0 < drift < 5.0


def test_truncation_at_the_time_limit():
    env = gym.make("l3e/Field-v0", max_episode_steps=5)
    env.reset(seed=0)
    flags = [env.step(np.zeros(3, dtype=np.float32))[2:4] for _ in range(5)]
    assert flags[-1] == (False, True) and all(f == (False, False) for f in flags[:-1])


def test_os0_128_option_and_async_vector_env():
    envs = gym.make_vec("l3e/Tunnel-v0", num_envs=2, vectorization_mode="async", lidar={"model": "os0-128"})
    obs, info = envs.reset(seed=[0, 1])
    assert obs["ranges"].shape == (2, 128, 256)
    obs, reward, terminated, truncated, info = envs.step(np.tile([[1.0, 0.0, 0.0]], (2, 1)).astype(np.float32))
    assert reward.shape == (2,) and np.all(reward > 0)
    envs.close()


@pytest.mark.parametrize("odometry_bias", [(), ("yaw",)])
def test_fusion_in_the_loop_reports_estimate_mask_and_running_ate(odometry_bias):
    env = NavigationEnv(
        dict(scene="tunnel", fusion=dict(enabled=True, detector="eigen:110", odometry_bias=list(odometry_bias)))
    )
    _, info = env.reset(seed=0)
    follow = RouteFollower(env.route)
    assert info["running_ate"] == 0.0 and not info["localizability_known"]
    odom_err, flagged_x = [], []
    for _ in range(60):
        _, _, _, _, info = env.step(follow(info["T_w_b"]))
        odom_err.append(np.linalg.norm(info["odom_T_w_b"][:3, 3] - info["T_w_b"][:3, 3]))
        flagged_x.append(info["localizability_mask"][0])
    assert info["fused_T_w_b"].shape == (4, 4) and info["localizability_probabilities"].shape == (6,)
    assert np.mean(flagged_x) > 0.5  # the tunnel's axis is x in the body frame at the start
    assert 0 < info["running_ate"] < 0.5
    assert info["fusion_counts"]["detector_errors"] == 0
    assert env.fusion.backend.odometry_bias.shape == (len(odometry_bias),)
    assert env.fusion.fusion_config.odometry_bias_sigmas[0] == env.config.odometry.yaw_bias_std
    assert env.fusion.fusion_config.odometry_bias == odometry_bias
    assert env.config.fusion.odometry_bias == odometry_bias
    assert env.fusion.registration == RegistrationConfig()  # the labels' registration: one everywhere
    assert env.fusion.fusion_config.icp_residual_variance == FusionConfig().icp_residual_variance
    env.close()


@pytest.mark.parametrize("every", [1, 4])
def test_a_failing_detector_is_counted_and_the_episode_goes_on(every):
    fusion = dict(enabled=True, detector="none", backend="ekf", detector_every=every)
    env = NavigationEnv(dict(scene="office", fusion=fusion))
    _, info = env.reset(seed=0)

    def broken(*args, **kwargs):
        raise RuntimeError("detector crashed")

    env.fusion.detector.predict = broken
    for _ in range(5):
        _, _, _, _, info = env.step(np.zeros(3))
    counts = info["fusion_counts"]
    # each judged step's failure counted (every 4th: steps 0 and 4); its unknown answer holds between
    assert counts["detector_errors"] == len(range(0, 5, every)) and counts["unknown"] == 5
    assert np.isfinite(info["fused_T_w_b"]).all()
    env.close()


@pytest.mark.parametrize("every", [1, 4])
@pytest.mark.slow
def test_the_classifier_in_a_process_of_its_own_gives_the_same_episode_and_a_dead_one_answers_unknown(every):
    runs = []
    for beside in (False, True):
        fusion = dict(enabled=True, detector="learned", detector_process=beside, detector_every=every)
        env = NavigationEnv(dict(scene="office", fusion=fusion))
        _, info = env.reset(seed=0)
        follow = RouteFollower(env.route)
        trail = []
        for _ in range(12):
            _, _, _, _, info = env.step(follow(info["T_w_b"]))
            trail.append((info["fused_T_w_b"].copy(), info["localizability_probabilities"].copy()))
        runs.append(trail)
        if beside:
            env.fusion.ahead._process.kill()  # a process that dies: unknown answers, counted; the walk goes on
            env.fusion.ahead._process.join()
            for _ in range(3):
                _, _, _, _, info = env.step(follow(info["T_w_b"]))
            asked = sum(k % every == 0 for k in (12, 13, 14))  # a held answer asks no process
            assert info["fusion_counts"]["detector_errors"] == asked and not info["localizability_known"]
        env.close()
    for (T_inline, p_inline), (T_beside, p_beside) in zip(*runs):
        np.testing.assert_array_equal(p_inline, p_beside)
        np.testing.assert_array_equal(T_inline, T_beside)
    with pytest.raises(ValueError, match="needs the registration"):
        NavigationEnv(dict(scene="office", fusion=dict(enabled=True, detector="eigen:30", detector_process=True)))


def test_a_swept_lidar_turns_each_revolution_with_the_step():
    """lidar={"sweep": True}: the scan after a step is cast over the step's motion, each point from
    where the sensor was when it fired; the one after reset over a revolution standing still."""
    env = gym.make("l3e/Tunnel-v0", lidar={"sweep": True, "range_noise_std": 0.0}).unwrapped
    env.reset(seed=0)
    at_rest = env.scan
    assert at_rest.times is not None and at_rest.times.max() < env.config.robot.dt
    before = env.robot.T_w_s
    env.step(np.array([1.0, 0.0, 1.0], dtype=np.float32))  # forward at 1 m/s, turning at 1 rad/s
    swept = env.scan
    still = env.lidar.scan(env.robot.T_w_s)  # the same pose's revolution without the motion
    assert swept.times is not None and len(swept) > 0.9 * len(still)
    common, i, j = np.intersect1d(
        swept.beam.astype(np.int64) * 10000 + swept.column,
        still.beam.astype(np.int64) * 10000 + still.column,
        return_indices=True,
    )
    moved = np.linalg.norm(swept.points[i] - still.points[j], axis=1)
    early = swept.times[i] < 0.02  # fired near the step's start, where the pose was furthest from the end's
    assert np.median(moved[early]) > 0.05 and np.median(moved[swept.times[i] > 0.098]) < 0.01
    assert not np.array_equal(before, env.robot.T_w_s)
    assert gym.make("l3e/Tunnel-v0").unwrapped.lidar.scan(np.eye(4)).times is None


@pytest.mark.parametrize("source", ["gyro", "odometry"])
def test_fusion_in_the_loop_deskews_a_swept_lidar_with_the_odometry_and_gyro(source):
    """The gyro draws from a stream of its own: the drive, its scans and its odometry are the same
    whichever deskews, and only the fused points differ."""

    def drive(deskew: str):
        env = NavigationEnv(
            dict(scene="tunnel", lidar=dict(sweep=True), fusion=dict(enabled=True, detector="eigen:110", deskew=deskew))
        )
        _, info = env.reset(seed=0)
        follow, fused = RouteFollower(env.route), []
        step = env.fusion.step

        def spy(increment, points, T, *attitude):
            fused.append(points)
            return step(increment, points, T, *attitude)

        env.fusion.step = spy
        for _ in range(30):
            _, _, _, _, info = env.step(follow(info["T_w_b"]))
        env.close()
        return env.scan.points, fused, info

    raw, fused, info = drive(source)
    assert len(fused) == 30 and fused[-1].shape == raw.shape and not np.array_equal(fused[-1], raw)
    assert 0.0 < np.abs(fused[-1] - raw).max() < 0.2  # a step's motion taken out, no more
    assert 0 < info["running_ate"] < 0.5 and info["fusion_counts"]["detector_errors"] == 0
    if source == "gyro":
        other_raw, other_fused, other_info = drive("odometry")
        np.testing.assert_array_equal(other_raw, raw)
        np.testing.assert_array_equal(other_info["odom_T_w_b"], info["odom_T_w_b"])
        assert not np.array_equal(other_fused[-1], fused[-1])
        with pytest.raises(ValueError, match="fusion.deskew must be one of"):
            NavigationEnv(dict(scene="tunnel", fusion=dict(deskew="imu")))


@pytest.mark.slow
def test_fusion_in_the_loop_takes_the_imu_attitude_once_a_second_from_a_stream_of_its_own():
    """The attitude's draws leave the drive as it was. With every ICP axis flagged (a threshold
    no eigenvalue reaches) and no ground, the fusion has the odometry alone, whose roll and pitch
    drift several degrees here; with the attitude, four readings weighed as the correlated readings
    they are, its tilt stays within a few times the unit's error (0.3 deg). With the ground, the
    floor holds the tilt where the legs drift (legs that carry one ground seen to the next)."""

    def drive(attitude: str, ground: str = "none"):
        env = NavigationEnv(
            dict(
                scene="tunnel",
                odometry=dict(rp_noise_per_m=0.1),
                fusion=dict(enabled=True, detector="eigen:1e12", attitude=attitude, ground=ground),
            )
        )
        _, info = env.reset(seed=0)
        follow = RouteFollower(env.route)
        for _ in range(40):
            _, _, _, _, info = env.step(follow(info["T_w_b"]))
        env.close()
        return info

    def tilt_error(T: np.ndarray, truth: np.ndarray) -> float:
        return float(np.degrees(np.arccos(np.clip((inverse(truth) @ T)[2, 2], -1.0, 1.0))))

    plain, held = drive("none"), drive("tilt")
    np.testing.assert_array_equal(plain["odom_T_w_b"], held["odom_T_w_b"])
    np.testing.assert_array_equal(plain["T_w_b"], held["T_w_b"])
    assert held["localizability_mask"].all()
    drift = tilt_error(plain["fused_T_w_b"], plain["T_w_b"])
    assert drift > 3.0  # the odometry's roll and pitch drift
    assert tilt_error(held["fused_T_w_b"], held["T_w_b"]) < min(1.5, 0.2 * drift)
    assert not np.array_equal(plain["fused_T_w_b"], held["fused_T_w_b"])
    floor = drive("none", "plane")
    assert tilt_error(floor["fused_T_w_b"], floor["T_w_b"]) < 0.1
    with pytest.raises(ValueError, match="attitude must be one of"):
        NavigationEnv(dict(scene="tunnel", fusion=dict(enabled=True, detector="none", attitude="compass")))
    with pytest.raises(ValueError, match="unknown option.*icp_covariance"):  # the estimator weighs by the Hessian
        NavigationEnv(dict(scene="tunnel", fusion=dict(enabled=True, detector="none", icp_covariance="fixed")))
    with pytest.raises(ValueError, match="odometry_bias takes distinct axes"):
        NavigationEnv(dict(scene="tunnel", fusion=dict(enabled=True, detector="none", odometry_bias=["roll"])))


def test_the_odometry_noise_is_the_same_whatever_the_sensor():
    """The odometry and the LiDAR draw from streams of their own: the drive's odometry is the same for
    any sensor or sweep setting, and the scans still differ from seed to seed."""

    def drive(seed: int = 0, **lidar):
        env = NavigationEnv(dict(scene="tunnel", lidar=lidar))
        _, info = env.reset(seed=seed)
        follow, odometry = RouteFollower(env.route), []
        for _ in range(8):
            obs, _, _, _, info = env.step(follow(info["T_w_b"]))
            odometry.append(obs["odometry"])
        env.close()
        return np.array(odometry), env.scan.points

    odom_vlp, scan_vlp = drive()
    odom_os0, _ = drive(model="os0-128")
    odom_swept, _ = drive(sweep=True)
    np.testing.assert_array_equal(odom_os0, odom_vlp)
    np.testing.assert_array_equal(odom_swept, odom_vlp)
    odom_seed1, scan_seed1 = drive(seed=1)
    assert (
        not np.array_equal(odom_seed1, odom_vlp)
        and len(scan_seed1)
        and not np.array_equal(scan_seed1[:100], scan_vlp[:100])
    )
    with pytest.raises(ValueError, match="noise_streams"):  # the option is gone, and named as unknown
        NavigationEnv(dict(scene="tunnel", noise_streams="separate"))


@pytest.mark.parametrize("arrival", ["truth", "estimate"])
def test_an_episode_ends_where_the_pose_that_arrival_names_reaches_the_goal(arrival):
    """arrival='estimate': the robot stops where it believes the goal is (its fused estimate, here
    made to run 3 m ahead), and info's distance_to_goal says how far it truly is."""
    from scenes.geometry import box, ground_plane, merge
    from scenes.scene import Scene

    route = np.array([[0.0, 0.0, 0.0], [8.0, 0.0, 0.0]])
    mesh = merge([ground_plane(-5, 15, -6, 6)] + [box((x, 3.0, 1.0), (0.5, 0.5, 2.0)) for x in range(-2, 12, 3)])
    env = NavigationEnv(
        dict(scene="posts", arrival=arrival, fusion=dict(enabled=True, detector="none", backend="ekf")),
        scene_object=Scene("posts", mesh, [route], (0, 0, 0), (8.0, 0.0), {"main": route}),
    )
    env.reset(seed=0)
    fused_step = env.fusion.step

    def ahead(*args, **kwargs):
        info = fused_step(*args, **kwargs)
        T = info["fused_T_w_b"].copy()
        T[0, 3] += 3.0
        return {**info, "fused_T_w_b": T}

    env.fusion.step = ahead
    for _ in range(120):
        _, _, terminated, _, info = env.step(np.array([1.0, 0.0, 0.0]))
        if terminated:
            break
    env.close()
    assert terminated
    if arrival == "estimate":
        stop = env.config.stop_radius
        assert stop - 0.15 <= np.linalg.norm(info["fused_T_w_b"][:2, 3] - (8.0, 0.0)) <= stop  # at its goal
        assert info["distance_to_goal"] == pytest.approx(3.0 + stop, abs=0.15)  # stopped 3 m short in truth
    else:
        assert info["distance_to_goal"] == pytest.approx(1.0, abs=0.15)


def test_arrival_on_the_estimate_needs_the_fusion():
    with pytest.raises(ValueError, match="turn the fusion on"):
        NavigationEnv(dict(scene="office", arrival="estimate"))
    with pytest.raises(ValueError, match="arrival must be one of"):
        NavigationEnv(dict(scene="office", arrival="belief"))
    with pytest.raises(ValueError, match="stop_radius must be"):
        NavigationEnv(dict(scene="office", stop_radius=2.0))
