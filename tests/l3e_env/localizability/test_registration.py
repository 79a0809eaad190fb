import numpy as np
import pytest
import small_gicp

from l3e_env.config import LidarConfig
from l3e_env.core.transforms import inverse, matrix_to_pose, pose_to_matrix
from l3e_env.localizability.registration import (
    TO_PROJECT_ORDER,
    PreparedTarget,
    RegistrationConfig,
    RegistrationError,
    dcreg_mask,
    eigen_mask,
    prepare_source,
    register,
    scan_hessian,
)
from l3e_env.sim.lidar import Lidar
from l3e_env.sim.raycast import EmbreeCaster
from scenes import make_scene


def scan_pair(scene_name, pose, delta, seed=0):
    scene = make_scene(scene_name)
    lidar = Lidar(EmbreeCaster(scene.mesh, threads=1), LidarConfig())
    rng = np.random.default_rng(seed)
    T_p = pose_to_matrix(np.array(pose))
    T_p_c = pose_to_matrix(np.array(delta))
    return lidar.scan(T_p, rng).points, lidar.scan(T_p @ T_p_c, rng).points, T_p_c


def test_icp_recovers_a_small_offset_in_a_feature_rich_room():
    target, source, T_true = scan_pair("office", [5, 0, 0.85, 0, 0, 0.3], [0.15, -0.1, 0.05, 0.02, -0.03, 0.1])
    res = register(source, target)
    err = matrix_to_pose(res.T_target_source @ inverse(T_true))
    assert res.converged and res.num_inliers > 500
    assert np.abs(err[:3]).max() < 0.03 and np.abs(err[3:]).max() < np.radians(0.5)


def test_a_target_prepared_on_two_threads_gives_the_same_registration_to_the_bit():
    cfg = RegistrationConfig()
    target, source, _ = scan_pair("office", [5, 0, 0.85, 0, 0, 0.3], [0.1, 0.02, 0.0, 0.0, 0.0, 0.03])
    one, two = register(source, PreparedTarget(target, cfg), cfg), register(source, PreparedTarget(target, cfg, 2), cfg)
    assert one.converged
    assert np.array_equal(one.T_target_source, two.T_target_source) and np.array_equal(one.hessian, two.hessian)


def test_normals_computed_where_matched_give_the_registration_onto_small_gicps_normals():
    """The target's voxels are those of small_gicp's preprocess_points and its normals, computed only
    where a registration matches, are small_gicp's: the same registration as onto its whole cloud's."""
    cfg = RegistrationConfig()
    target, source, _ = scan_pair("tunnel", [50, 0, 0.85, 0, 0, 0], [0.1, 0.05, 0.02, 0.01, -0.01, 0.05])
    lazy = PreparedTarget(target, cfg)
    cloud, _ = small_gicp.preprocess_points(target, cfg.downsampling_resolution, cfg.num_neighbors)
    whole = np.asarray(cloud.points())[:, :3]
    assert np.array_equal(lazy.points, whole)  # preprocess_points' own voxels, part means and all
    result = register(source, lazy, cfg)
    assert 0.05 < lazy._known.mean() < 0.95  # the ground's and the matched voxels' normals only
    eager = PreparedTarget(target, cfg)
    normals = np.asarray(cloud.normals())[:, :3]
    normals[np.abs(whole @ eager.ground[:3] - eager.ground[3]) < 0.05] = eager.ground[:3]
    eager.normals = normals
    expected = register(source, eager, cfg)
    assert result.converged and np.allclose(result.T_target_source, expected.T_target_source, atol=1e-9)
    np.testing.assert_allclose(result.hessian, expected.hessian, rtol=1e-7, atol=1e-7)
    with pytest.raises(ValueError, match="one per voxel"):
        eager.normals = normals[:10]


