import ast
from pathlib import Path

import gtsam
import numpy as np
import pytest

from fusion import (
    BACKENDS,
    FusionConfig,
    FusionError,
    FusionGraph,
    MetricError,
    ate,
    ate_aligned,
    icp_information,
    rpe,
    to_gtsam_order,
    to_project_order,
    umeyama,
)


def pose(x=0.0, y=0.0, z=0.0, yaw=0.0):
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x, y, z)
    return T


def test_tangent_order_conversion_matches_gtsam_semantics():
    np.testing.assert_array_equal(to_gtsam_order(np.arange(6.0)), [3, 4, 5, 0, 1, 2])
    np.testing.assert_array_equal(to_project_order(to_gtsam_order(np.arange(6.0))), np.arange(6.0))
    x_step = gtsam.Pose3.Expmap(to_gtsam_order(np.array([0.5, 0, 0, 0, 0, 0])))
    np.testing.assert_allclose(x_step.translation(), [0.5, 0, 0], atol=1e-12)
    roll = gtsam.Pose3.Expmap(to_gtsam_order(np.array([0, 0, 0, 0.1, 0, 0])))
    np.testing.assert_allclose(roll.rotation().roll(), 0.1, atol=1e-12)
    H = np.diag(np.arange(1.0, 7.0))
    assert to_gtsam_order(H)[0, 0] == 4.0 and to_project_order(to_gtsam_order(H))[5, 5] == 6.0
    with pytest.raises(ValueError):
        to_gtsam_order(np.zeros(5))


def drive(mode, mask_x, steps=200, backend="graph", hessian=None, config=None):
    """A tunnel-like run: ICP sees no motion along x (it sticks), odometry over-reports x by 5 %.
    `hessian`: each ICP step's (project order); None: the fixed sigmas."""
    graph = BACKENDS[backend](np.eye(4), config or FusionConfig(mode=mode))
    truth, est = [np.eye(4)], [np.eye(4)]
    odom_sigmas = np.array([0.05, 0.05, 0.05, 0.01, 0.01, 0.01])  # legs: less certain than ICP
    mask = np.array([mask_x, False, False, False, False, False])
    for _ in range(steps):
        step = pose(0.1, 0.0, 0.0, 0.002)
        truth.append(truth[-1] @ step)
        odom = pose(0.105, 0.0, 0.0, 0.002 + 0.001)
        icp = pose(0.0, 0.0, 0.0, 0.002)  # degenerate along x, right elsewhere
        T, report = graph.add_step(odom, odom_sigmas, icp, mask, hessian)
        est.append(T)
    return np.array(truth), np.array(est), graph, report


@pytest.mark.parametrize("backend", BACKENDS)
def test_masking_the_degenerate_axis_beats_full_icp_and_dropping_uses_odometry_only(backend):
    truth, full, *_ = drive("full", mask_x=True, backend=backend)
    _, masked, graph, report = drive("mask", mask_x=True, backend=backend)
    _, dropped, *_ = drive("drop", mask_x=True, backend=backend)
    assert report.icp_used and report.masked_axes == 1
    e_full, e_mask, e_drop = ate(full, truth), ate(masked, truth), ate(dropped, truth)
    assert e_mask < 0.2 * e_full  # full ICP stalls: the robot "stays" at the tunnel entrance
    assert e_mask < e_drop  # the unmasked yaw of ICP fixes the odometry's yaw bias
    # along x the masked estimate follows the odometry (5 % over)
    assert abs(masked[-1][0, 3] - 1.05 * truth[-1][0, 3]) < 0.3
    assert graph.trajectory().shape == (201, 4, 4)