@pytest.mark.parametrize("ground_normals", [False, True])
def test_hessian_matches_finite_differences_of_the_point_to_plane_cost(ground_normals):
    cfg = RegistrationConfig(ground_normals=ground_normals)
    target, source, _ = scan_pair("office", [5, 0, 0.85, 0, 0, 0.3], [0.05, 0.02, 0.0, 0.0, 0.0, 0.03])
    tgt = PreparedTarget(target, cfg)
    src = prepare_source(source, cfg)
    res = register(src, tgt, cfg)
    # rebuild the final correspondences and differentiate the residuals numerically
    T = res.T_target_source
    p = np.asarray(src.points())[:, :3]
    q, n = tgt.points, tgt.normals  # the normals the registration read
    from scipy.spatial import cKDTree

    d, idx = cKDTree(q).query(p @ T[:3, :3].T + T[:3, 3])
    keep = d < cfg.max_correspondence_distance[-1]
    p, q, n = p[keep], q[idx[keep]], n[idx[keep]]

    def residuals(delta):  # right perturbation in project order (x, y, z, roll, pitch, yaw)
        Tp = T @ pose_to_matrix(delta)
        return np.einsum("ij,ij->i", n, p @ Tp[:3, :3].T + Tp[:3, 3] - q)

    eps = 1e-6
    J = np.column_stack([(residuals(eps * e) - residuals(-eps * e)) / (2 * eps) for e in np.eye(6)])
    H_fd = J.T @ J
    rel = np.linalg.norm(res.hessian - H_fd) / np.linalg.norm(H_fd)
    assert rel < 1e-4, rel
    assert list(TO_PROJECT_ORDER) == [3, 4, 5, 0, 1, 2]


def test_eigenvalue_detector_flags_the_tunnel_axis_only():
    target, source, _ = scan_pair("tunnel", [50, 0, 0.85, 0, 0, 0], [0.0, 0.05, 0.0, 0.0, 0.0, 0.01])
    res = register(source, target)
    w = np.linalg.eigvalsh(res.hessian)
    tau = np.sqrt(w[0] * w[1])  # between the tunnel direction and the rest
    scores, mask = eigen_mask(res.hessian, tau)
    assert mask.tolist() == [True, False, False, False, False, False]
    assert scores[0] > 0.9
    assert not eigen_mask(res.hessian, 0.0)[1].any()
    assert eigen_mask(res.hessian, 1e12)[1].all()


def test_a_single_scan_hessian_is_that_of_registering_the_scan_onto_itself():
    tunnel, _, _ = scan_pair("tunnel", [50, 0, 0.85, 0, 0, 0], [0, 0, 0, 0, 0, 0])
    H = scan_hessian(tunnel)
    assert np.abs(H - register(tunnel, tunnel).hessian).max() < 1e-4 * np.abs(H).max()  # ICP stays at identity
    w, V = np.linalg.eigh(H)
    assert abs(V[0, 0]) > 0.95 and w[1] > 20 * w[0]  # the weakest direction runs along the tunnel (x)
    office, _, _ = scan_pair("office", [5, 0, 0.85, 0, 0, 0.3], [0, 0, 0, 0, 0, 0])
    assert np.linalg.eigvalsh(scan_hessian(office))[0] > 5 * w[0]
    with pytest.raises(RegistrationError, match="points"):
        scan_hessian(tunnel[:20])


def test_bad_scans_raise_clear_errors(capfd):
    target, source, _ = scan_pair("office", [5, 0, 0.85, 0, 0, 0], [0, 0, 0, 0, 0, 0])
    with pytest.raises(RegistrationError, match="NaN"):
        register(np.vstack([source, [[np.nan, 0, 0]]]), target)
    with pytest.raises(RegistrationError, match="minimum"):
        register(source[:20], target)
    with pytest.raises(RegistrationError, match="minimum"):
        register(source, np.zeros((0, 3)))
    with pytest.raises(RegistrationError, match="has 0 points"):
        scan_hessian(np.zeros((0, 3)))
    assert "Empty point cloud" not in capfd.readouterr().err  # refused before small_gicp prints its warning
    with pytest.raises(RegistrationError, match=r"\(N, 3\)"):
        register(source[:, :2], target)
    with pytest.raises(ValueError, match="6x6"):
        eigen_mask(np.eye(5), 1.0)


def test_a_guess_that_is_not_a_rigid_transform_is_refused_and_a_rigid_one_is_followed():
    target, source, T_true = scan_pair("office", [5, 0, 0.85, 0, 0, 0.3], [0.6, -0.2, 0.0, 0.0, 0.0, 0.4])
    sheared = T_true.copy()
    sheared[0, 1] += 1e-3
    with pytest.raises(ValueError, match="not a rigid transform"):
        register(source, target, init_T_target_source=sheared)
    with pytest.raises(ValueError, match="finite 4x4"):
        register(source, target, init_T_target_source=np.full((4, 4), np.nan))
    res = register(source, target, init_T_target_source=T_true @ pose_to_matrix(np.array([0.02, 0.01, 0, 0, 0, 0.01])))
    err = matrix_to_pose(res.T_target_source @ inverse(T_true))
    assert res.converged and np.abs(err[:3]).max() < 0.01 and np.abs(err[3:]).max() < np.radians(0.5)


def test_icp_without_overlap_is_reported_not_converged():
    target, _, _ = scan_pair("office", [5, 0, 0.85, 0, 0, 0], [0, 0, 0, 0, 0, 0])
    far = target + np.array([200.0, 0, 0], dtype=np.float32)
    res = register(far, target)
    assert not res.converged
    assert isinstance(small_gicp.PointCloud(np.zeros((3, 3))), small_gicp.PointCloud)


def test_a_hessian_moves_to_the_body_frame_with_the_mounting():
    """A step's error d in the sensor frame is Ad(T_b_s) d in the body frame: the body-frame Hessian
    gives the same quadratic cost, and the perturbed body step is the body step times exp(Ad d)."""
    import gtsam

    from fusion import to_gtsam_order
    from l3e_env.core.transforms import adjoint
    from l3e_env.localizability.registration import hessian_in_frame

    rng = np.random.default_rng(0)
    T_b_s = pose_to_matrix([0.3, -0.1, 0.85, 0.02, -0.05, 0.4])
    J = rng.normal(size=(50, 6))
    H = J.T @ J
    d_s = 1e-4 * rng.normal(size=6)
    d_b = adjoint(T_b_s) @ d_s
    assert d_s @ H @ d_s == pytest.approx(d_b @ hessian_in_frame(H, T_b_s) @ d_b, rel=1e-9)

    def exp(d):  # project order (translation, rotation) to GTSAM's
        return gtsam.Pose3.Expmap(to_gtsam_order(d)).matrix()

    step = pose_to_matrix([0.1, 0.01, 0.0, 0.0, 0.0, 0.02])
    perturbed = T_b_s @ step @ exp(d_s) @ inverse(T_b_s)
    np.testing.assert_allclose(perturbed, T_b_s @ step @ inverse(T_b_s) @ exp(d_b), atol=1e-9)