def test_the_filter_matches_the_smoother_at_the_newest_pose():
    """Without loop closures the newest iSAM2 estimate is the filtered one, up to the smoother
    relinearising past poses: here 2.6 mm over 5 m (3e-6 m when odometry and ICP agree in yaw);
    a sign error in the filter's measurement Jacobian gives 11 mm."""
    _, graph_est, *_ = drive("mask", mask_x=True, steps=50)
    _, ekf_est, *_ = drive("mask", mask_x=True, steps=50, backend="ekf")
    np.testing.assert_allclose(ekf_est[:, :3, 3], graph_est[:, :3, 3], atol=4e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def tunnel_hessian(weak_direction: np.ndarray) -> np.ndarray:
    """A Hessian that holds every direction at 1e6 but `weak_direction` (unit, project order) at 1e-3."""
    d = weak_direction / np.linalg.norm(weak_direction)
    return 1e6 * np.eye(6) - (1e6 - 1e-3) * np.outer(d, d)


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_registrations_hessian_weighs_each_axis_as_it_is_held_without_a_mask(backend):
    """Unmasked, with the Hessian's information the slipping tunnel axis weighs nothing and the
    odometry decides along it (5 % over), while full ICP with fixed sigmas stalls; a masked axis
    is dropped from the Hessian's information as from the fixed one."""
    hessian = tunnel_hessian(np.eye(6)[0])
    truth, weighed, *_ = drive("mask", mask_x=False, backend=backend, hessian=hessian)
    _, stalled, *_ = drive(
        "mask", mask_x=False, backend=backend, config=FusionConfig(icp_covariance="fixed"), hessian=hessian
    )
    assert abs(weighed[-1][0, 3] - 1.05 * truth[-1][0, 3]) < 0.3
    assert stalled[-1][0, 3] < 0.5 * truth[-1][0, 3]
    information = icp_information(FusionConfig(), np.full((6, 6), 3.0), np.array([1, 0, 0, 0, 0, 1], bool))
    assert not information[[0, 5]].any() and not information[:, [0, 5]].any() and (information[1:5, 1:5] > 0).all()
    np.testing.assert_allclose(
        icp_information(FusionConfig(), np.full((6, 6), np.nan), np.zeros(6, bool)),
        np.diag(1.0 / np.asarray(FusionConfig().icp_sigmas) ** 2),
    )  # no Hessian: fixed
    # rounding leaves a free direction a hair below zero; with every other axis masked the factor is diagonal
    graph = BACKENDS[backend](np.eye(4))
    almost = np.diag([-1e-12, 1e6, 1e6, 1e6, 1e6, 1e6])
    T, report = graph.add_step(pose(0.1), np.full(6, 0.01), pose(0.1), np.r_[False, np.ones(5, bool)], almost)
    assert report.icp_used and np.isfinite(T).all()
    coupled = np.eye(6)  # a tunnel step with x, y and z masked: the rotations held together
    coupled[3:, 3:] = [[1.6e5, 9.7e4, -7.5e5], [9.7e4, 1.9e7, 2.5e5], [-7.5e5, 2.5e5, 1.4e7]]
    T, report = graph.add_step(
        pose(0.1), np.full(6, 0.01), pose(0.1), np.r_[np.ones(3, bool), np.zeros(3, bool)], coupled
    )
    assert report.icp_used and report.masked_axes == 3 and np.isfinite(T).all()
    for bad in (FusionConfig(icp_covariance="adaptive"), FusionConfig(icp_residual_variance=0.0)):
        with pytest.raises(ValueError, match="icp_covariance|icp_residual_variance"):
            BACKENDS[backend](np.eye(4), bad)


def test_the_filter_matches_the_smoother_with_a_hessian_that_couples_axes():
    """y and yaw held together (an information matrix that is not diagonal), x slipping: the
    smoother's square-root noise model and the filter's inverse of the kept block agree."""
    hessian = tunnel_hessian(np.eye(6)[0])
    hessian[1, 5] = hessian[5, 1] = 5e5
    _, graph_est, *_ = drive("mask", mask_x=False, steps=50, hessian=hessian)
    _, ekf_est, *_ = drive("mask", mask_x=False, steps=50, backend="ekf", hessian=hessian)
    np.testing.assert_allclose(ekf_est[:, :3, 3], graph_est[:, :3, 3], atol=4e-3)
    _, fixed_est, *_ = drive("mask", mask_x=False, steps=50, config=FusionConfig(icp_covariance="fixed"))
    assert np.abs(graph_est[-1][:3, 3] - fixed_est[-1][:3, 3]).max() > 0.05


@pytest.mark.parametrize("backend", BACKENDS)
def test_under_constrained_steps_fall_back_and_never_crash(backend):
    graph = BACKENDS[backend](np.eye(4))
    T, report = graph.add_step(None, None, pose(0.1), np.ones(6, dtype=bool))
    assert report.fallback and "all axes masked" in report.fallback
    np.testing.assert_allclose(T[:3, 3], [0.1, 0, 0], atol=1e-6)
    T, report = graph.add_step(None, None, None, None)
    assert "constant-position" in report.fallback and np.isfinite(T).all()
    T, report = graph.add_step(np.full((4, 4), np.nan), np.ones(6), pose(0.1), np.zeros(6, dtype=bool))
    assert report.icp_used and np.isfinite(T).all()
    with pytest.raises(ValueError, match="fusion mode"):
        BACKENDS[backend](np.eye(4), FusionConfig(mode="sometimes"))


@pytest.mark.parametrize("backend", BACKENDS)
def test_bad_odometry_sigmas_are_refused_by_name(backend):
    graph = BACKENDS[backend](np.eye(4))
    for bad in (np.full(6, np.inf), np.r_[np.ones(5), np.nan], np.ones(3), None):
        with pytest.raises(ValueError, match="odometry sigmas"):
            graph.add_step(pose(0.1), bad, pose(0.1), np.zeros(6, dtype=bool))


def test_an_unsolvable_graph_names_the_step():
    graph = FusionGraph(np.eye(4))
    factors = gtsam.NonlinearFactorGraph()
    factors.add(gtsam.BetweenFactorPose3(0, 5, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    with pytest.raises(FusionError, match="fusion step 1: GTSAM could not solve"):
        graph._update(factors, gtsam.Values(), 1)  # a factor on a pose that has no value


@pytest.mark.parametrize("backend", BACKENDS)
def test_without_odometry_the_masked_axes_stand_still_and_the_held_ones_follow_icp(backend):
    """No odometry, ICP with y and yaw masked: nothing else holds those two axes, so they keep the
    previous pose's (a weak constant-position tie); x follows ICP. The pose stays solvable."""
    graph = BACKENDS[backend](np.eye(4))
    mask = np.array([False, True, False, False, False, True])
    icp = pose(0.2, 0.3, 0.0, 0.1)
    T, report = graph.add_step(None, None, icp, mask)
    assert report.fallback and "masked axes" in report.fallback
    x = to_project_order(gtsam.Pose3.Logmap(gtsam.Pose3(icp)))[0]  # x in the motion's tangent
    np.testing.assert_allclose([T[0, 3], T[1, 3]], [x, 0.0], atol=1e-3)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-3)
    T, _ = graph.add_step(pose(0.1), np.full(6, 0.01), pose(0.1), np.zeros(6, dtype=bool))
    assert np.isfinite(T).all() and abs(T[0, 3] - x - 0.1) < 1e-3


def tilted_walk(backend, attitude_sigmas=None, steps=100):
    """Odometry whose pitch and yaw drift 1 mrad a step; an IMU's attitude (the truth: level, no
    turn) every 10 steps where `attitude_sigmas` is given. Returns the final roll, pitch, yaw."""
    graph = BACKENDS[backend](np.eye(4))
    drift = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.0, 0.001, 0.001), np.array([0.1, 0.0, 0.0])).matrix()
    for k in range(steps):
        T, _ = graph.add_step(drift, np.array([0.01, 0.01, 0.01, 0.002, 0.002, 0.002]))
        if attitude_sigmas is not None and (k + 1) % 10 == 0:
            T = graph.add_attitude(np.eye(3), attitude_sigmas)
    rot = gtsam.Rot3(T[:3, :3])
    return np.array([rot.roll(), rot.pitch(), rot.yaw()]), graph


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_attitude_holds_the_measured_axes_and_leaves_the_heading_free_without_a_magnetometer(backend):
    drifted, _ = tilted_walk(backend)
    assert drifted[1] > 0.09 and drifted[2] > 0.09  # 100 steps of 1 mrad
    tilt, graph = tilted_walk(backend, np.array([0.001, 0.001, np.inf]))
    assert abs(tilt[0]) < 0.005 and abs(tilt[1]) < 0.005  # gravity holds roll and pitch
    assert abs(tilt[2] - drifted[2]) < 0.005  # no heading measured: yaw drifts as before
    full, _ = tilted_walk(backend, np.array([0.001, 0.001, 0.001]))
    assert np.abs(full).max() < 0.005
    for bad_rotation in (np.full((3, 3), np.nan), 2.0 * np.eye(3), np.diag([1.0, 1.0, -1.0])):
        with pytest.raises(ValueError, match="rotation matrix"):
            graph.add_attitude(bad_rotation, np.ones(3))
    for bad_sigmas in (np.array([0.01, np.nan, 0.01]), np.zeros(3), np.ones(2)):
        with pytest.raises(ValueError, match="attitude sigmas"):
            graph.add_attitude(np.eye(3), bad_sigmas)