def _point_to_plane_hessian(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """sum of J^T J over point-to-plane rows [n, p x n], in project order (x, y, z, roll, pitch, yaw)."""
    J = np.hstack([normals, np.cross(points, normals)])
    return J.T @ J


def _cylinder(rng, radius=2.0, length=20.0, n=4000):  # a round tube along x: x and roll slide
    a, x = rng.uniform(0, 2 * np.pi, n), rng.uniform(-length / 2, length / 2, n)
    normals = np.column_stack([0 * a, np.cos(a), np.sin(a)])
    return np.column_stack([x, radius * normals[:, 1], radius * normals[:, 2]]), -normals


def _plane(rng, n=4000):  # ground only: x, y and yaw slide
    xy = rng.uniform(-15, 15, (n, 2))
    return np.column_stack([xy, np.full(n, -0.85)]), np.tile([0.0, 0.0, 1.0], (n, 1))


def _cube_room(rng, half=4.0, n=6000):  # six walls: nothing slides
    axis, side = rng.integers(0, 3, n), rng.choice([-1.0, 1.0], n)
    points = rng.uniform(-half, half, (n, 3))
    points[np.arange(n), axis] = side * half
    normals = np.zeros((n, 3))
    normals[np.arange(n), axis] = -side
    return points, normals


@pytest.mark.parametrize(
    "surface, expected",
    [
        (_cylinder, [True, False, False, True, False, False]),
        (_plane, [True, True, False, False, False, True]),
        (_cube_room, [False] * 6),
    ],
)
def test_dcreg_flags_the_axes_that_slide_on_surfaces_whose_degeneracy_is_known(surface, expected, rng):
    H = _point_to_plane_hessian(*surface(rng))
    scores, mask = dcreg_mask(H, 10.0)
    assert mask.tolist() == expected
    assert ((scores > 0.5) == mask).all() and ((scores >= 0) & (scores <= 1)).all()
    turned = np.kron(np.eye(2), pose_to_matrix(np.array([0, 0, 0, 0, 0, np.pi / 2]))[:3, :3])  # x -> y
    assert dcreg_mask(turned @ H @ turned.T, 10.0)[1].tolist() == [expected[i] for i in (1, 0, 2, 4, 3, 5)]


def test_dcreg_reads_the_scene_on_a_real_scan_and_refuses_bad_input():
    tunnel, _, _ = scan_pair("tunnel", [50, 0, 0.85, 0, 0, 0], [0, 0, 0, 0, 0, 0])
    mask = dcreg_mask(scan_hessian(tunnel), 10.0)[1]
    assert mask[0] and not mask[1:3].any()  # the tunnel's axis slides, its cross-section holds
    with pytest.raises(ValueError, match="exceed 1"):
        dcreg_mask(np.eye(6), 1.0)
    with pytest.raises(ValueError, match="6x6"):
        dcreg_mask(np.full((6, 6), np.nan), 10.0)


def test_the_eigenvalue_test_means_the_same_on_every_sensor():
    """The scan's Hessian sums at most max_source_points rows (the source's even thinning), so a
    128-beam scan of a place weighs as a VLP-16 scan of it: tau needs no per-sensor scale."""
    mine = make_scene("mine")
    caster = EmbreeCaster(mine.mesh, threads=1)
    for x, flagged in ((-30.0, set()), (60.0, {0})):  # the yard, the smooth tunnel (x degenerate)
        largest = {}
        for model in ("vlp16", "os0-128", "hdl32e"):
            points = (
                Lidar(caster, LidarConfig(model=model))
                .scan(pose_to_matrix(np.array([x, 0.3, 0.85, 0, 0, 0.2])), np.random.default_rng(0))
                .points
            )
            H = scan_hessian(points)
            assert set(np.flatnonzero(eigen_mask(H, 30.0)[1])) == flagged, model
            largest[model] = np.linalg.eigvalsh(H)[-1]
        assert max(largest.values()) < 2 * min(largest.values())  # the same scale (131k rays against 29k)


GROUND = RegistrationConfig()  # the default: the ground plane's normals
PLAIN = RegistrationConfig(ground_normals=False)  # small_gicp's neighbours' normals


def test_the_ground_plane_is_fitted_under_a_tilted_sensor_and_its_voxels_take_its_normal():
    tilt = [0, 0, 0, np.radians(4), np.radians(-3), 0]  # the body rolls and pitches over the floor
    target, _, _ = scan_pair("office", [5, 0, 0.85, *tilt[3:5], 0.3], [0, 0, 0, 0, 0, 0])
    tgt = PreparedTarget(target, GROUND)
    up = pose_to_matrix(np.array([0, 0, 0, *tilt[3:5], 0]))[:3, :3].T @ [0, 0, 1]  # the floor's normal, sensor frame
    assert np.degrees(np.arccos(tgt.ground[:3] @ up)) < 0.3
    assert abs(tgt.ground[3] + 0.85) < 0.03  # the floor lies 0.85 m below the sensor
    on = np.abs(tgt.points @ tgt.ground[:3] - tgt.ground[3]) < 0.05
    assert on.mean() > 0.05 and np.all(tgt.normals[on] == tgt.ground[:3])
    plain = PreparedTarget(target, PLAIN)
    # off the ground, small_gicp's normals (up to their sign, which point-to-plane ICP does not read)
    assert plain.ground is None and np.allclose(np.abs((plain.normals[~on] * tgt.normals[~on]).sum(1)), 1.0)


def test_ground_normals_recover_steps_beside_walls_and_leave_the_tunnel_axis_free():
    """Steps of 0.1 m forward on the fork's pillared route: the ground's leaning normals hold small_gicp's
    registration back; with the plane's normal it reads the step (studies/icp_step_bias.py)."""
    ratios = {}
    for name, cfg in (("default", PLAIN), ("ground", GROUND)):
        steps = []
        for k, x in enumerate((14.0, 20.0, 26.0, 32.0, 38.0, 44.0)):
            target, source, _ = scan_pair("fork", [x, 10, 0.85, 0, 0, 0], [0.1, 0, 0, 0, 0, 0], seed=k)
            res = register(source, target, cfg)
            assert res.converged
            steps.append(matrix_to_pose(res.T_target_source)[0] / 0.1)
        ratios[name] = np.mean(steps)
    assert abs(ratios["ground"] - 1) < 0.03 and ratios["ground"] - 1 > ratios["default"] - 1 + 0.02, ratios
    # in a tunnel the ground's plane normal no longer pins x: the Hessian's x information drops
    target, source, _ = scan_pair("tunnel", [50, 0, 0.85, 0, 0, 0], [0.0, 0.05, 0.0, 0.0, 0.0, 0.01])
    with_plane, without = register(source, target, GROUND), register(source, target, PLAIN)
    assert with_plane.converged and with_plane.hessian[0, 0] < 0.5 * without.hessian[0, 0]
    assert eigen_mask(with_plane.hessian, np.sqrt(np.prod(np.linalg.eigvalsh(with_plane.hessian)[:2])))[1][0]


@pytest.mark.slow
def test_a_round_floor_keeps_its_own_normals():
    """The ground plane's normal on a curved floor would make it flat and hold a round pipe's roll:
    there the plane holds too few of the ground candidates and is not used."""
    target, _, _ = scan_pair("primitives-4", [0, 0, 0.85, 0, 0, 0], [0, 0, 0, 0, 0, 0])
    tgt = PreparedTarget(target, GROUND)
    plain = PreparedTarget(target, PLAIN).normals  # small_gicp's, up to their sign
    assert tgt.ground is None and np.allclose(np.abs((tgt.normals * plain).sum(1)), 1.0)


@pytest.mark.slow
def test_ground_normals_converge_on_an_open_field_where_weakly_held_matches_flip():
    """On the field's route the ground holds nothing sideways: a few far features decide x, y and yaw,
    and their matches can flip from one iteration to the next. The registration must settle (the
    step back uphill is not taken) instead of swinging until it runs out of iterations."""
    from dataclasses import replace

    from l3e_env.experiments.drive import record_run, register_sequence

    rec = record_run("field-0", progress=False)
    # the drive's last 290 steps, where the guard matters: without it most of them run out of iterations
    start = 500
    tail = replace(
        rec, ground_truth=rec.ground_truth[start:], odometry=rec.odometry[start:], scans=rec.scans[start:],
        samples=rec.samples[start:],
    )  # fmt: skip
    regs = register_sequence(tail, GROUND, progress=False)
    converged = [r is not None and r.converged for r in regs]
    assert len(regs) > 250 and np.mean(converged) > 0.97, np.flatnonzero(~np.array(converged))