def test_the_filter_matches_the_smoother_at_the_newest_pose_with_attitudes():
    graph_tilt, _ = tilted_walk("graph", np.array([0.001, 0.001, np.inf]), steps=50)
    ekf_tilt, _ = tilted_walk("ekf", np.array([0.001, 0.001, np.inf]), steps=50)
    np.testing.assert_allclose(ekf_tilt, graph_tilt, atol=1e-3)


def test_the_bias_factors_jacobians_match_numerical_differences():
    from fusion.bias import corrected_increment, odometry_bias_factor

    measured = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.01, -0.02, 0.1), np.array([0.1, 0.02, 0.01])).matrix()
    axes, bias = ("yaw", "z"), np.array([0.003, -0.01])
    Z, G = corrected_increment(measured, bias, axes)
    assert np.degrees(gtsam.Rot3(measured[:3, :3]).between(Z.rotation()).yaw()) < 0  # a positive bias over-reads
    for n in range(2):
        step = 1e-6 * np.eye(2)[n]
        np.testing.assert_allclose(
            gtsam.Pose3.Logmap(Z.between(corrected_increment(measured, bias + step, axes)[0])) / 1e-6,
            G[:, n],
            atol=1e-8,
        )
    X_prev = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.1, 0.2, 0.3), np.array([1.0, 2.0, 3.0]))
    X_cur = X_prev.compose(gtsam.Pose3(gtsam.Rot3.RzRyRx(0.02, -0.01, 0.12), np.array([0.11, 0.0, 0.02])))
    factor = odometry_bias_factor(measured, 0, 1, 2, gtsam.noiseModel.Unit.Create(6), axes)
    values = gtsam.Values()
    values.insert(0, X_prev)
    values.insert(1, X_cur)
    values.insert(2, bias)
    analytic, _ = factor.linearize(values).jacobian()
    e0, numeric = factor.unwhitenedError(values), []
    for key, dim in ((0, 6), (1, 6), (2, 2)):
        for n in range(dim):
            moved = gtsam.Values(values)
            step = 1e-7 * np.eye(dim)[n]
            moved.update(key, values.atPose3(key).retract(step) if key < 2 else bias + step)
            numeric.append((factor.unwhitenedError(moved) - e0) / 1e-7)
    np.testing.assert_allclose(np.array(numeric).T, analytic, atol=1e-6)


def biased_walk(backend, axes, held_steps=200, blind_steps=100, yaw_bias=0.005, z_bias=0.01):
    """Legs that over-read the heading by `yaw_bias` rad and the height by `z_bias` m per metre;
    ICP holds every axis for `held_steps`, then yaw and z are masked for `blind_steps` (as where a
    corridor leaves the scans nothing to turn or climb against). Returns the final yaw and height
    errors and the fusion."""
    config = FusionConfig(odometry_bias=axes, odometry_bias_sigmas=(0.01, 0.02, 0.02))
    fusion = BACKENDS[backend](np.eye(4), config)
    truth, step = np.eye(4), pose(0.1, 0.0, 0.0, 0.0)
    odom = pose(0.1, 0.0, 0.1 * z_bias, 0.1 * yaw_bias)
    sigmas = np.array([0.004, 0.004, 0.004, 3e-4, 3e-4, 6e-4])
    for k in range(held_steps + blind_steps):
        truth = truth @ step
        mask = np.array([False, False, k >= held_steps, False, False, k >= held_steps])
        T, _ = fusion.add_step(odom, sigmas, step, mask)
        yaw_error = np.arctan2((np.linalg.inv(truth) @ T)[1, 0], (np.linalg.inv(truth) @ T)[0, 0])
    return abs(yaw_error), abs(T[2, 3] - truth[2, 3]), fusion


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_legs_bias_learnt_where_icp_holds_keeps_the_heading_and_height_where_it_does_not(backend):
    plain_yaw, plain_z, _ = biased_walk(backend, ())
    yaw_only, yaw_only_z, fusion = biased_walk(backend, ("yaw",))
    assert plain_yaw > 0.04 and plain_z > 0.08  # 10 m blind: 0.05 rad and 0.1 m of the legs' bias
    assert yaw_only < 0.2 * plain_yaw and yaw_only_z == pytest.approx(plain_z, rel=0.05)
    assert fusion.odometry_bias == pytest.approx([0.005], rel=0.1)
    both_yaw, both_z, fusion = biased_walk(backend, ("yaw", "z"))
    assert both_yaw < 0.2 * plain_yaw and both_z < 0.2 * plain_z
    assert fusion.odometry_bias == pytest.approx([0.005, 0.01], rel=0.1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_strides_scale_learnt_where_icp_holds_keeps_the_length_of_a_tunnel(backend):
    """Legs that over-read each step by 3 %: ICP holds every axis for 20 m, then x is masked for 10 m,
    as along a tunnel. With the scale as a state the blind stretch is walked at its true length."""

    def walk(axes):
        fusion = BACKENDS[backend](np.eye(4), FusionConfig(odometry_bias=axes))
        truth, step, odom = np.eye(4), pose(0.1), pose(0.103)
        sigmas = np.array([0.004, 0.004, 0.004, 3e-4, 3e-4, 6e-4])
        for k in range(300):
            truth = truth @ step
            T, _ = fusion.add_step(odom, sigmas, step, np.r_[k >= 200, np.zeros(5, bool)])
        return abs(T[0, 3] - truth[0, 3]), fusion

    plain, _ = walk(())
    scaled, fusion = walk(("scale",))
    assert plain > 0.25  # 10 m blind at 3 % over
    assert scaled < 0.2 * plain and fusion.odometry_bias == pytest.approx([0.03 / 1.03], rel=0.1)


def test_the_filter_matches_the_smoother_with_the_legs_bias():
    """The graph holds one bias state per metre, the filter one per step: the same walk, within 1 mm."""
    *_, graph = biased_walk("graph", ("yaw", "z"), held_steps=100, blind_steps=50)
    *_, ekf = biased_walk("ekf", ("yaw", "z"), held_steps=100, blind_steps=50)
    np.testing.assert_allclose(ekf.odometry_bias, graph.odometry_bias, rtol=0.05)
    np.testing.assert_allclose(ekf.trajectory()[-1][:3, 3], graph.trajectory()[-1][:3, 3], atol=1e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_legs_bias_survives_standing_still_missing_steps_and_refuses_bad_settings(backend):
    fusion = BACKENDS[backend](np.eye(4), FusionConfig(odometry_bias=("yaw",)))
    for _ in range(20):  # standing still: the bias does not wander, and the graph adds no bias state
        T, _ = fusion.add_step(np.eye(4), np.full(6, 1e-3), np.eye(4), np.zeros(6, bool))
    assert getattr(fusion, "_knot", 0) == 0 and np.isfinite(T).all()
    T, report = fusion.add_step(None, None, pose(0.1), np.ones(6, dtype=bool))
    assert "all axes masked" in report.fallback and np.isfinite(T).all()
    T, report = fusion.add_step(None, None, None, None)
    assert "constant-position" in report.fallback and np.isfinite(fusion.odometry_bias).all()
    for bad in (
        dict(odometry_bias=("roll",)),
        dict(odometry_bias=("yaw", "yaw")),
        dict(odometry_bias=("yaw",), odometry_bias_walk=(0.0, 1e-3, 1e-4)),
        dict(odometry_bias=("z",), odometry_bias_sigmas=(np.nan, 1e-3, 0.02)),
        dict(odometry_bias=("scale",), odometry_bias_sigmas=(1e-3, 1e-3)),
    ):
        with pytest.raises(ValueError, match="odometry_bias"):
            BACKENDS[backend](np.eye(4), FusionConfig(**bad))


def test_a_fixed_lag_keeps_the_newest_estimate_of_the_whole_smoother_in_a_bounded_window():
    """Noisy legs with yaw and z biases, ICP masked on the last third, an IMU's tilt every 10 steps:
    a 40-step window gives the whole drive's newest estimate at every step, holds no more than its
    window, and its trajectory keeps every pose (those that left as they left)."""
    rng = np.random.default_rng(3)
    sigmas = np.array([0.004, 0.004, 0.004, 3e-4, 3e-4, 6e-4])
    steps = [
        (
            pose(0.1, 0.0, 0.001, 0.0005 + 0.003 * np.sin(k / 20)) @ pose(*(rng.normal(0, 0.003, 3))),
            pose(0.1, 0.0, 0.0, 0.003 * np.sin(k / 20)) @ pose(*(rng.normal(0, 0.001, 3))),
            k >= 200,
        )
        for k in range(300)
    ]
    runs = {}
    for lag in (None, 40):
        graph = FusionGraph(np.eye(4), FusionConfig(odometry_bias=("yaw", "z"), smoother_lag=lag))
        newest = []
        for k, (odom, icp, blind) in enumerate(steps):
            T, _ = graph.add_step(odom, sigmas, icp, np.array([False, False, blind, False, False, blind]))
            if (k + 1) % 10 == 0:
                T = graph.add_attitude(np.eye(3), np.array([0.002, 0.002, np.inf]))
            newest.append(T)
        runs[lag] = np.array(newest), graph
    (full, _), (lagged, graph) = runs[None], runs[40]
    assert np.abs(lagged[:, :3, 3] - full[:, :3, 3]).max() < 0.01
    assert np.abs(lagged[:, :3, :3] - full[:, :3, :3]).max() < 1e-3
    assert np.abs(full[-1][:3, 3] - graph.trajectory()[-1][:3, 3]).max() < 0.01
    # the window's poses (up to a batch of marginalize_every beyond the lag) and bias states
    assert len(graph.isam.calculateEstimate().keys()) <= 40 + graph.config.marginalize_every + 3 + 5
    trajectory = graph.trajectory()
    assert len(trajectory) == 301 and np.abs(trajectory[1:251, :3, 3] - full[:250, :3, 3]).max() < 0.02
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="smoother_lag"):
            FusionGraph(np.eye(4), FusionConfig(smoother_lag=bad))
        with pytest.raises(ValueError, match="marginalize_every"):
            FusionGraph(np.eye(4), FusionConfig(smoother_lag=40, marginalize_every=bad))


def test_the_window_marginalizes_in_batches():
    """With `marginalize_every`, the poses leave the window in batches: it holds between the lag and
    the lag plus a batch of steps, and the trajectory still keeps every pose."""
    sizes = {}
    for every in (1, 5):
        graph = FusionGraph(np.eye(4), FusionConfig(smoother_lag=10, marginalize_every=every))
        held = []
        for _ in range(60):
            graph.add_step(pose(0.1), np.full(6, 0.01), pose(0.1), np.zeros(6, dtype=bool))
            held.append(len(graph.isam.calculateEstimate().keys()))
        sizes[every] = held[20:]
        trajectory = graph.trajectory()
        assert len(trajectory) == 61
        np.testing.assert_allclose(trajectory[:, 0, 3], 0.1 * np.arange(61), atol=1e-6)
    assert max(sizes[1]) - min(sizes[1]) <= 1
    assert min(sizes[5]) >= min(sizes[1]) and max(sizes[5]) - min(sizes[5]) >= 4


@pytest.mark.parametrize("lag", [None, 200])
def test_a_long_drive_with_masked_coupled_icp_factors_stays_solvable(lag):
    """3 000 steps of ICP factors with coupled Hessians and random masked axes (rotations too): the
    newest pose's marginal grows with the drive while each step stays sharp. GTSAM's default Cholesky
    met an indeterminate system near step 2 580 here, whole drive and window alike."""
    rng = np.random.default_rng(0)
    graph = FusionGraph(np.eye(4), FusionConfig(smoother_lag=lag))
    sigmas = np.array([0.01, 0.01, 0.01, 0.002, 0.002, 0.004])
    for k in range(3000):
        true = pose(0.1, yaw=0.02 * np.sin(k / 50))
        noise_odom, noise_icp = rng.normal(0, sigmas), rng.normal(0, sigmas / 5)
        odom = true @ gtsam.Pose3.Expmap(to_gtsam_order(noise_odom)).matrix()
        icp = true @ gtsam.Pose3.Expmap(to_gtsam_order(noise_icp)).matrix()
        rows = rng.normal(size=(200, 6)) * np.array([1.0, 1.0, 1.0, 5.0, 5.0, 5.0])
        T, _ = graph.add_step(odom, sigmas, icp, rng.random(6) < 0.2, rows.T @ rows)
    assert np.isfinite(T).all() and graph.k == 3000


def test_robust_kernels_build():
    for kernel in ("huber", "cauchy"):
        graph = FusionGraph(np.eye(4), FusionConfig(robust_kernel=kernel))
        T, _ = graph.add_step(pose(0.1), np.full(6, 0.01), pose(0.1), np.zeros(6, dtype=bool))
        np.testing.assert_allclose(T[:3, 3], [0.1, 0, 0], atol=1e-6)


def test_ate_rpe_and_alignment():
    rng = np.random.default_rng(0)
    gt = np.array([pose(0.1 * k, np.sin(0.05 * k), 0.01 * k, 0.01 * k) for k in range(100)])
    shifted = gt.copy()
    shifted[:, 0, 3] += 0.3
    assert ate(shifted, gt) == pytest.approx(0.3)
    assert ate_aligned(shifted, gt) == pytest.approx(0.0, abs=1e-9)
    assert rpe(gt, gt, 5) == pytest.approx((0.0, 0.0), abs=1e-12)
    R = gtsam.Rot3.RzRyRx(*rng.normal(0, 0.3, 3)).matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, rng.normal(0, 5, 3)
    moved = gt[:, :3, 3] @ R.T + T[:3, 3]
    np.testing.assert_allclose(umeyama(gt[:, :3, 3], moved), T, atol=1e-9)
    line = np.column_stack([np.arange(20.0), np.zeros(20), np.zeros(20)])
    with pytest.raises(MetricError, match="colinear"):
        umeyama(line, line)
    with pytest.raises(MetricError, match="NaN"):
        ate(np.full((3, 3), np.nan), np.zeros((3, 3)))
    with pytest.raises(MetricError, match="length"):
        ate(np.zeros((3, 3)), np.zeros((4, 3)))


def test_fusion_imports_nothing_of_the_project():
    for path in Path(__file__).parents[2].joinpath("fusion").glob("*.py"):
        tree = ast.parse(path.read_text())
        names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {
            n.module.split(".")[0]
            for n in ast.walk(tree)
            if isinstance(n, ast.ImportFrom) and n.module and n.level == 0
        }
        assert not names & {"l3e_env", "scenes", "policies"}, path


def test_stretch_drift_counts_only_the_error_made_inside_the_stretches():
    from fusion import MetricError, stretch_drift
    from l3e_env.core.transforms import pose_to_matrix

    n = 60
    gt = np.stack([pose_to_matrix(np.array([0.5 * k, 0, 0, 0, 0, 0])) for k in range(n)])
    est = gt.copy()
    est[:, 1, 3] += 3.0  # an error carried in from before: no drift of its own
    est[20:, 0, 3] += 0.02 * np.arange(n - 20)  # 2 cm too far each step from step 20 on
    inside = np.zeros(n, bool)
    inside[30:40] = inside[50:55] = True
    drift, distance = stretch_drift(est, gt, inside)
    assert distance == pytest.approx(0.5 * (9 + 4))
    assert drift == pytest.approx(0.02 * (9 + 4))
    assert stretch_drift(est, gt, np.zeros(n, bool)) == (0.0, 0.0)
    turned = pose_to_matrix(np.array([1, 2, 0, 0, 0, 0.3])) @ est  # a heading error made before the stretch
    assert stretch_drift(turned, gt, inside)[0] == pytest.approx(drift, rel=1e-9)
    assert ate(turned, gt) > 2 * ate(est, gt)  # which the ATE does count
    with pytest.raises(MetricError, match="mask"):
        stretch_drift(est, gt, inside[:-1])


def test_the_pipeline_says_start_first_when_stepped_before_a_drive():
    from l3e_env.config import OdometryConfig
    from l3e_env.detection.detectors import NoDetector
    from l3e_env.detection.pipeline import LocalizationPipeline

    pipeline = LocalizationPipeline(NoDetector(), "graph", FusionConfig(), OdometryConfig(), np.eye(4))
    with pytest.raises(RuntimeError, match=r"call start\(T_w_b\)"):
        pipeline.step(pose(0.1), None, np.zeros((0, 3)), None)
    pipeline.start(np.eye(4))
    outcome = pipeline.step(pose(0.1), None, np.zeros((0, 3)), None)
    assert np.allclose(outcome.T_w_b[:3, 3], [0.1, 0, 0], atol=1e-6)


def pitched(x: float, pitch: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(pitch), np.sin(pitch)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[0, 3] = x
    return T


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_mask_in_the_level_frame_drops_a_tilted_tunnels_slide_and_keeps_its_height(backend):
    """A body pitched 8 deg walks a level tunnel: ICP sticks along the tunnel (world x), which in the
    body frame is x and z together. Masked on the level frame's x (the mask basis), the slide goes to
    the legs and the height stays; masked on the body's x, ICP's zero step holds the body's z and
    the estimate sinks along the tunnel."""
    theta = np.radians(8.0)
    T_l_b = np.eye(4)
    T_l_b[:3, :3] = pitched(0.0, theta)[:3, :3]  # the level frame: world-aligned here
    level = np.zeros((6, 6))
    level[:3, :3] = level[3:, 3:] = T_l_b[:3, :3]
    mask = np.r_[True, np.zeros(5, bool)]
    finals = {}
    for name, basis in (("level", level), ("body", None)):
        fusion = BACKENDS[backend](pitched(0.0, theta), FusionConfig(icp_covariance="fixed"))
        truth = pitched(0.0, theta)
        for _ in range(100):
            step = np.linalg.inv(truth) @ pitched(truth[0, 3] + 0.1, theta)
            truth = truth @ step
            odom = step.copy()
            odom[:3, 3] *= 1.05
            T, report = fusion.add_step(odom, np.full(6, 0.05), np.eye(4), mask, None, 1, basis)
        finals[name] = (T, truth)
        assert report.icp_used and report.masked_axes == 1
    T, truth = finals["level"]
    assert abs(T[2, 3] - truth[2, 3]) < 0.05 and abs(T[0, 3] - 1.05 * truth[0, 3]) < 0.1, T[:3, 3]
    T, truth = finals["body"]
    assert abs(T[2, 3] - truth[2, 3]) > 0.5, T[:3, 3]  # the body's z held by the stuck ICP: off by metres
    with pytest.raises(ValueError, match="invertible, finite 6x6"):
        icp_information(FusionConfig(), None, mask, np.zeros((6, 6)))


@pytest.mark.parametrize("backend", BACKENDS)
def test_masking_the_informations_own_directions_keeps_what_a_flagged_axis_shares_with_a_held_one(backend):
    """Mode "directions": a Hessian whose weak direction is x and whose strong one mixes x and z
    (a floor seen tilted). Flagging x drops only the weak direction: the factor still holds the
    strong mix, where the axis mask drops every row and column of x."""
    strong = np.array([0.3, 0, 1, 0, 0, 0]) / np.hypot(0.3, 1)
    weak = np.array([1, 0, -0.3, 0, 0, 0]) / np.hypot(0.3, 1)
    hessian = 1e6 * np.outer(strong, strong) + 1e-3 * np.outer(weak, weak) + 1e6 * np.diag([0, 1, 0, 1, 1, 1])
    mask = np.r_[True, np.zeros(5, bool)]
    directions = icp_information(FusionConfig(mode="directions"), hessian, mask)
    axes = icp_information(FusionConfig(), hessian, mask)
    assert strong @ directions @ strong == pytest.approx(
        strong @ hessian @ strong / FusionConfig().icp_residual_variance
    )
    assert abs(weak @ directions @ weak) < 1e-3 and not axes[0].any()
    assert strong @ axes @ strong < 0.95 * strong @ directions @ strong  # the axis mask lost part of the mix
    fusion = BACKENDS[backend](np.eye(4), FusionConfig(mode="directions"))
    T, report = fusion.add_step(pose(0.1), np.full(6, 0.05), pose(0.0), mask, hessian)
    assert report.icp_used and np.isfinite(T).all()
